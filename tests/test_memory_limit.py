"""Every batch command under a 2 GiB address-space limit (issue 40), on inputs whose headers claim far
more than that: an EXR probe of 100000 x 50000 px, a PNG photo of 30000 x 30000 px, a record on a
200000 x 400 lighting grid and an empty one on 100000 x 200000. Each command must finish: the
oversized input refused with a reason that names it, the small good inputs beside it done, and the
exit code 4 (some inputs failed, the rest written). Each command runs in its own process that sets
the limit before importing anything (``f2l`` then picks allocators that reserve only what they use:
``f2l/__init__.py``)."""

from __future__ import annotations

import json
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from PIL import Image

LIMIT_BYTES = 2 * 2**30


def _huge_header_exr(path: Path, width: int = 100000, height: int = 50000) -> None:
    """A small valid EXR whose dataWindow is patched to claim ``width`` x ``height``."""
    from f2l.io.exr import write_exr

    write_exr(path, np.ones((32, 64, 3), np.float32))
    data = bytearray(path.read_bytes())
    at = data.find(b"dataWindow\0box2i\0") + len(b"dataWindow\0box2i\0") + 4
    data[at:at + 16] = struct.pack("<4i", 0, 0, width - 1, height - 1)
    path.write_bytes(bytes(data))


def _huge_header_png(path: Path, side: int = 30000) -> None:
    """A small PNG whose IHDR claims ``side`` x ``side`` pixels (CRC recomputed)."""
    Image.fromarray(np.full((16, 16, 3), 128, np.uint8)).save(path)
    data = bytearray(path.read_bytes())
    assert data[12:16] == b"IHDR"
    data[16:24] = struct.pack(">II", side, side)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])) & 0xFFFFFFFF)
    path.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    import skimage.data

    from f2l.io.exr import write_exr
    from f2l.lighting.grid import LatLongGrid
    from f2l.synth.dataset import write_synthetic_shards
    from tests.test_build_dataset import SESSION_TOML, _bracket, _sky

    base = tmp_path_factory.mktemp("memory")
    tree = base / "tree"
    _bracket(tree / "site" / "sky", seed=3)
    (tree / "site" / "session.toml").write_text(SESSION_TOML)
    faces = tree / "site" / "faces"
    faces.mkdir(parents=True)
    Image.fromarray(skimage.data.astronaut()).crop((64, 0, 384, 320)).resize((256, 256)).save(faces / "a.png")
    _huge_header_png(faces / "huge.png")
    (tree / "park" / "probes").mkdir(parents=True)
    _huge_header_exr(tree / "park" / "probes" / "given.exr")
    Image.fromarray(skimage.data.astronaut()).resize((256, 256)).save(tree / "park" / "c.png")

    probes = base / "probes"
    probes.mkdir()
    write_exr(probes / "sky.exr", _sky(16, 40.0, 10.0, 128.0))
    _huge_header_exr(probes / "huge.exr")

    grid = LatLongGrid(8, 16)
    src = base / "src"
    write_synthetic_shards(src, n=1, seed=7, grid=grid, image_size=48, overcast_fraction=0.0, progress=False)
    table = pq.read_table(sorted(src.glob("part-*.parquet"))[0])
    good = table.to_pylist()[0]
    big = dict(good, face_id="big-grid", grid_height=200000, grid_width=400)
    empty = dict(good, face_id="empty-huge-grid", num_pixels=0, pixel_rc=[], points=[], normals=[],
                 observed_rgb=[], mask=[], visibility_bits=b"", grid_height=100000, grid_width=200000)
    shards = base / "shards"
    shards.mkdir()
    pq.write_table(pa.Table.from_pylist([good, big, empty], schema=table.schema), shards / "part-00000.parquet",
                   row_group_size=1)
    return {"base": base, "tree": tree, "probes": probes, "shards": shards}


SCRIPT = """
import json, resource, sys
resource.setrlimit(resource.RLIMIT_AS, ({limit}, {limit}))
from typer.testing import CliRunner
from f2l.cli import app
res = CliRunner().invoke(app, json.loads(sys.argv[1]) + ["--json"])
print(json.dumps({{"exit_code": res.exit_code, "stdout": res.stdout[-20000:], "output": res.output[-3000:],
                  "exception": None if res.exception is None or isinstance(res.exception, SystemExit)
                  else repr(res.exception)}}))
"""


@pytest.fixture(scope="module")
def limited(inputs):
    b, tree = inputs["base"], inputs["tree"]
    commands = [
        ("ingest", ["ingest", str(tree), "--work", str(b / "work"), "--no-detect-roles"]),
        ("make-probes", ["make-probes", str(tree), "--work", str(b / "work"), "--probe-height", "16"]),
        ("fit-faces", ["fit-faces", str(tree / "site" / "faces"), "--out", str(b / "fitted"), "--grid", "8x16"]),
        ("estimate", ["estimate", str(inputs["shards"]), "-m", "sh9", "--out", str(b / "est"), "--workers", "1"]),
        ("fit-probe", ["eval", "fit-probe", str(inputs["probes"]), "-m", "sh9", "--grid", "16x32", "--out", str(b / "fp")]),
        ("build-dataset", ["build-dataset", str(tree), "--work", str(b / "bwork"), "--out", str(b / "bout")]),
    ]
    results = {}
    for name, args in commands:  # one process per command, as a user runs them
        proc = subprocess.run([sys.executable, "-c", SCRIPT.format(limit=LIMIT_BYTES), json.dumps(args)],
                              capture_output=True, text=True, timeout=600, cwd=Path(__file__).resolve().parents[1])
        assert proc.returncode == 0, (name, proc.stderr[-3000:])
        results[name] = r = json.loads(proc.stdout.strip().splitlines()[-1])
        assert r["exception"] is None, (name, r["exception"])
        assert r["stdout"].strip(), (name, r)
        r["summary"] = json.loads(r["stdout"].strip().splitlines()[-1])
    return results


def test_every_command_finishes_under_the_limit_with_some_failed(limited):
    assert {name: r["exit_code"] for name, r in limited.items()} == {
        "ingest": 4, "make-probes": 4, "fit-faces": 4, "estimate": 4, "fit-probe": 4, "build-dataset": 4}


def test_make_probes_refuses_the_huge_given_probe_and_assembles_the_sky(limited, inputs):
    rows = pq.read_table(inputs["base"] / "work" / "probes.parquet").to_pylist()
    given = [r for r in rows if r["kind"] == "given"]
    assert len(given) == 1 and given[0]["status"] == "error"
    assert "given.exr" in given[0]["message"] and "100000x50000" in given[0]["message"]
    assert [r["status"] for r in rows if r["kind"] == "probe" and r["session"] == "site"] == ["ok"]


def test_fit_faces_refuses_the_huge_photo_from_its_header_and_fits_the_other(limited, inputs):
    rows = {Path(r["source_path"]).name: r
            for r in pq.read_table(inputs["base"] / "fitted" / "status" / "fit_faces.parquet").to_pylist()}
    assert rows["huge.png"]["status"] == "error" and "30000x30000" in rows["huge.png"]["message"]
    assert rows["a.png"]["status"] == "ok"


def test_estimate_refuses_the_oversized_and_the_empty_record_and_estimates_the_good_one(limited, inputs):
    rows = {r["face_id"]: r for r in pq.read_table(inputs["base"] / "est" / "estimates.parquet").to_pylist()}
    assert rows["big-grid"]["status"] != "ok" and "200000x400" in rows["big-grid"]["message"]
    assert rows["empty-huge-grid"]["status"] != "ok" and "empty-huge-grid" in rows["empty-huge-grid"]["message"]
    assert [r["status"] for k, r in rows.items() if k not in ("big-grid", "empty-huge-grid")] == ["ok"]


def test_fit_probe_refuses_the_huge_probe_and_fits_the_sky(limited):
    s = limited["fit-probe"]["summary"]
    assert s["ok"] == 1 and s["errors"] == 1


def test_build_dataset_leaves_out_the_huge_inputs_and_builds_the_rest(limited):
    s = limited["build-dataset"]["summary"]
    assert s["counts"]["records"] >= 1
    failed = " ".join(f"{f['path']} {f['reason']}" for f in s["failed"])
    assert "huge.png" in failed and "given.exr" in failed


def test_ingest_reads_headers_only_and_names_the_huge_photo(limited, inputs):
    rows = {r["path"]: r for r in pq.read_table(inputs["base"] / "work" / "captures.parquet").to_pylist()}
    assert rows["site/faces/huge.png"]["status"] == "error" and "huge.png" in rows["site/faces/huge.png"]["message"]
    assert rows["park/probes/given.exr"]["status"] == "ok"  # its header is read; make-probes refuses its size
    assert all(r["status"] == "ok" for p, r in rows.items() if p != "site/faces/huge.png")
