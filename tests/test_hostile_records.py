"""Hostile face records, shards and photo names (issue 40): each is refused with a per-record
status naming the record (or file) and the reason, the good ones are estimated or fitted and
written, and nothing is allocated from a record's declared sizes before they are checked.

Shards are written directly with pyarrow from a real synthetic record whose row is altered
(``meta_json`` nested 100,000 deep, a zero-pixel record, grids of 80 M and 20 G texels, arrays
longer than declared, a face_id already seen in another shard).
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
import sys

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from f2l.cli import app
from f2l.io.shards import BadRecord, FaceRecord, iter_records
from f2l.io.record_limits import MAX_GRID_TEXELS, MAX_RECORD_PIXELS, declared_size_problem
from f2l.lighting.grid import LatLongGrid

GRID = LatLongGrid(16, 32)


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """Three real records' rows (16 x 32 grid) and the shard schema."""
    from f2l.synth.dataset import write_synthetic_shards

    src = tmp_path_factory.mktemp("src")
    write_synthetic_shards(src, n=3, seed=7, grid=GRID, image_size=48, overcast_fraction=0.0, progress=False)
    table = pq.read_table(sorted(src.glob("part-*.parquet"))[0])
    return table.to_pylist(), table.schema


def write_shard(folder, rows, schema):
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "part-00000.parquet"
    pq.write_table(pa.Table.from_pylist(rows, schema=schema), path, row_group_size=1)
    return path


def altered(row, face_id, **changes):
    out = dict(row, face_id=face_id)
    out.update(changes)
    return out


def few_pixels(row, n, grid_height, grid_width, visibility_byte=0):
    """``row`` cut to ``n`` pixels on a declared grid, with visibility bytes to match."""
    return dict(num_pixels=n, pixel_rc=row["pixel_rc"][:2 * n], points=row["points"][:3 * n],
                normals=row["normals"][:3 * n], observed_rgb=row["observed_rgb"][:3 * n],
                mask=row["mask"][:n], grid_height=grid_height, grid_width=grid_width,
                visibility_bits=bytes([visibility_byte]) * (n * -(-grid_height * grid_width // 8)))


EMPTY = dict(num_pixels=0, pixel_rc=[], points=[], normals=[], observed_rgb=[], mask=[], visibility_bits=b"")


@pytest.fixture(scope="module")
def hostile_run(base, tmp_path_factory):
    """One estimate over a shard of good and hostile records, and a second shard repeating a face_id."""
    from f2l.estimate.runner import run_estimates

    rows, schema = base
    good0, good1, good2 = rows
    d = tmp_path_factory.mktemp("hostile")
    hostile = [
        good0,
        altered(good1, "hostile-deep", meta_json="[" * 100_000 + "]" * 100_000),
        altered(good1, "hostile-nan", meta_json='{"a": NaN}'),
        altered(good1, "hostile-empty", **EMPTY),
        altered(good1, "hostile-empty-huge", **EMPTY, grid_height=100_000, grid_width=200_000),
        altered(good1, "hostile-grid", **few_pixels(good1, 5, 200_000, 400)),
        altered(good1, "hostile-pixels", num_pixels=MAX_RECORD_PIXELS + 1),
        # declares 5 pixels but holds 20 M floats of points: refused from the footer, not read
        altered(good1, "hostile-long", **dict(few_pixels(good1, 5, 16, 32),
                                              points=np.zeros(20_000_000, np.float32))),
        # declares a 16 x 32 grid but holds 100 MB of visibility
        altered(good1, "hostile-long-vis", **dict(few_pixels(good1, 5, 16, 32),
                                                  visibility_bits=bytes(100_000_000))),
    ]
    shard_a = write_shard(d / "a", hostile, schema)
    shard_b = write_shard(d / "b", [good1], schema)
    shard_c = write_shard(d / "c", [altered(good1, good1["face_id"]), good2], schema)  # good1 again
    out = d / "est"
    summary = run_estimates([d / "a", d / "b", d / "c"], ["sh9"], out, workers=1, threads=1, progress=False)
    table = pq.read_table(out / "estimates.parquet").to_pylist()
    return {"summary": summary, "rows": table, "out": out, "shards": (shard_a, shard_b, shard_c),
            "good": (good0, good1, good2), "dirs": [d / "a", d / "b", d / "c"]}


def by_id(rows, face_id):
    return [r for r in rows if r["face_id"] == face_id]


def test_good_records_are_estimated_and_written(hostile_run):
    rows, out = hostile_run["rows"], hostile_run["out"]
    ok = [r for r in rows if r["status"] == "ok"]
    assert sorted(r["face_id"] for r in ok) == sorted(g["face_id"] for g in hostile_run["good"])
    for r in ok:
        assert (out / r["probe_path"]).is_file() and (out / r["preview_path"]).is_file()
    assert hostile_run["summary"]["ok"] == 3 and hostile_run["summary"]["failed"] == 9


@pytest.mark.parametrize("face_id, reason", [
    ("hostile-deep", "meta_json: nested 100000 levels deep, more than the 32 accepted"),
    ("hostile-nan", "meta_json"),
    ("hostile-empty", "the record has no face pixels (num_pixels = 0)"),
    ("hostile-empty-huge", "200000 lighting grid"),
    ("hostile-grid", f"200000x400 lighting grid = 80000000 texels, more than the {MAX_GRID_TEXELS}"),
    ("hostile-pixels", f"more than the {MAX_RECORD_PIXELS} accepted (F2L_MAX_RECORD_PIXELS)"),
    ("hostile-long", "column 'points' holds 20000000 values, more than the 15 its records declare"),
    ("hostile-long-vis", "bytes uncompressed, more than its records' declared sizes"),
])
def test_a_hostile_record_gets_its_own_status_naming_shard_record_and_reason(hostile_run, face_id, reason):
    (row,) = by_id(hostile_run["rows"], face_id)
    assert row["status"] == "bad_record" and row["probe_path"] is None
    shard_a = str(hostile_run["shards"][0])
    assert shard_a in row["message"] and repr(face_id) in row["message"] and reason in row["message"]
    assert "model" not in row["message"]  # the record's fault, not the model's


def test_a_duplicate_face_id_is_estimated_once_and_named(hostile_run):
    _, shard_b, shard_c = hostile_run["shards"]
    face_id = hostile_run["good"][1]["face_id"]
    first, dup = by_id(hostile_run["rows"], face_id)  # the first one sorts first
    assert first["status"] == "ok" and first["source_path"] == hostile_run["good"][1]["source_path"]
    assert dup["status"] == "duplicate_face_id" and dup["probe_path"] is None
    assert dup["source_path"] == str(shard_c)
    assert f"duplicate face_id (first in {shard_b})" in dup["message"]
    probes = sorted((hostile_run["out"] / "probes" / "sh9").glob("*.exr"))
    assert len(probes) == 3  # one per distinct good face


def test_a_rerun_keeps_the_first_and_reports_the_duplicate_again(hostile_run):
    from f2l.estimate.runner import run_estimates

    out = hostile_run["out"]
    summary = run_estimates(hostile_run["dirs"], ["sh9"], out, workers=1, threads=1, progress=False)
    assert summary["skipped_done"] == 3 and summary["ok"] == 0
    rows = pq.read_table(out / "estimates.parquet").to_pylist()
    assert sorted((r["face_id"], r["status"]) for r in rows) == sorted(
        (r["face_id"], r["status"]) for r in hostile_run["rows"])


def test_iter_records_refuses_without_raising(hostile_run):
    got = {r.face_id: r for r in iter_records(hostile_run["shards"][0])}
    assert isinstance(got[hostile_run["good"][0]["face_id"]], FaceRecord)
    assert isinstance(got["hostile-deep"], BadRecord) and "nested" in got["hostile-deep"].reason
    assert isinstance(got["hostile-grid"], BadRecord)
    assert isinstance(got["hostile-empty"], FaceRecord)  # a shard may store it; estimate refuses it


def test_declared_size_limits_and_their_env_vars(monkeypatch):
    assert declared_size_problem(10_000, 64, 128) is None
    assert declared_size_problem(100_000, 512, 1024) is None  # research-size grids pass
    assert "no face pixels" in declared_size_problem(0, 64, 128, min_pixels=1)
    assert "F2L_MAX_GRID_TEXELS" in declared_size_problem(10, 2048, 1024)
    monkeypatch.setenv("F2L_MAX_GRID_TEXELS", str(4096 * 4096))
    assert declared_size_problem(10, 2048, 1024) is None
    monkeypatch.setenv("F2L_MAX_RECORD_PIXELS", "100")
    assert "F2L_MAX_RECORD_PIXELS" in declared_size_problem(101, 64, 128)
    assert "not an integer" in declared_size_problem(None, 64, 128)


def test_an_empty_record_in_memory_is_refused_before_the_model_loads(base, monkeypatch):
    from f2l.estimate import record as record_mod
    from f2l.estimate.config import EstimatorConfig

    rows, _ = base
    rec = FaceRecord.from_row(altered(rows[0], "mem-empty", **EMPTY))
    rec.grid_height, rec.grid_width = 100_000, 200_000  # built in memory: never read from a shard

    def no_model(*a, **k):
        raise AssertionError("the model must not load for a refused record")

    monkeypatch.setattr(record_mod, "_get_model", no_model)
    row = record_mod.estimate_record(rec, "sh9", "/nonexistent", EstimatorConfig(threads=1))
    assert row["status"] == "bad_record" and row["message"].startswith("mem-empty: ")
    assert "no face pixels" in row["message"]


_LIMITED = """
import resource, sys
resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))
from f2l.cli import app
sys.argv = ["f2l", *sys.argv[1:]]
app()
"""


def test_oversized_grid_is_refused_under_a_2_gib_address_space_limit(base, tmp_path):
    """The 80 M-texel record (50 MB of visibility, a 2.4 MB file) next to a good one, estimated by
    the CLI in a process limited to 2 GiB of address space: the good one ok, the big one refused."""
    rows, schema = base
    write_shard(tmp_path / "s", [rows[0], altered(rows[1], "big-grid", **few_pixels(rows[1], 5, 200_000, 400, 0xFF))],
                schema)
    # Arrow's default allocator (mimalloc) reserves ~1.3 GB of address space up front, memory it
    # never touches; the system allocator keeps the limit about what is used
    env = dict(os.environ, ARROW_DEFAULT_MEMORY_POOL="system")
    proc = subprocess.run([sys.executable, "-c", _LIMITED, "estimate", str(tmp_path / "s"), "-m", "sh9",
                           "--out", str(tmp_path / "est"), "--json", "--workers", "1"],
                          capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 4, proc.stderr[-3000:]  # 4: the big record failed, the good one written
    assert "Traceback" not in proc.stderr
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert summary["ok"] == 1 and summary["failed"] == 1
    table = {r["face_id"]: r for r in pq.read_table(tmp_path / "est" / "estimates.parquet").to_pylist()}
    assert table[rows[0]["face_id"]]["status"] == "ok"
    bad = table["big-grid"]
    assert bad["status"] == "bad_record" and "'big-grid'" in bad["message"]
    assert "200000x400 lighting grid" in bad["message"] and "F2L_MAX_GRID_TEXELS" in bad["message"]


# --- exit codes ---------------------------------------------------------------------------------

def test_estimate_exits_4_when_some_records_failed_and_1_when_none_could_be_done(hostile_run, base, tmp_path):
    res = invoke("estimate", hostile_run["dirs"][0], "-m", "sh9", "--out", tmp_path / "mixed", "--json",
                 "--workers", "1")
    assert res.exit_code == 4, res.output  # 4: some failed, the rest written
    assert json.loads(res.stdout.strip().splitlines()[-1])["failed"] == 8
    rows, schema = base
    write_shard(tmp_path / "bad", [altered(rows[0], "only-deep", meta_json="[" * 1000 + "]" * 1000)], schema)
    res = invoke("estimate", tmp_path / "bad", "-m", "sh9", "--out", tmp_path / "none", "--json", "--workers", "1")
    assert res.exit_code == 1, res.output
    (row,) = pq.read_table(tmp_path / "none" / "estimates.parquet").to_pylist()  # written all the same
    assert row["status"] == "bad_record" and "only-deep" in row["message"]


# --- a photo whose file name is not valid UTF-8 -------------------------------------------------

BAD_NAME = b"\xff\xfe.png"


@pytest.fixture(scope="module")
def odd_names(tmp_path_factory):
    skdata = pytest.importorskip("skimage.data")
    from PIL import Image

    d = tmp_path_factory.mktemp("odd_names")
    Image.fromarray(skdata.astronaut()).save(d / "astronaut.png")
    with open(os.fsencode(str(d)) + b"/" + BAD_NAME, "wb") as f:
        f.write((d / "astronaut.png").read_bytes())
    return d


def test_fit_faces_fits_a_photo_with_a_non_utf8_name_under_an_escaped_name(odd_names, tmp_path):
    res = invoke("fit-faces", odd_names, "--out", tmp_path, "--grid", "16x32", "--no-overlays", "--json")
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["photos"] == 2 and summary["status"]["ok"] == 2 and summary["records"] == 2
    status = {r["source_path"]: r for r in pq.read_table(tmp_path / "status" / "fit_faces.parquet").to_pylist()}
    escaped = os.path.join(str(odd_names), "\\xff\\xfe.png")
    assert set(status) == {str(odd_names / "astronaut.png"), escaped}
    assert "not valid UTF-8" in status[escaped]["message"] and status[escaped]["message"].startswith(escaped)
    records = {r.source_path: r for r in iter_records(tmp_path)}
    assert set(records) == set(status) and all(isinstance(r, FaceRecord) for r in records.values())
    assert records[escaped].face_id in status[escaped]["face_ids"]


def test_estimate_on_photos_refuses_a_non_utf8_name_and_estimates_the_others(odd_names, tmp_path):
    res = invoke("estimate", odd_names, "-m", "sh9", "--out", tmp_path / "est", "--json", "--workers", "1")
    assert res.exit_code == 4, res.output  # 4: one photo refused, the rest written
    summary = json.loads(res.stdout)
    assert summary["ok"] == 1
    (bad,) = summary["photos"]["not_ok"]
    assert bad["status"] == "error" and bad["source_path"].endswith("\\xff\\xfe.png")
    assert "not valid UTF-8" in bad["message"] and "\\xff\\xfe.png" in bad["message"]
    (row,) = pq.read_table(tmp_path / "est" / "estimates.parquet").to_pylist()
    assert row["status"] == "ok" and row["face_id"].startswith("astronaut-")
