"""f2l ingest: a capture tree of real (synthetic) DNG brackets, face photos, probes and broken
files → captures.parquet: metadata, sessions, roles, brackets, statuses, and incremental reruns."""

from __future__ import annotations

import json
import os
import shutil
from datetime import datetime
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from PIL import Image

from f2l.capture.dng import write_bracket
from f2l.capture.manifest import run_ingest
from f2l.io.exr import write_exr
from f2l.io.schema import validate_table

CR2 = Path(__file__).resolve().parents[2] / "shared" / "data" / "raw" / "IMG_5952.CR2"
EXPOSURES = [1 / 1000, 1 / 250, 1 / 60, 1 / 15, 1 / 4]  # 2 EV apart
TOML = """
probe_azimuth_deg = 30.0
[lens]
projection = "equidistant"
fov_deg = 185.0
[[shots]]
files = "sky/frame_*"
yaw_deg = 90.0
pitch_deg = 80.0
"""


def _scene(seed: int, h: int = 24, w: int = 32) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (0.05 + 0.2 * rng.random((h, w, 3))).astype(np.float32)


def _bracket(folder: Path, seed: int, exposures=EXPOSURES, start=datetime(2024, 6, 21, 12, 0, 0),
             **kw) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    return write_bracket(folder, _scene(seed), exposures, seed=seed, timestamp=start, **kw)


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    from skimage import data

    root = tmp_path_factory.mktemp("captures") / "raw"
    # site1: role folders, a session TOML, a probe, broken files
    _bracket(root / "site1" / "sky", 1)
    _bracket(root / "site1" / "sky", 2, exposures=[1 / 125], prefix="lone",
             start=datetime(2024, 6, 21, 12, 10, 0))  # 10 minutes later: a bracket of one frame
    (root / "site1" / "faces").mkdir(parents=True)
    Image.fromarray(data.astronaut()).save(root / "site1" / "faces" / "astronaut.png")
    write_exr(root / "site1" / "probe.exr", np.full((8, 16, 3), 0.5, np.float32))
    (root / "site1" / "session.toml").write_text(TOML)
    good = sorted((root / "site1" / "sky").glob("frame_*"))[0].read_bytes()
    (root / "site1" / "faces" / "truncated.dng").write_bytes(good[: len(good) // 3])
    (root / "site1" / "faces" / "zero.cr2").write_bytes(b"")
    (root / "site1" / "faces" / "garbage.nef").write_bytes(os.urandom(4096))
    # site2: no role folders: the bracket and the face are detected by content
    _bracket(root / "site2", 3, exposures=EXPOSURES[:3], prefix="shot")
    Image.fromarray(data.astronaut()).save(root / "site2" / "portrait.jpg", quality=90)
    Image.fromarray((np.random.default_rng(0).random((64, 64, 3)) * 255).astype(np.uint8)).save(
        root / "site2" / "noise.png")
    # site3: a bracket folder mixing two cameras
    _bracket(root / "site3" / "sky", 4, exposures=EXPOSURES[:2], model="Camera A", prefix="a")
    _bracket(root / "site3" / "sky", 5, exposures=EXPOSURES[2:4], model="Camera B", prefix="b",
             start=datetime(2024, 6, 21, 12, 0, 2))
    return root


@pytest.fixture(scope="module")
def ingested(tree, tmp_path_factory):
    work = tmp_path_factory.mktemp("work")
    summary = run_ingest(tree, work)
    table = pq.read_table(work / "captures.parquet")
    rows = {r["path"]: r for r in table.to_pylist()}
    return summary, work, table, rows


def test_table_validates_and_counts(ingested):
    summary, work, table, rows = ingested
    validate_table(table, "captures", source="captures.parquet")
    assert summary.files == len(rows) == 20 and summary.read == 20 and summary.reused == 0
    assert summary.sessions == 3
    assert summary.brackets == 2  # site1/sky (5 frames) and site2 (3 frames, detected)


def test_bracket_frames_and_exif(ingested):
    _, _, _, rows = ingested
    sky = [rows[p] for p in sorted(rows) if p.startswith("site1/sky/frame_")]
    assert len(sky) == 5
    assert {r["bracket_id"] for r in sky} == {"site1/frame_00"} or len({r["bracket_id"] for r in sky}) == 1
    for r, t in zip(sorted(sky, key=lambda r: r["exposure_s"]), EXPOSURES):
        assert r["status"] == "ok" and r["kind"] == "raw" and r["role"] == "sky_bracket"
        assert r["role_source"] == "folder" and r["session"] == "site1"
        assert r["exposure_s"] == pytest.approx(t, rel=1e-6)
        assert r["f_number"] == pytest.approx(8.0) and r["iso"] == pytest.approx(100)
        assert r["ev100"] == pytest.approx(np.log2(64 / t), abs=1e-6)
        assert r["camera"] == "f2l Synthetic Bayer" and r["cfa_pattern"] == "RGGB"
        assert r["white_level"] == 4095 and r["black_levels"] == [256.0] * 4
        assert len(r["sha256"]) == 64 and r["width"] == 32 and r["height"] == 24
        view = json.loads(r["view_json"])
        assert view == {"projection": "equidistant", "fov_deg": 185.0, "yaw_deg": 90.0,
                        "pitch_deg": 80.0, "probe_azimuth_deg": 30.0}


def test_one_frame_bracket_and_mixed_cameras(ingested):
    _, _, _, rows = ingested
    lone = [r for p, r in rows.items() if "/lone_" in p]
    assert len(lone) == 1 and lone[0]["status"] == "skipped"
    assert "bracket of one frame" in lone[0]["message"] and lone[0]["path"] in lone[0]["message"]
    mixed = [r for p, r in rows.items() if p.startswith("site3/")]
    assert len(mixed) == 4 and all(r["status"] == "error" for r in mixed)
    assert all("Camera A" in r["message"] and "Camera B" in r["message"] for r in mixed)
    assert all(r["bracket_id"] is None for r in mixed + lone)


def test_broken_files_have_a_status_naming_them(ingested, tree):
    _, _, _, rows = ingested
    for name, reason in (("truncated.dng", ""), ("zero.cr2", "empty"), ("garbage.nef", "")):
        r = rows[f"site1/faces/{name}"]
        assert r["status"] == "error" and name in r["message"], r
        assert reason in r["message"] and r["sha256"] == ""
    assert rows["site1/faces/astronaut.png"]["status"] == "ok"


def test_roles_from_folders_content_and_kind(ingested):
    _, _, _, rows = ingested
    assert rows["site1/faces/astronaut.png"]["role"] == "face"
    assert rows["site1/faces/astronaut.png"]["role_source"] == "folder"
    probe = rows["site1/probe.exr"]
    assert (probe["kind"], probe["role"], probe["width"], probe["height"]) == ("hdr", "probe", 16, 8)
    portrait = rows["site2/portrait.jpg"]
    assert (portrait["role"], portrait["role_source"]) == ("face", "detected")
    assert rows["site2/noise.png"]["role"] == "other"
    detected = [r for p, r in rows.items() if p.startswith("site2/shot_")]
    assert len(detected) == 3 and len({r["bracket_id"] for r in detected}) == 1
    assert all((r["role"], r["role_source"]) == ("sky_bracket", "detected") for r in detected)


def test_reingest_reads_nothing_and_a_change_is_reread(ingested, tree, tmp_path):
    _, work, table, _ = ingested
    work2 = tmp_path / "work"
    shutil.copytree(work, work2)
    again = run_ingest(tree, work2, detect_roles=False)  # nothing may need the detectors
    assert again.read == 0 and again.reused == again.files == table.num_rows
    assert pq.read_table(work2 / "captures.parquet").equals(table)
    photo = tree / "site2" / "noise.png"
    st = photo.stat()
    os.utime(photo, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    try:
        third = run_ingest(tree, work2)
    finally:
        os.utime(photo, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert third.read == 1 and third.reused == table.num_rows - 1


def test_flat_folder_sessions_by_time_gap_and_bad_toml(tmp_path):
    root = tmp_path / "flat"
    root.mkdir()
    for i, hours in enumerate((0.0, 0.1, 3.0)):
        p = root / f"img{i}.png"
        Image.fromarray(np.full((16, 16, 3), 100 + i, np.uint8)).save(p)
        t = 1_700_000_000 + hours * 3600
        os.utime(p, (t, t))
    (root / "session.toml").write_text("[lens]\nprojection = 'pinhole'\n")
    summary = run_ingest(root, tmp_path / "w", detect_roles=False)
    rows = {r["path"]: r for r in pq.read_table(tmp_path / "w" / "captures.parquet").to_pylist()}
    assert summary.sessions == 2
    assert rows["img0.png"]["session"] == rows["img1.png"]["session"] != rows["img2.png"]["session"]
    assert all(r["status"] == "ok" and "session.toml" in r["message"] and "projection" in r["message"]
               for r in rows.values())


def test_missing_root_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a folder"):
        run_ingest(tmp_path / "nope", tmp_path / "w")


def test_real_canon_cr2_exif(tmp_path):
    if not CR2.is_file():
        pytest.skip(f"{CR2} not present (the shared data folder is not checked out here)")
    root = tmp_path / "raw" / "site"
    root.mkdir(parents=True)
    os.symlink(CR2, root / CR2.name)  # a link out of the tree: read only with allow_outside
    run_ingest(tmp_path / "raw", tmp_path / "w", detect_roles=False, allow_outside=True)
    (row,) = pq.read_table(tmp_path / "w" / "captures.parquet").to_pylist()
    assert row["status"] == "ok" and row["kind"] == "raw"
    assert row["exposure_s"] == pytest.approx(1 / 400) and row["f_number"] == pytest.approx(22)
    assert row["iso"] == pytest.approx(640) and "Canon" in row["camera"]
    assert row["white_level"] == 4095 and row["cfa_pattern"] == "RGGB"
