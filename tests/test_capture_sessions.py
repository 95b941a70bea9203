"""Issue 17: real capture sessions that disagree with f2l's conveniences — a circular equisolid
fisheye whose image circle is smaller than the short side (polynomial fall-off on the circle's
radius), a panoramic head's 7 rectilinear views in one folder (cos⁴ fall-off, per-file
orientations), both with a real camera's colour matrix (LibRaw's Canon EOS 30D entry) — through
`f2l ingest` + `f2l make-probes`, recovered in linear Rec.709 against the scene."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from f2l.capture.lens import LensError, lens_from_view
from f2l.testing.sessions import (CANON_EOS_30D_XYZ_TO_CAMERA, FISHEYE_FALLOFF, write_fisheye_session,
                                  write_panorama_session)
from f2l.cli import app
from f2l.io.exr import REC709_CHROMATICITIES, read_exr, write_exr
from f2l.lighting.grid import LatLongGrid, direction_from_angles
from f2l.lighting.resample import resample

CR2 = Path(__file__).resolve().parents[2] / "shared" / "data" / "raw" / "IMG_5952.CR2"
PROBE_HEIGHT = 128


def run(*args, code: int = 0):
    res = CliRunner().invoke(app, [str(a) for a in args])
    assert res.exit_code == code, res.output
    return res


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    base = tmp_path_factory.mktemp("sessions")
    root, work = base / "raw", base / "work"
    truths = {"fisheye": write_fisheye_session(root), "pano": write_panorama_session(root)}
    ingest = json.loads(run("ingest", root, "--work", work, "--no-detect-roles", "--json").stdout)
    probes = json.loads(run("make-probes", root, "--work", work, "--probe-height", PROBE_HEIGHT, "--json").stdout)
    rows = {(r["kind"], r["name"]): r for r in pq.read_table(work / "probes.parquet").to_pylist()}
    return root, work, truths, ingest, probes, rows


def _errors(work: Path, row: dict, truth) -> dict:
    """Per-channel relative errors on covered, unclipped sky texels (farther than 5° from the sun,
    above 2° of elevation: the fisheye's rim texels are partly outside its circle)."""
    from PIL import Image

    grid = LatLongGrid(PROBE_HEIGHT, 2 * PROBE_HEIGHT)
    probe = read_exr(work / row["path"])
    expected = resample(truth.probe, grid.height, grid.width)
    coverage = np.asarray(Image.open(work / row["path"].replace(".exr", ".coverage.png"))) > 127
    d = grid.directions.reshape(grid.height, grid.width, 3)
    sun = direction_from_angles(math.radians(truth.sun_elevation_deg), math.radians(truth.sun_azimuth_deg))
    near_sun = np.degrees(np.arccos(np.clip(d @ sun, -1, 1))) <= 5.0
    sky = coverage & ~near_sun & (np.degrees(np.arcsin(d[..., 1])) > 2.0)
    rel = np.abs(probe[sky] - expected[sky]) / expected[sky]
    got = direction_from_angles(math.radians(row["sun_elevation_deg"]), math.radians(row["sun_azimuth_deg"]))
    return {"texels": int(sky.sum()), "median": np.median(rel, axis=0),
            "within_5pct": float((rel < 0.05).all(1).mean()),
            "sun_deg": math.degrees(math.acos(min(1.0, float(got @ sun))))}


def test_ingest_finds_one_bracket_per_view(sessions):
    _, work, truths, ingest, _, _ = sessions
    assert ingest["by_status"] == {"ok": 56} and ingest["brackets"] == 8 and ingest["session_problems"] == []
    pano = [b for b in ingest["bracket_list"] if b["session"] == "pano"]
    assert len(pano) == 7 and all(b["frames"] == 7 for b in pano)
    views = {(b["view"]["yaw_deg"], b["view"]["pitch_deg"]) for b in pano}
    assert views == {(y, 30) for y in range(0, 360, 60)} | {(0, 90)}
    rows = pq.read_table(work / "captures.parquet").to_pylist()
    for b in pano:  # a bracket never mixes views, and holds each exposure once
        frames = [r for r in rows if r["bracket_id"] == b["bracket_id"]]
        assert len({r["view_json"] for r in frames}) == 1 and len({r["exposure_s"] for r in frames}) == 7


@pytest.mark.parametrize("session", ["fisheye", "pano"])
def test_probe_is_the_scene_in_linear_rec709(sessions, session):
    _, work, truths, _, summary, rows = sessions
    assert summary["probes"] == 2 and summary["errors"] == 0
    row = rows[("probe", session)]
    assert row["status"] == "ok" and row["colour_space"] == "rec709"
    err = _errors(work, row, truths[session])
    assert err["texels"] > 10000
    assert np.all(err["median"] <= 0.01), err  # per channel, absolute scale (not fitted)
    assert err["within_5pct"] >= 0.95, err
    assert err["sun_deg"] <= 0.2, err
    import OpenEXR

    with OpenEXR.File(str(work / row["path"]), header_only=True) as f:
        assert f.header()["chromaticities"] == pytest.approx(REC709_CHROMATICITIES, abs=1e-6)


def test_camera_rgb_is_not_rec709(sessions, tmp_path):
    """Without the colour matrix the probe is off per channel (what make-probes used to write)."""
    from f2l.capture.views import merge_bracket_view

    root, work, truths, _, _, _ = sessions
    frames = [r for r in pq.read_table(work / "captures.parquet").to_pylist() if r["session"] == "fisheye"]
    ratios = {}
    for space in ("camera", "rec709"):
        row, view = merge_bracket_view(root, tmp_path / space, frames[0]["bracket_id"], frames, colour_space=space)
        assert row["colour_space"] == space
        ratios[space] = np.median(view.image[view.image.sum(2) > 0], axis=0)
    per_channel = ratios["camera"] / ratios["rec709"]
    assert np.abs(per_channel - 1).max() > 0.3, per_channel


def test_lens_descriptions_agree():
    """Focal length in mm + sensor width + circle, fov + circle, focal px, and the COLMAP model
    the ideal lens is: the same rays."""
    w, h = 1536, 1024
    f_px = 8.0 * w / 36.0
    radius = 2 * f_px * math.sin(math.pi / 4)
    lenses = [lens_from_view({"projection": "equisolid", "focal_length_mm": 8.0, "sensor_width_mm": 36.0,
                              "image_circle_radius_px": radius}, w, h),
              lens_from_view({"projection": "equisolid", "fov_deg": 180.0, "image_circle_radius_px": radius}, w, h),
              lens_from_view({"projection": "equisolid", "sensor_width_mm": 36.0}, w, h, exif_focal_mm=8.0)]
    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 3))
    d[:, 2] = -np.abs(d[:, 2]) - 0.05
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pixels = [lens.view_camera(w, h).cam_direction_to_pixel(d)[0] for lens in lenses]
    for px in pixels[1:]:
        np.testing.assert_allclose(px, pixels[0], atol=1e-3)
    assert lenses[0].max_angle_deg == pytest.approx(90.0, abs=1e-3)
    colmap = lens_from_view({"colmap_model": "OPENCV_FISHEYE", "colmap_params": list(lenses[0].params),
                             "max_angle_deg": 90.0}, w, h)
    np.testing.assert_allclose(colmap.view_camera(w, h).cam_direction_to_pixel(d)[0], pixels[0], atol=1e-9)
    # a view box-averaged by 3 after a 1-px crop sees each ray at (x - 1) / 3
    small = lenses[0].view_camera(511, 341, k=3, crop_x=1, crop_y=0)
    np.testing.assert_allclose(small.cam_direction_to_pixel(d)[0], (pixels[0] - [1, 0]) / 3, atol=1e-6)
    with pytest.raises(LensError, match="sensor_width_mm"):
        lens_from_view({"projection": "rectilinear", "focal_length_mm": 16.0}, w, h)
    with pytest.raises(LensError, match="projection"):
        lens_from_view({"fov_deg": 90.0}, w, h)


def test_falloff_is_checked_only_where_the_lens_sees():
    """The fisheye's fall-off written on the half-diagonal instead of the circle's radius is
    negative in the corners (min -1.07), which a circular fisheye never sees: accepted there, the
    same gain as on the circle where it sees; refused on a rectilinear lens, which sees corners."""
    w, h = 1536, 1024
    radius = 2 * (8.0 * w / 36.0) * math.sin(math.pi / 4)
    s2 = (0.5 * math.hypot(w, h) / radius) ** 2
    fisheye = {"projection": "equisolid", "focal_length_mm": 8.0, "sensor_width_mm": 36.0}
    on_circle = lens_from_view({**fisheye, "falloff": {"model": "polynomial", "coefficients": list(FISHEYE_FALLOFF)}},
                               w, h)
    diagonal = {"model": "polynomial", "coefficients": [FISHEYE_FALLOFF[0] * s2, FISHEYE_FALLOFF[1] * s2**2],
                "radius": "half_diagonal"}
    on_diagonal = lens_from_view({**fisheye, "falloff": diagonal}, w, h)
    cam = on_circle.view_camera(w // 4, h // 4, k=4)
    g_circle, g_diagonal = on_circle.gain(cam, k=4), on_diagonal.gain(cam, k=4)
    np.testing.assert_allclose(g_diagonal, g_circle, rtol=1e-9)
    assert g_circle[cam.valid_pixel_mask()].min() == pytest.approx(1 + sum(FISHEYE_FALLOFF), abs=0.01)
    corner = 1 + diagonal["coefficients"][0] + diagonal["coefficients"][1]
    assert corner < -1.0
    rect = lens_from_view({"projection": "rectilinear", "fov_deg": 90.0, "falloff": diagonal}, w, h)
    with pytest.raises(LensError, match="not positive where the lens sees"):
        rect.gain(rect.view_camera(w // 4, h // 4, k=4), k=4)
    # exactly the written polynomial at the view's pixel centres
    x, y = 4 * (100 + 0.5) - w / 2, 4 * (60 + 0.5) - h / 2
    rho2 = (x * x + y * y) / radius**2
    assert g_circle[60, 100] == pytest.approx(1 + FISHEYE_FALLOFF[0] * rho2 + FISHEYE_FALLOFF[1] * rho2**2, rel=1e-6)


def test_flat_field_and_cos4(tmp_path):
    w, h = 64, 48
    lens = lens_from_view({"projection": "rectilinear", "fov_deg": 70.0, "falloff": {"model": "cos4"}}, w, h)
    cam = lens.view_camera(w, h)
    cos4 = lens.gain(cam)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    f = (w / 2) / math.tan(math.radians(35.0))
    expected = (f / np.sqrt(f * f + (xx - w / 2) ** 2 + (yy - h / 2) ** 2)) ** 4
    np.testing.assert_allclose(cos4, expected, rtol=1e-5)
    write_exr(tmp_path / "flat.exr", 0.5 * expected)  # a flat-field frame at any exposure
    flat = lens_from_view({"projection": "rectilinear", "fov_deg": 70.0,
                           "falloff": {"model": "flat_field", "file": "flat.exr"}}, w, h)
    g = flat.gain(flat.view_camera(w // 2, h // 2, k=2), k=2, root=tmp_path)
    blocks = expected.reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3))
    np.testing.assert_allclose(g, blocks / expected[23:25, 31:33].mean(), rtol=2e-3)


def test_brackets_split_where_the_exposure_sequence_restarts():
    from f2l.capture.brackets import split_brackets

    def frame(i, t, ev):
        return {"path": f"IMG_{i:04d}.CR2", "timestamp_utc": f"2024-06-21T12:00:{t:02d}", "mtime_ns": 0,
                "exposure_s": 2.0**ev / 100, "f_number": 8.0, "iso": 100.0, "view_json": "{}"}

    # three 3-frame AEB brackets (0, -2, +2 EV) shot in one burst: same second, no orientation given
    frames = [frame(i, 0, ev) for i, ev in enumerate([0, -2, 2] * 3)]
    assert [len(b) for b in split_brackets(frames)] == [3, 3, 3]
    # one bracket, then a pause: the pause splits even where exposures would not repeat
    frames = [frame(0, 0, 0), frame(1, 1, -2), frame(2, 2, 2), frame(3, 20, 4), frame(4, 21, 6)]
    assert [len(b) for b in split_brackets(frames)] == [3, 2]


TOML_AFTER_SHOTS = """[lens]
projection = "equidistant"
fov_deg = 180.0

[[shots]]
files = "sky/*"
pitch_deg = 90.0
probe_azimuth_deg = 30.0
"""


def test_session_toml_errors_reach_the_terminal(tmp_path):
    """A top-level key written after a [[shots]] table belongs to that shot in TOML: ingest,
    make-probes and the probes table say so, with the file and the key."""
    from f2l.capture.dng import write_bracket

    root, work = tmp_path / "raw", tmp_path / "work"
    write_bracket(root / "site" / "sky", np.full((32, 48, 3), 0.3), [1 / 100, 1 / 25], seed=1)
    (root / "site" / "session.toml").write_text(TOML_AFTER_SHOTS)
    res = run("ingest", root, "--work", work, "--no-detect-roles")
    for words in ("session.toml", "shots/0", "probe_azimuth_deg", "top-level key"):
        assert words in res.stderr, res.stderr
    rows = pq.read_table(work / "captures.parquet").to_pylist()
    assert all("probe_azimuth_deg" in r["session_problem"] for r in rows)
    res = run("make-probes", root, "--work", work)
    assert "session.toml" in res.stderr and "probe_azimuth_deg" in res.stderr
    (view,) = [r for r in pq.read_table(work / "probes.parquet").to_pylist() if r["kind"] == "view"]
    assert view["status"] == "unplaced" and "session.toml was not used" in view["message"]


@pytest.mark.skipif(not CR2.is_file(), reason=f"{CR2} not present (../shared holds the real camera file)")
def test_real_cr2_session_says_what_it_lacks(tmp_path):
    root, work = tmp_path / "raw", tmp_path / "work"
    (root / "site" / "sky").mkdir(parents=True)
    os.symlink(CR2, root / "site" / "sky" / CR2.name)  # a link out of the tree: --allow-outside reads it
    run("ingest", root, "--work", work, "--no-detect-roles", "--json", "--allow-outside")
    (row,) = pq.read_table(work / "captures.parquet").to_pylist()
    assert row["status"] == "skipped" and "bracket of one frame" in row["message"]
    res = run("make-probes", root, "--work", work)
    (probe,) = pq.read_table(work / "probes.parquet").to_pylist()
    assert probe["status"] == "skipped" and "bracket of one frame" in probe["message"]
    assert "no lens description" in probe["message"] and "no lens description" in res.stdout


@pytest.mark.skipif(not CR2.is_file(), reason=f"{CR2} not present")
def test_canon_matrix_is_libraws_entry():
    import rawpy

    with rawpy.imread(str(CR2)) as raw:
        np.testing.assert_allclose(np.asarray(raw.rgb_xyz_matrix)[:3].ravel(), CANON_EOS_30D_XYZ_TO_CAMERA, atol=1e-4)


def test_full_resolution_probe(sessions, tmp_path):
    """--full-probe: the fisheye's probe at its views' own resolution; area-averaged to the probe
    grid it is the 128 x 256 probe, and it still holds the sky to 1% per channel."""
    import pyarrow.compute as pc

    root, work, truths, _, _, rows = sessions
    work2 = tmp_path / "work"
    work2.mkdir()
    table = pq.read_table(work / "captures.parquet")
    pq.write_table(table.filter(pc.equal(table["session"], "fisheye")), work2 / "captures.parquet")
    run("make-probes", root, "--work", work2, "--probe-height", PROBE_HEIGHT, "--full-probe", "--json")
    row = {(r["kind"], r["name"]): r for r in pq.read_table(work2 / "probes.parquet").to_pylist()}[("probe", "fisheye")]
    full = read_exr(work2 / row["full_path"])
    pixel_deg = math.degrees(1 / (8.0 * 1536 / 36.0 / 2))  # the view (box-averaged by 2) at its centre
    assert full.shape[0] == min(512, 2 * math.ceil(90 / pixel_deg)) and full.shape[1] == 2 * full.shape[0]
    probe = read_exr(work2 / row["path"])
    upper = np.zeros(probe.shape[:2], bool)
    upper[: PROBE_HEIGHT // 2 - 2] = True
    coarse = resample(full, PROBE_HEIGHT, 2 * PROBE_HEIGHT)
    rel = np.abs(coarse[upper] - probe[upper]) / np.maximum(probe[upper], 1e-12)
    assert np.median(rel) < 0.005, np.median(rel)
