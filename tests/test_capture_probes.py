"""Issue 5 end to end: a known HDR sky → an up-looking fisheye view with vignetting → real DNG
brackets (7 exposures 2 EV apart, noise, clipping) → `f2l ingest` → `f2l make-probes` → the
lat-long probe, compared with the scene on the texels the fisheye saw."""

from __future__ import annotations

import json
import math

import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from f2l.capture.cameras import ViewCamera, Vignetting, apply_vignetting
from f2l.capture.dng import write_bracket
from f2l.capture.sphere import render_view
from f2l.cli import app
from f2l.io.exr import read_exr
from f2l.lighting.grid import LatLongGrid, direction_from_angles
from f2l.lighting.resample import resample
from f2l.metrics.lighting import sun_direction
from f2l.synth.skies import clear_sky

GRID = LatLongGrid(64, 128)
SUN_ELEVATION_DEG, SUN_AZIMUTH_DEG = 35.0, 60.0
VIGNETTING = (-0.25, 0.05, 0.0)  # ~20% fall-off at the image circle's edge
EXPOSURES = [2.0 ** (k - 12) for k in range(0, 14, 2)]  # 7 frames, 2 EV apart: 1/4096 .. 1 s
F_NUMBER = 4.0
SESSION_TOML = f"""
[lens]
projection = "equidistant"
fov_deg = 180.0
vignetting = [{VIGNETTING[0]}, {VIGNETTING[1]}, {VIGNETTING[2]}]
[[shots]]
files = "sky/*"
pitch_deg = 90.0
"""


def full_scale(view: np.ndarray) -> float:
    """Sensor full scale (radiance x exposure factor) of the fixture: the median sky pixel sits at
    a quarter of full scale in the longest frame; the sun saturates even the shortest one."""
    return 4.0 * float(np.median(view[view.sum(2) > 0])) * max(EXPOSURES) / F_NUMBER**2


def run(*args, exit_code: int = 0):
    res = CliRunner().invoke(app, [str(a) for a in args])
    assert res.exit_code == exit_code, res.output
    return res


@pytest.fixture(scope="module")
def scene_hi():
    """The scene at 256 x 512 (a sun of ~1e5 x the median sky, so it clips in every frame)."""
    sky = clear_sky(LatLongGrid(256, 512), math.radians(SUN_ELEVATION_DEG),
                    math.radians(SUN_AZIMUTH_DEG), turbidity=3.0, sun_kappa=8192.0)
    return (sky / float(np.median(sky[:128]))).astype(np.float32)  # median sky radiance 1


@pytest.fixture(scope="module")
def scene(scene_hi):
    """The same scene area-resampled to the probe grid: what assembly should recover."""
    return resample(scene_hi, GRID.height, GRID.width)


@pytest.fixture(scope="module")
def pipeline(scene_hi, tmp_path_factory):
    base = tmp_path_factory.mktemp("capture")
    root, work = base / "raw", base / "work"
    camera = ViewCamera.equidistant(180.0, 320, 320, pitch_deg=90.0)
    view, valid = render_view(scene_hi, camera, supersample=3)
    view = apply_vignetting(view, Vignetting(*VIGNETTING)) * valid[..., None]
    fs = full_scale(view)
    write_bracket(root / "site" / "sky", view, EXPOSURES, f_number=F_NUMBER, iso=100,
                  full_scale_radiance=fs, read_noise_dn=2.0, seed=7)
    (root / "site" / "session.toml").write_text(SESSION_TOML)
    ingest = json.loads(run("ingest", root, "--work", work, "--json").stdout)
    probes = json.loads(run("make-probes", root, "--work", work, "--probe-height", GRID.height, "--json").stdout)
    return root, work, ingest, probes, fs


def test_ingest_finds_one_bracket_with_its_view(pipeline):
    _, work, ingest, _, _ = pipeline
    assert ingest["files"] == 7 and ingest["brackets"] == 1 and ingest["by_status"] == {"ok": 7}
    rows = pq.read_table(work / "captures.parquet").to_pylist()
    assert {r["role"] for r in rows} == {"sky_bracket"}
    assert sorted(r["exposure_s"] for r in rows) == pytest.approx(EXPOSURES)
    view = json.loads(rows[0]["view_json"])
    assert view["projection"] == "equidistant" and view["pitch_deg"] == 90.0


def test_probe_recovers_the_scene(pipeline, scene):
    root, work, _, summary, fs = pipeline
    assert summary["brackets"] == 1 and summary["views"] == 1 and summary["probes"] == 1
    rows = {(r["kind"], r["name"]): r for r in pq.read_table(work / "probes.parquet").to_pylist()}
    probe_row = rows[("probe", "site")]
    assert probe_row["status"] == "ok"
    probe = read_exr(work / probe_row["path"])
    upper = np.zeros(GRID.shape, bool)
    upper[: GRID.height // 2 - 2] = True  # the fisheye's rim (last 2 rows above the horizon) is soft
    from PIL import Image

    coverage = np.asarray(Image.open(work / probe_row["path"].replace(".exr", ".coverage.png"))) > 127
    assert coverage[: GRID.height // 2 - 1].all() and not coverage[GRID.height // 2 + 1:].any()
    assert not probe[GRID.height // 2 + 1:].any()  # the ground was not seen: 0, not invented
    # radiance: the merged values are scene radiance / full_scale_radiance (EV100 0)
    lum = lambda a: a @ np.array([0.2126, 0.7152, 0.0722])  # noqa: E731
    ratio = lum(probe)[upper] / lum(scene)[upper]
    gain = np.median(ratio)
    near_sun = np.degrees(np.arccos(np.clip(
        GRID.directions @ direction_from_angles(math.radians(SUN_ELEVATION_DEG),
                                                math.radians(SUN_AZIMUTH_DEG)), -1, 1)))
    unclipped = upper & (near_sun > 8.0)
    rel = np.abs(probe[unclipped] / gain - scene[unclipped]) / scene[unclipped]
    assert np.median(rel) <= 0.02, np.median(rel)
    assert gain == pytest.approx(1.0 / fs, rel=0.01)  # absolute: 1.0 = full scale at EV100 0
    # the sun: saturated in every frame → flagged, and still where it was
    d = sun_direction(probe, GRID)
    truth = direction_from_angles(math.radians(SUN_ELEVATION_DEG), math.radians(SUN_AZIMUTH_DEG))
    assert math.degrees(math.acos(np.clip(d @ truth, -1, 1))) <= 1.0
    assert probe_row["sun_elevation_deg"] == pytest.approx(SUN_ELEVATION_DEG, abs=1.0)
    (view_row,) = [r for r in rows.values() if r["kind"] == "view"]
    assert view_row["frames"] == 7 and view_row["status"] == "ok"
    assert 0 < view_row["saturated_fraction"] < 0.01


def test_unplaced_bracket_without_lens_model(tmp_path, scene):
    root, work = tmp_path / "raw", tmp_path / "work"
    write_bracket(root / "s" / "sky", np.full((48, 64, 3), 0.3, np.float32), EXPOSURES[:3], seed=1)
    run("ingest", root, "--work", work, "--json")
    summary = json.loads(run("make-probes", root, "--work", work, "--json").stdout)
    assert summary["views"] == 0 and summary["probes"] == 0
    (row,) = pq.read_table(work / "probes.parquet").to_pylist()
    assert row["status"] == "unplaced" and "projection" in row["message"]
    assert (work / row["path"]).is_file()  # merged all the same


def test_downsample_view_preserves_radiance_and_flags_blocks():
    from f2l.capture.views import downsample_view

    rng = np.random.default_rng(0)
    rgb = rng.random((101, 130, 3)).astype(np.float32) * 1e4
    sat = np.zeros((101, 130), bool)
    sat[50, 64] = True
    small, small_sat = downsample_view(rgb, sat, 50)  # k = 3: 33 x 43 blocks of a centred crop
    assert small.shape == (33, 43, 3) and small_sat.shape == (33, 43)
    crop = rgb[1:100, 0:129]
    np.testing.assert_allclose(small.sum((0, 1)) * 9, crop.sum((0, 1), dtype=np.float64), rtol=1e-5)
    assert small_sat.sum() == 1 and small_sat[(50 - 1) // 3, 64 // 3]
    same, same_sat = downsample_view(rgb, sat, 200)
    assert same is rgb and same_sat is sat


@pytest.mark.parametrize("compression", ["ljpeg", "none"])
def test_bench_capture_runs_the_real_stages(compression):
    from f2l.dev.bench_capture import format_table, run_capture_bench

    (row,) = run_capture_bench((2,), frames=3, megapixels=0.05, repeat=1, compression=compression)
    assert row["brackets_found"] == 2  # two brackets in one folder, split by ingest
    assert row["files"] == 6 and row["compression"] == compression and row["decode_s"] > 0 and row["ingest_s"] > 0 and row["merge_s"] > 0
    assert row["ratio"] == pytest.approx((row["ingest_s"] + row["merge_s"]) / row["decode_s"])
    assert 0 < row["assembly_s"] < row["make_probes_s"]  # placed views: merged and assembled in the second run
    assert row["ratio_with_assembly"] == pytest.approx((row["ingest_s"] + row["make_probes_s"]) / row["decode_s"])
    assert all(row["peak_mib"][k] >= row["work_mib"][k] >= 0 for k in ("decode", "ingest", "merge", "probes"))
    assert "(ingest+merge)/decode" in format_table([row])


def test_a_broken_bracket_among_several_sessions_fails_alone(tmp_path):
    """make-probes decodes the next bracket while finishing the current one: a bracket whose file
    broke after ingest gets an error row naming the file; the sessions around it are merged."""
    root, work = tmp_path / "raw", tmp_path / "work"
    scene = np.full((48, 64, 3), 0.3, np.float32)
    for k in range(3):
        write_bracket(root / f"s{k}" / "sky", scene, EXPOSURES[:3], seed=k, compression="ljpeg")
    run("ingest", root, "--work", work, "--json")
    broken = root / "s1" / "sky" / "frame_01.dng"
    broken.write_bytes(broken.read_bytes()[:200])  # truncated after ingest
    summary = json.loads(run("make-probes", root, "--work", work, "--json", exit_code=4).stdout)  # 4: some failed
    rows = pq.read_table(work / "probes.parquet").to_pylist()
    by_session = {r["session"]: r for r in rows if r["kind"] == "view"}
    assert [by_session[s]["status"] for s in ("s0", "s1", "s2")] == ["unplaced", "error", "unplaced"]
    assert "frame_01.dng" in by_session["s1"]["message"] and "truncated" in by_session["s1"]["message"]
    assert (work / by_session["s0"]["path"]).is_file() and (work / by_session["s2"]["path"]).is_file()
    assert summary["errors"] == 1
