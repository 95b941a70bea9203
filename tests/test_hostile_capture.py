"""Issue 40, capture side: hostile session.toml values and paths, and file names, at ingest time.

One capture tree (module scope) holds a good session next to one bad session per case; the real
``f2l ingest`` runs over it once. Each test checks: no traceback, ingest's exit code (0: bad input
is reported per session and per row, it never stops the ingest), the good session ingested as
before, and a message naming the file and the key.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from f2l.cli import app
from tests.test_build_dataset import SESSION_TOML, _bracket

LENS_LINE = "fov_deg = 180.0"
BAD_NAME = b"\xff\xfe.png"


def _falloff(file: str) -> str:
    return SESSION_TOML.replace(LENS_LINE, f'{LENS_LINE}\nfalloff = {{model = "flat_field", file = "{file}"}}')


def _session(root: Path, name: str, toml: str, seed: int = 3) -> None:
    _bracket(root / name / "sky", seed=seed)
    (root / name / "session.toml").write_text(toml)


def _flat(path: Path) -> None:
    from f2l.io.exr import write_exr

    path.parent.mkdir(parents=True, exist_ok=True)
    write_exr(path, np.ones((96, 96, 3), np.float32))


def _ingest(root: Path, work: Path, *extra: str):
    res = CliRunner().invoke(app, ["ingest", str(root), "--work", str(work), "--no-detect-roles", *extra])
    assert res.exception is None or isinstance(res.exception, SystemExit), res.output
    assert "Traceback" not in res.output
    return res


def _rows(work: Path) -> dict[str, dict]:
    return {r["path"]: r for r in pq.read_table(work / "captures.parquet").to_pylist()}


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    base = tmp_path_factory.mktemp("hostile")
    root = base / "raw"
    _session(root, "good", SESSION_TOML)
    # case 1: non-finite numbers and absurd nesting
    _session(root, "nan", SESSION_TOML.replace("pitch_deg = 90.0", "pitch_deg = nan"))
    _session(root, "inf", SESSION_TOML.replace("probe_azimuth_deg = 90.0", "probe_azimuth_deg = inf"))
    (root / "deep").mkdir()
    (root / "deep" / "session.toml").write_text("a = " + "{b = " * 1000 + "1" + "}" * 1000 + "\n")
    _bracket(root / "deep" / "sky", seed=3)
    # case 2: lens values that cannot place a view
    _session(root, "huge", SESSION_TOML.replace(LENS_LINE, "focal_length_px = 1e308"))
    _session(root, "tiny", SESSION_TOML.replace(LENS_LINE, "focal_length_mm = 1e-308\nsensor_width_mm = 36.0"))
    _session(root, "pp", SESSION_TOML.replace(LENS_LINE, f"{LENS_LINE}\nprincipal_point_px = [1e6, -1e6]"))
    # case 3: a glob that matches nothing
    _session(root, "glob", SESSION_TOML.replace('files = "sky/*"', 'files = "nothing/*"'))
    # case 4: paths out of the session folder
    outside = base / "outside"
    _flat(outside / "flat.exr")
    _session(root, "dotdot", _falloff("../../../../etc/passwd"))
    _session(root, "abs", _falloff(str(outside / "flat.exr")))
    _session(root, "link", _falloff("cal/flat.exr"))
    os.symlink(outside, root / "link" / "cal")
    _session(root, "inside", _falloff("cal/../cal/flat.exr"))
    _flat(root / "inside" / "cal" / "flat.exr")
    # case 5: the flat field itself, truncated
    _session(root, "flat", _falloff("flat.exr"))
    _flat(root / "flat" / "flat.exr")
    data = (root / "flat" / "flat.exr").read_bytes()
    (root / "flat" / "flat.exr").write_bytes(data[: len(data) // 2])
    # case 6: file names that are not UTF-8
    _session(root, "utf8", SESSION_TOML)
    (root / "utf8" / "faces").mkdir()
    with open(os.fsencode(root / "utf8" / "faces") + b"/" + BAD_NAME, "wb") as fh:
        fh.write(b"not an image")
    res = _ingest(root, base / "work", "--json")
    return {"root": root, "work": base / "work", "base": base, "outside": outside, "res": res,
            "summary": json.loads(res.stdout), "rows": _rows(base / "work")}


def _session_rows(tree, session: str) -> list[dict]:
    return [r for p, r in tree["rows"].items() if p.startswith(session + "/")]


def _good_is_fine(tree) -> None:
    good = _session_rows(tree, "good")
    assert len(good) == 3 and all(r["status"] == "ok" and r["bracket_id"] == "good/frame_00" for r in good)
    assert json.loads(good[0]["view_json"])["pitch_deg"] == 90.0


def _refused(tree, session: str, *needles: str) -> list[dict]:
    """The session's 3 frames: ``error`` rows outside any bracket, naming its session.toml and
    every needle."""
    rows = _session_rows(tree, session)
    assert len(rows) == 3
    for r in rows:
        assert r["status"] == "error" and r["bracket_id"] is None, r
        for needle in (str(tree["root"] / session / "session.toml"), *needles):
            assert needle in r["message"], r["message"]
    return rows


def test_ingest_exit_code_and_good_session(tree):
    assert tree["res"].exit_code == 4  # bad input is reported (exit 4: some failed), never stops the ingest
    _good_is_fine(tree)
    assert tree["summary"]["sessions"] == 14


def test_non_finite_and_deep_session_toml_is_a_session_problem(tree):
    problems = tree["summary"]["session_problems"]
    for session, key in (("nan", "shots/0/pitch_deg"), ("inf", "probe_azimuth_deg"), ("deep", "nested deeper")):
        line = next(p for p in problems if p.startswith(f"session {session}:"))
        assert str(tree["root"] / session / "session.toml") in line and key in line, line
        rows = _session_rows(tree, session)
        assert rows and all(key in r["session_problem"] for r in rows)
        # ingested without its TOML: no NaN reaches the rows' views
        assert all("NaN" not in r["view_json"] and "Infinity" not in r["view_json"] for r in rows)


def test_implausible_lens_is_a_row_error_at_ingest(tree):
    for session, key in (("huge", "lens/focal_length_px"), ("tiny", "lens/focal_length_mm"),
                         ("pp", "lens/principal_point_px")):
        _refused(tree, session, key)
        assert any(w.startswith(f"session {session}:") and key in w for w in tree["summary"]["warnings"])
    ids = {b["bracket_id"] for b in tree["summary"]["bracket_list"]}
    assert not ids & {"huge/frame_00", "tiny/frame_00", "pp/frame_00"}


def test_lens_plausibility_ranges():
    from f2l.capture.lens import LensError, lens_from_view

    fisheye = {"projection": "equidistant", "fov_deg": 180.0}
    assert lens_from_view(fisheye, 96, 96).params[0] == pytest.approx(48 / (np.pi / 2))
    for bad, key in (({"focal_length_px": 1e308}, "focal_length_px"), ({"focal_length_px": 1e-308}, "focal_length_px"),
                     ({"fov_deg": 1e-300}, "fov_deg"), ({"principal_point_px": [48.0, 1e6]}, "principal_point_px"),
                     ({"image_circle_radius_px": 1e9}, "image_circle_radius_px"),
                     ({"focal_length_mm": 8.0, "sensor_width_mm": 1e9}, "sensor_width_mm")):
        with pytest.raises(LensError) as err:
            lens_from_view({**fisheye, **bad}, 96, 96)
        assert err.value.key == key and key in str(err.value)
    with pytest.raises(LensError, match="colmap_params"):
        lens_from_view({"colmap_model": "PINHOLE", "colmap_params": [1e308, 1e308, 48, 48]}, 96, 96)
    # a shifted principal point within the margin is accepted
    lens_from_view({**fisheye, "principal_point_px": [-20.0, 130.0]}, 96, 96)


def test_glob_matching_nothing_is_a_warning(tree):
    line = next(w for w in tree["summary"]["warnings"] if w.startswith("session glob:"))
    assert str(tree["root"] / "glob" / "session.toml") in line and "shots/0/files" in line and "nothing/*" in line
    assert all(r["status"] == "ok" for r in _session_rows(tree, "glob"))  # frames kept, no orientation
    res = _ingest(tree["root"], tree["work"])  # the text summary prints it (all rows reused)
    assert "nothing/*" in res.stderr and "f2l: warning:" in res.stderr


def test_paths_out_of_the_session_are_refused(tree):
    for session, why in (("dotdot", "leaves the session folder"), ("abs", "absolute path"),
                         ("link", "symbolic link")):
        for r in _refused(tree, session, "lens/falloff/file", why, "--allow-outside"):
            assert "sha256" not in json.loads(r["view_json"])["falloff"]  # never opened
    # a path that stays inside (even through "..") is recorded relative to the root, with its hash
    inside = _session_rows(tree, "inside")
    frames = [r for r in inside if r["path"].endswith(".dng")]
    assert all(r["status"] == "ok" and r["bracket_id"] for r in frames)
    falloff = json.loads(frames[0]["view_json"])["falloff"]
    assert falloff["file"] == "inside/cal/flat.exr" and len(falloff["sha256"]) == 64
    assert "allow_outside" not in falloff


def test_allow_outside_lets_the_merge_read_it(tree, tmp_path):
    root = tmp_path / "raw"
    _session(root, "good", SESSION_TOML)
    _session(root, "abs", _falloff(str(tree["outside"] / "flat.exr")))
    work = tmp_path / "work"
    refused = _ingest(root, work, "--json")
    assert json.loads(refused.stdout)["brackets"] == 1
    allowed = _ingest(root, work, "--json", "--allow-outside")
    assert allowed.exit_code == 0 and json.loads(allowed.stdout)["brackets"] == 2
    res = CliRunner().invoke(app, ["make-probes", str(root), "--work", str(work), "--json"])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["views"] == 2 and summary["errors"] == 0


def test_merge_rechecks_the_flat_field_path(tmp_path):
    from f2l.capture.lens import LensError, lens_from_view

    root = tmp_path / "raw"
    _flat(root / "s" / "flat.exr")
    _flat(tmp_path / "out" / "flat.exr")
    os.symlink(tmp_path / "out", root / "s" / "cal")
    base = {"projection": "rectilinear", "fov_deg": 70.0}
    ok = lens_from_view({**base, "falloff": {"model": "flat_field", "file": "s/flat.exr"}}, 96, 96)
    assert ok.gain(ok.view_camera(96, 96), root=root) is not None
    for file, why in (("../out/flat.exr", "leaves"), (str(tmp_path / "out" / "flat.exr"), "absolute"),
                      ("s/cal/flat.exr", "symbolic link")):
        lens = lens_from_view({**base, "falloff": {"model": "flat_field", "file": file}}, 96, 96)
        with pytest.raises(LensError, match=why):
            lens.gain(lens.view_camera(96, 96), root=root)
    allowed = lens_from_view({**base, "falloff": {"model": "flat_field", "file": str(tmp_path / "out" / "flat.exr"),
                                                  "allow_outside": True}}, 96, 96)
    assert allowed.gain(allowed.view_camera(96, 96), root=root) is not None


def test_named_flat_field_is_not_a_probe(tree):
    flat = tree["rows"]["flat/flat.exr"]
    assert flat["role"] == "other" and flat["role_source"] == "toml"
    assert not [r for r in tree["rows"].values() if r["role"] == "probe"]
    # the frames that use it are bracketed as usual (the truncation shows at the merge)
    frames = [r for r in _session_rows(tree, "flat") if r["path"].endswith(".dng")]
    assert all(r["status"] == "ok" and r["bracket_id"] == "flat/frame_00" for r in frames)


def test_non_utf8_file_name_is_an_error_row(tree):
    shown = "utf8/faces/\\xff\\xfe.png"
    row = tree["rows"][shown]
    assert row["status"] == "error" and "not valid UTF-8" in row["message"] and "\\xff\\xfe.png" in row["message"]
    assert row["sha256"] == ""
    rows = _session_rows(tree, "utf8")
    assert sum(r["status"] == "ok" for r in rows) == 3  # the session's bracket is ingested
    # build-dataset runs past it and names the file
    res = CliRunner().invoke(app, ["build-dataset", str(tree["root"]), "--work", str(tree["base"] / "bw"),
                                   "--out", str(tree["base"] / "out"), "--json"])
    assert res.exit_code != 2 and "Traceback" not in res.output
    assert "\\\\xff\\\\xfe.png" in res.stdout  # JSON-escaped backslashes


# -- capture files that are symbolic links out of the tree ----------------------------------------
def _png(path: Path, seed: int = 0) -> None:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.random.default_rng(seed).integers(0, 255, (32, 32, 3), np.uint8)).save(path)


@pytest.fixture
def linked(tmp_path):
    """A tree whose ``s/faces/out.png`` links out of it, ``s/faces/in.png`` to a file inside it,
    ``s/faces/loop_a.png`` and ``loop_b.png`` to each other, ``s/elsewhere`` to a folder out of it
    and ``s/again`` to its own session folder (a loop)."""
    root, outside = tmp_path / "raw", tmp_path / "outside"
    _session(root, "good", SESSION_TOML)
    _png(outside / "out.png", 1)
    _png(outside / "folder" / "hidden.png", 2)
    _png(root / "shared" / "real.png", 3)
    faces = root / "s" / "faces"
    faces.mkdir(parents=True)
    os.symlink(outside / "out.png", faces / "out.png")
    os.symlink(root / "shared" / "real.png", faces / "in.png")
    os.symlink(faces / "loop_b.png", faces / "loop_a.png")
    os.symlink(faces / "loop_a.png", faces / "loop_b.png")
    os.symlink(outside / "folder", root / "s" / "elsewhere")
    os.symlink(root / "s", root / "s" / "again")
    return root, outside, tmp_path / "work"


def test_symlink_out_of_the_tree_is_refused(linked):
    root, outside, work = linked
    res = _ingest(root, work, "--json")
    assert res.exit_code == 4, res.output  # some files failed, the rest ingested
    rows = _rows(work)
    out = rows["s/faces/out.png"]
    assert out["status"] == "error" and out["sha256"] == "", out
    assert "symlink points outside the capture tree" in out["message"]
    assert str(root / "s" / "faces" / "out.png") in out["message"] and str(outside / "out.png") in out["message"]
    assert rows["s/faces/in.png"]["status"] == "ok" and rows["s/faces/in.png"]["sha256"]  # a link within the tree
    for name in ("loop_a.png", "loop_b.png"):  # a link loop cannot be stat'ed: an error row, no hang
        assert rows[f"s/faces/{name}"]["status"] == "error" and "cannot be read" in rows[f"s/faces/{name}"]["message"]
    # folder links are never walked: nothing under s/elsewhere (out) or s/again (a loop)
    assert not [p for p in rows if p.startswith(("s/elsewhere/", "s/again/"))], sorted(rows)
    warning = next(w for w in json.loads(res.stdout)["warnings"] if "s/elsewhere" in w)
    assert str(outside / "folder") in warning and "not scanned" in warning
    assert not [w for w in json.loads(res.stdout)["warnings"] if "s/again" in w]  # inside: no warning
    _good = [r for p, r in rows.items() if p.startswith("good/")]
    assert len(_good) == 3 and all(r["status"] == "ok" and r["bracket_id"] for r in _good)


def test_allow_outside_reads_the_link_and_shares_no_row(linked):
    root, outside, work = linked
    _ingest(root, work, "--json")  # refused first: the row must not be reused as it is
    res = _ingest(root, work, "--json", "--allow-outside")
    out = _rows(work)["s/faces/out.png"]
    assert out["status"] == "ok" and out["sha256"] and out["width"] == 32, out
    assert json.loads(res.stdout)["by_status"]["error"] == 2  # the two loop links only
    again = _ingest(root, work, "--json")  # and refused again without it
    assert _rows(work)["s/faces/out.png"]["status"] == "error" and again.exit_code == 4


def test_build_dataset_allow_outside(tmp_path):
    """build-dataset refuses a session whose flat field is an absolute path (its frames are failed
    inputs: exit 4, the other session built) and uses it with --allow-outside."""
    import skimage.data
    from PIL import Image

    from tests.test_build_dataset import PIPELINE

    root = tmp_path / "raw"
    _flat(tmp_path / "outside" / "flat.exr")
    _session(root, "good", SESSION_TOML)
    _session(root, "abs", _falloff(str(tmp_path / "outside" / "flat.exr")))
    face = Image.fromarray(skimage.data.astronaut()).crop((64, 0, 384, 320)).resize((256, 256), Image.Resampling.LANCZOS)
    for s in ("good", "abs"):
        (root / s / "faces").mkdir()
        face.save(root / s / "faces" / f"{s}.png")
    (tmp_path / "pipeline.toml").write_text(PIPELINE)

    def build(*extra: str):
        res = CliRunner().invoke(app, ["build-dataset", str(root), "--work", str(tmp_path / "work"), "--out",
                                       str(tmp_path / "out"), "--pipeline", str(tmp_path / "pipeline.toml"),
                                       "--json", *extra])
        assert "Traceback" not in res.output
        return res, json.loads(res.stdout), json.loads((tmp_path / "out" / "dataset_card.json").read_text())

    res, summary, card = build()
    assert res.exit_code == 4, res.output
    refused = [f for f in summary["failed"] if f["path"].startswith("abs/sky/")]
    assert len(refused) == 3 and all("absolute path" in f["reason"] and "--allow-outside" in f["reason"]
                                     for f in refused), summary["failed"]
    assert {s["name"]: s["probe"] is not None for s in card["sessions"]} == {"abs": False, "good": True}
    assert card["pipeline"]["stages"][0]["allow_outside"] is False
    res, summary, card = build("--allow-outside")
    assert res.exit_code == 0, res.output
    assert summary["failed"] == [] and summary["stages"]["merge"]["computed"] == 1  # only abs's bracket
    assert {s["name"]: s["probe"] is not None for s in card["sessions"]} == {"abs": True, "good": True}
    assert card["pipeline"]["stages"][0]["allow_outside"] is True
