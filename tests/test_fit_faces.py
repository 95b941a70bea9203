"""``f2l fit-faces`` on real and synthetic photos, fit_face's rejections, the landmarker, and the
synthetic round trip synth → fit-faces → compare-geometry → estimate (in-process CLI)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from PIL import Image
from typer.testing import CliRunner

from f2l.cli import app
from f2l.face.fit import FaceFit, FitOptions, Rejected, face_record, fit_face
from f2l.face.overlay import PAD, overlay_layout
from f2l.face.regions import LEFT_EYE, RIGHT_EYE
from f2l.io.shards import iter_records
from f2l.lighting.grid import LatLongGrid
from f2l.synth.render import pose_matrix

GRID = "16x32"
RESOLUTION = 104  # the CLI default


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def status_rows(out: Path) -> dict[str, dict]:
    rows = pq.read_table(out / "status" / "fit_faces.parquet").to_pylist()
    return {Path(r["source_path"]).name: r for r in rows}


@pytest.fixture(scope="module")
def photo_dir(tmp_path_factory):
    import skimage.data

    d = tmp_path_factory.mktemp("photos")
    Image.fromarray(skimage.data.astronaut()).save(d / "astronaut.png")
    Image.fromarray(skimage.data.coffee()).save(d / "coffee.png")
    (d / "broken.png").write_bytes((d / "astronaut.png").read_bytes()[:3000])
    (d / "empty.jpg").write_bytes(b"")
    # the astronaut at 200 px: a face ~36 px wide, found by the detector (it searches down to
    # 0.8 x min_face_px) but narrower than the 40 px it may fit
    Image.open(d / "astronaut.png").resize((200, 200), Image.Resampling.LANCZOS).save(d / "tiny.png")
    return d


# --- the astronaut ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def astronaut_run(photo_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("astronaut_fit")
    res = invoke("fit-faces", photo_dir / "astronaut.png", "--out", out, "--grid", GRID, "--json")
    return res, out


def test_astronaut_gives_one_valid_record(astronaut_run):
    res, out = astronaut_run
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["records"] == 1 and summary["status"]["ok"] == 1
    records = list(iter_records(out))
    assert len(records) == 1
    rec = records[0]
    rec.validate()
    assert rec.face_id.startswith("astronaut-") and rec.face_id.endswith("-f0")
    assert (rec.image_height, rec.image_width) == (RESOLUTION, RESOLUTION)
    assert (rec.grid_height, rec.grid_width) == (16, 32)
    assert rec.num_pixels >= 5000  # measured 5851
    assert int(rec.mask.sum()) > 2000  # measured 3233
    counts = rec.meta["counts"]
    assert counts["num_pixels"] == rec.num_pixels and counts["num_masked"] == int(rec.mask.sum())
    assert counts["num_features"] > 300 and counts["num_border"] > 500
    # her fringe covers the forehead's hairline band: the colour test leaves it out as hair
    # (measured 343 pixels; 38 of the band's pixels are skin and kept)
    assert counts["num_hair"] > 200 and rec.meta["fit"]["hairline"] == "colour"
    assert abs(rec.meta["pose_deg"]["yaw"]) < 15.0  # she faces the camera (measured +0.4°)
    assert rec.meta["camera"]["focal_source"] == "default"
    # the fitted face lies at a plausible distance in front of the camera, normals toward it
    assert (rec.points[:, 2] < 0).all()
    to_cam = -rec.points / np.linalg.norm(rec.points, axis=1, keepdims=True)
    assert (np.einsum("ij,ij->i", rec.normals, to_cam) > 0.1).all()


def test_astronaut_side_files_and_status(astronaut_run, photo_dir):
    _, out = astronaut_run
    rec = next(iter(iter_records(out)))
    fid = rec.face_id
    assert rec.photo_path == f"photos/{fid}.png" and rec.meta["overlay_path"] == f"overlays/{fid}.png"
    crop = np.asarray(Image.open(out / "photos" / f"{fid}.png"))
    assert crop.shape == (RESOLUTION, RESOLUTION, 3) and crop.std() > 10
    with Image.open(out / "overlays" / f"{fid}.png") as overlay:
        overlay.load()
        assert overlay.width >= 4 * RESOLUTION and overlay.height > 2 * RESOLUTION
        # four panels of the crop at the default scale 2, laid out by overlay_layout
        origins = overlay_layout((RESOLUTION, RESOLUTION, 3))
        assert len(origins) == 4 and overlay.width == origins[-1][1] + 2 * RESOLUTION + PAD
    rows = pq.read_table(out / "status" / "fit_faces.parquet").to_pylist()
    assert len(rows) == 1
    row = rows[0]
    assert row["status"] == "ok" and row["face_ids"] == [fid] and row["num_detected"] == 1
    assert row["source_path"] == str(photo_dir / "astronaut.png")
    assert fid.split("-")[1] == row["sha256"][:10]
    assert json.loads(row["rejected_json"]) == []


# --- a folder with good, faceless and bad files ------------------------------------------------

@pytest.fixture(scope="module")
def folder_run(photo_dir, tmp_path_factory):
    d = tmp_path_factory.mktemp("mixed")
    for name in ("astronaut.png", "coffee.png", "broken.png", "empty.jpg"):
        shutil.copy(photo_dir / name, d / name)
    out = tmp_path_factory.mktemp("mixed_fit")
    return invoke("fit-faces", d, "--out", out, "--grid", GRID, "--json"), out


def test_folder_one_bad_photo_never_stops_the_batch(folder_run):
    res, out = folder_run
    assert res.exit_code == 4, res.output  # 4: one photo failed, the rest written
    summary = json.loads(res.stdout)
    assert summary["photos"] == 4 and summary["records"] == 1
    assert summary["status"] == {"ok": 1, "no_face": 1, "rejected": 0, "error": 2}
    rows = status_rows(out)
    assert set(rows) == {"astronaut.png", "coffee.png", "broken.png", "empty.jpg"}
    assert rows["astronaut.png"]["status"] == "ok" and len(rows["astronaut.png"]["face_ids"]) == 1
    assert rows["coffee.png"]["status"] == "no_face" and "coffee" in rows["coffee.png"]["message"]
    assert rows["coffee.png"]["num_detected"] == 0
    for name in ("broken.png", "empty.jpg"):
        assert rows[name]["status"] == "error", rows[name]
        assert name in rows[name]["message"] and rows[name]["face_ids"] == []
    records = list(iter_records(out))
    assert [r.face_id for r in records] == rows["astronaut.png"]["face_ids"]


def test_all_photos_failing_exits_1(photo_dir, tmp_path):
    d = tmp_path / "in"
    d.mkdir()
    shutil.copy(photo_dir / "broken.png", d / "broken.png")
    res = invoke("fit-faces", d, "--out", tmp_path / "out", "--grid", GRID, "--json")
    assert res.exit_code == 1, res.output
    summary = json.loads(res.stdout)
    assert summary["status"]["error"] == 1 and summary["photos"] == 1 and summary["records"] == 0
    assert status_rows(tmp_path / "out")["broken.png"]["status"] == "error"


def test_tiny_face_is_rejected_as_too_small(photo_dir, tmp_path):
    # measured: the detector finds the 200-px astronaut, its face is ~36 px wide (< 40)
    res = invoke("fit-faces", photo_dir / "tiny.png", "--out", tmp_path, "--grid", GRID, "--json")
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["status"]["rejected"] == 1
    row = status_rows(tmp_path)["tiny.png"]
    assert row["status"] == "rejected" and row["num_detected"] == 1 and row["face_ids"] == []
    rejected = json.loads(row["rejected_json"])
    assert [r["reason"] for r in rejected] == ["too_small"]
    assert "tiny.png" in rejected[0]["message"] and "< 40 px" in rejected[0]["message"]
    span = re.search(r"(\d+) px wide < 40 px", rejected[0]["message"])
    assert span is not None and 30 <= int(span.group(1)) < 40
    assert list(iter_records(tmp_path)) == []


# --- fit_face on constructed landmarks ---------------------------------------------------------

PHOTO_SIZE, FOCAL, DISTANCE, GREY = 256, 700.0, 60.0, 128


@pytest.fixture(scope="module")
def grey_photo():
    from f2l.io.photo import Photo

    return Photo(path="grey.png", kind="png", codes=np.full((PHOTO_SIZE, PHOTO_SIZE, 3), GREY, np.uint8),
                 focal_px=FOCAL, focal_source="default", orientation=1, exif={})


def synthetic_landmarks(yaw, pitch=0.0, roll=0.0):
    """(478, 3) landmarks of the canonical mesh posed at DISTANCE cm through the photo's pinhole;
    the 10 iris rows are copies of eye points."""
    from f2l.face.mesh import canonical_face_mesh

    c = np.asarray(canonical_face_mesh()[0], dtype=np.float64)
    v = (c - c.mean(0)) @ pose_matrix(yaw, pitch, roll).T + [0.0, 0.0, -DISTANCE]
    z = -v[:, 2]
    lm = np.stack([PHOTO_SIZE / 2 + FOCAL * v[:, 0] / z, PHOTO_SIZE / 2 - FOCAL * v[:, 1] / z,
                   -(v[:, 2] - v[:, 2].mean()) * FOCAL / DISTANCE], axis=1)
    iris = lm[list(RIGHT_EYE[:5]) + list(LEFT_EYE[:5])]
    return np.concatenate([lm, iris], axis=0)


# the photos here are flat grey (no detail at all: blur index 1), so the blur refusal is off
OPTIONS = FitOptions(resolution=64, grid=LatLongGrid(16, 32), max_blur_index=1.0)


def test_fit_face_frontal_gives_a_fit(grey_photo):
    lm = synthetic_landmarks(10.0, -5.0, 3.0)
    fit = fit_face(grey_photo, lm, 0, OPTIONS)
    assert isinstance(fit, FaceFit), fit
    assert (fit.head.yaw_deg, fit.head.pitch_deg, fit.head.roll_deg) == pytest.approx((10, -5, 3), abs=0.05)
    assert fit.head.distance_cm == pytest.approx(DISTANCE, abs=0.5)
    n = fit.num_pixels
    assert n > 0.3 * 64 * 64 and fit.pixel_rc.shape == (n, 2) and fit.pixel_rc.max() < 64
    assert fit.visibility_bits.shape == (n, 64) and fit.visibility_bits.dtype == np.uint8
    assert fit.mask.sum() > 500 and fit.counts()["num_masked"] == fit.mask.sum()
    # a uniform grey photo: every working pixel observes sRGB⁻¹(128), the crop is grey
    np.testing.assert_allclose(fit.observed_rgb, grey_photo.linear[0, 0, 0], rtol=1e-5)
    assert fit.crop_display.shape == (64, 64, 3) and (fit.crop_display == GREY).all()
    assert not fit.excluded["clipped"].any() and not fit.excluded["black"].any()
    # skin, features, border and hair partition the face pixels; on a uniform photo the
    # hairline band has the skin's colour and is skin
    total = fit.mask.astype(int) + fit.excluded["features"] + fit.excluded["border"] + fit.excluded["hair"]
    assert (total == 1).all() and not fit.excluded["hair"].any()
    np.testing.assert_allclose(np.linalg.norm(fit.normals, axis=1), 1.0, atol=1e-5)


def _band(fit):
    from f2l.face.regions import skin_regions

    return skin_regions(fit.view.to_working(fit.landmarks), fit.pixel_rc[:, ::-1] + 0.5)["hairline"]


def test_fit_face_hairline_band_by_colour(grey_photo):
    """A dark fringe painted over the forehead's hairline band: "colour" leaves it out as hair
    and keeps the skin; "exclude" leaves the band out as border, "keep" keeps all of it."""
    from f2l.io.photo import Photo
    from f2l.face.regions import skin_regions

    lm = synthetic_landmarks(10.0, -5.0, 3.0)
    rc = np.stack(np.divmod(np.arange(PHOTO_SIZE**2), PHOTO_SIZE), 1)
    band = skin_regions(lm, rc[:, ::-1] + 0.5)["hairline"].reshape(PHOTO_SIZE, PHOTO_SIZE)
    fringe = band & (np.arange(PHOTO_SIZE)[None, :] < lm[10, 0])  # the band's image-left half
    codes = np.full((PHOTO_SIZE, PHOTO_SIZE, 3), GREY, np.uint8)
    codes[fringe] = (40, 30, 24)  # dark brown hair
    photo = Photo(path="fringe.png", kind="png", codes=codes, focal_px=FOCAL, focal_source="default",
                  orientation=1, exif={})
    fit = fit_face(photo, lm, 0, OPTIONS)
    working_band = _band(fit)
    x = fit.pixel_rc[:, 1] + 0.5
    x_split = float(fit.view.to_working(lm)[10, 0])
    left, right = working_band & (x < x_split - 2), working_band & (x > x_split + 2)
    assert left.sum() > 20 and right.sum() > 20
    assert fit.excluded["hair"][left].mean() > 0.9 and not fit.mask[left].any()
    assert fit.mask[right].mean() > 0.95 and not fit.excluded["hair"][right].any()
    assert not fit.excluded["border"][working_band].any()
    excluded = fit_face(photo, lm, 0, FitOptions(resolution=64, grid=LatLongGrid(16, 32), hairline="exclude"))
    assert excluded.excluded["border"][working_band].all() and not excluded.mask[working_band].any()
    assert not excluded.excluded["hair"].any()
    kept = fit_face(photo, lm, 0, FitOptions(resolution=64, grid=LatLongGrid(16, 32), hairline="keep"))
    assert kept.mask[working_band].all()
    assert kept.mask.sum() == fit.mask.sum() + fit.excluded["hair"].sum()
    assert excluded.mask.sum() == fit.mask.sum() - fit.mask[working_band].sum()


def test_fit_face_rejects_profile(grey_photo):
    res = fit_face(grey_photo, synthetic_landmarks(65.0), 3, OPTIONS)
    assert isinstance(res, Rejected) and res.reason == "profile" and res.face_index == 3
    assert "+65°" in res.message and "50°" in res.message
    res = fit_face(grey_photo, synthetic_landmarks(-65.0), 0, OPTIONS)
    assert isinstance(res, Rejected) and res.reason == "profile" and "-65°" in res.message


def test_fit_face_rejects_cut_off(grey_photo):
    lm = synthetic_landmarks(0.0)
    x = lm[:468, 0]
    lm[:, 0] += PHOTO_SIZE - np.quantile(x, 0.8) + 0.01  # ~20% of the mesh points beyond x = w
    outside = float((lm[:468, 0] > PHOTO_SIZE).mean())
    assert 0.18 < outside < 0.22
    res = fit_face(grey_photo, lm, 0, OPTIONS)
    assert isinstance(res, Rejected) and res.reason == "cut_off"
    assert f"{outside:.0%} of its landmarks lie outside" in res.message


def test_fit_face_rejects_too_small(grey_photo):
    lm = synthetic_landmarks(0.0)
    centre = lm[:468, :2].mean(0)
    span = np.ptp(lm[:468, 0])  # the width: this frontal face's eye line is horizontal
    lm[:, :2] = centre + (lm[:, :2] - centre) * (30.0 / span)
    lm[:, 2] *= 30.0 / span
    res = fit_face(grey_photo, lm, 0, OPTIONS)
    assert isinstance(res, Rejected) and res.reason == "too_small"
    assert re.search(r"\b30 px wide < 40 px", res.message), res.message


# --- synthetic round trip ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def synth_truth(tmp_path_factory):
    truth = tmp_path_factory.mktemp("truth")
    res = invoke("eval", "synth", "--out", truth, "--n", 2, "--seed", 7, "--image-size", 192, "--features",
                 "--lambertian", "--overcast-fraction", 0, "--grid", GRID, "--json")
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["faces"] == 2
    return truth


@pytest.fixture(scope="module")
def synth_fitted(synth_truth, tmp_path_factory):
    fitted = tmp_path_factory.mktemp("fitted")
    res = invoke("fit-faces", synth_truth / "photos", "--out", fitted, "--grid", GRID,
                 "--gt-probes", synth_truth / "probes", "--json")
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["status"]["ok"] == 2
    return fitted


@pytest.fixture(scope="module")
def compared(synth_fitted, synth_truth, tmp_path_factory):
    twin = tmp_path_factory.mktemp("twin")
    res = invoke("eval", "compare-geometry", synth_fitted, "--truth", synth_truth, "--twin-out", twin, "--json")
    assert res.exit_code == 0, res.output
    return json.loads(res.stdout), twin


def test_synthetic_fit_records(synth_fitted, synth_truth):
    truth = {r.face_id: r for r in iter_records(synth_truth)}
    records = list(iter_records(synth_fitted))
    assert len(records) == 2
    for rec in records:
        rec.validate()
        stem = Path(rec.source_path).stem
        assert stem in truth and rec.face_id.startswith(stem + "-")
        assert rec.gt_probe_path == f"probes/{rec.face_id}.exr"
        assert (synth_fitted / rec.gt_probe_path).read_bytes() == \
            (synth_truth / truth[stem].gt_probe_path).read_bytes()
        # the synthetic EXIF gives the renderer's focal length
        assert rec.meta["camera"]["focal_source"] != "default"
        assert rec.meta["camera"]["focal_px"] == pytest.approx(truth[stem].meta["focal_px"], rel=1e-3)
        assert rec.meta["face_distance_cm"] == pytest.approx(60.0, abs=4.0)  # measured 58.4, 58.7
        assert rec.mask.sum() > 2000


def test_synthetic_geometry_matches_truth(compared, synth_fitted):
    report, twin = compared
    rows = report["rows"]
    assert len(rows) == 2 and report["summary"]["faces"] == 2
    for r in rows:
        # measured at 192 px: medians 1.1° and 2.0°, p90 3.2° and 4.8°; |yaw err| 0.4° and 0.3°;
        # |pitch err| 0.1° and 1.9°
        assert r["compared_px"] > 2000
        assert r["median_deg"] < 5.0, r
        assert r["p90_deg"] < 10.0, r
        assert abs(r["yaw_fit"] - r["yaw_true"]) < 4.0, r
        assert abs(r["pitch_fit"] - r["pitch_true"]) < 6.0, r
    fitted = {r.face_id: r for r in iter_records(synth_fitted)}
    twins = list(iter_records(twin))
    assert len(twins) == 2 and {t.face_id for t in twins} == set(fitted)
    for t in twins:
        f = fitted[t.face_id]
        assert t.gt_probe_path is not None and (twin / t.gt_probe_path).is_file()
        assert np.array_equal(t.observed_rgb, f.observed_rgb) and np.array_equal(t.pixel_rc, f.pixel_rc)
        assert not (t.mask & ~f.mask).any() and t.mask.sum() > 0.9 * f.mask.sum()


def test_estimate_on_fitted_records(synth_fitted, tmp_path):
    res = invoke("estimate", synth_fitted, "-m", "sh9", "--out", tmp_path, "--json")
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["ok"] == 2
    rows = pq.read_table(tmp_path / "estimates.parquet").to_pylist()
    assert len(rows) == 2 and all(r["status"] == "ok" for r in rows)
    assert {r["face_id"] for r in rows} == {r.face_id for r in iter_records(synth_fitted)}


def test_landmarker_is_deterministic_and_accurate(synth_truth):
    from f2l.face.landmarker import FaceLandmarker

    lmk = FaceLandmarker()
    records = list(iter_records(synth_truth))
    assert len(records) == 2
    for rec in records:
        image = np.asarray(Image.open(synth_truth / rec.photo_path).convert("RGB"))
        first, second = lmk(image), lmk(image)
        assert len(first) == 1 and first[0].points.shape == (478, 3)
        assert np.array_equal(first[0].points, second[0].points)
        truth = np.asarray(rec.meta["landmarks_xy"])
        width = float(np.ptp(truth[:, 0]))
        err = np.linalg.norm(first[0].points[:468, :2] - truth, axis=1)
        # measured: median 1.1% and 1.2% of the face width
        assert np.median(err) < 0.03 * width


# --- the pinned landmarker bundle ---------------------------------------------------------------

@pytest.fixture(scope="module")
def altered_bundle(tmp_path_factory):
    from f2l.face.mesh import default_task_path

    path = tmp_path_factory.mktemp("bundle") / "altered_landmarker.task"
    path.write_bytes(default_task_path().read_bytes() + b"\0")
    return path


def test_altered_bundle_is_refused(altered_bundle):
    from f2l.face.landmarker import FaceLandmarker
    from f2l.face.mesh import FaceMeshError

    with pytest.raises(FaceMeshError, match="SHA-256") as info:
        FaceLandmarker(task_path=altered_bundle)
    assert "altered_landmarker.task" in str(info.value)


def test_altered_bundle_via_cli(altered_bundle, photo_dir, tmp_path):
    res = invoke("fit-faces", photo_dir / "astronaut.png", "--out", tmp_path, "--grid", GRID,
                 "--landmarker", altered_bundle, "--json")
    assert res.exit_code != 0
    assert "altered_landmarker.task" in res.stderr and "SHA-256" in res.stderr
    assert list(iter_records(tmp_path)) == []


def test_footprint_resample_matches_scipy_map_coordinates():
    from scipy.ndimage import map_coordinates

    from f2l.face.fit import _resample

    rng = np.random.default_rng(0)
    img = rng.random((50, 70, 3)).astype(np.float32)
    xs, ys = np.linspace(-3, 75, 40), np.linspace(-2, 53, 40)  # reaches past every edge
    yy, xx = np.meshgrid(ys - 0.5, xs - 0.5, indexing="ij")
    for order in (0, 1):
        ref = np.stack([map_coordinates(img[..., c], np.stack([yy.ravel(), xx.ravel()]),
                                        order=order, mode="nearest").reshape(40, 40)
                        for c in range(3)], axis=-1)
        got = _resample(img, xs, ys, 2, order)  # (20, 20, 4, 3): 2x2 samples per pixel
        got = got.reshape(20, 20, 2, 2, 3).transpose(0, 2, 1, 3, 4).reshape(40, 40, 3)
        np.testing.assert_allclose(got, ref, atol=1e-6)
    grey = _resample(img[..., 0], xs, ys, 4, 1)
    assert grey.shape == (10, 10, 16)


def test_transport_traced_on_the_mask_only(grey_photo):
    from f2l.io.shards import unpack_visibility
    from f2l.transport.visibility import front_mask

    lm = synthetic_landmarks(5.0, 0.0, 0.0)
    grid = LatLongGrid(32, 64)
    fits = {p: fit_face(grey_photo, lm, 0, FitOptions(resolution=96, grid=grid, transport_pixels=p, max_blur_index=1.0))
            for p in ("mask", "all")}
    m, a = fits["mask"], fits["all"]
    assert np.array_equal(m.pixel_rc, a.pixel_rc) and np.array_equal(m.mask, a.mask)
    assert np.array_equal(m.traced, m.mask) and a.traced.all()
    untraced = ~m.mask
    assert untraced.sum() > 500
    vm, va = (unpack_visibility(f.visibility_bits, grid.size) for f in (m, a))
    # untraced pixels: their whole front hemisphere, no self-shadowing
    assert np.array_equal(vm[untraced], front_mask(m.normals[untraced].astype(np.float64), grid))
    # ... which the traced transport shadows in places (eye sockets, nose sides)
    assert (va[untraced] < vm[untraced]).any()
    # traced pixels agree with tracing every pixel (the pixel lattice differs; adaptive casting
    # may differ on a few grazing texels)
    assert (vm[m.mask] != va[m.mask]).mean() < 2e-3
    rec_meta = face_record(m, grey_photo, "f", FitOptions(grid=grid), source_path="x").meta
    assert rec_meta["transport"]["num_traced"] == int(m.mask.sum())
    assert rec_meta["fit"]["transport_pixels"] == "mask"
    with pytest.raises(ValueError, match="transport_pixels"):
        fit_face(grey_photo, lm, 0, FitOptions(resolution=64, grid=grid, transport_pixels="skin"))


@pytest.mark.parametrize("hw", [(64, 128), (8, 16), (6, 6), (2, 6)])
def test_sky_visibility_from_packed_bits_equals_the_unpacked_sum(hw):
    """The overlay's sky-visibility fraction, read from the packed bits by a per-byte table, is the
    solid-angle-weighted mean of the unpacked upper-hemisphere bits (also where a byte straddles
    the horizon: 6 x 6 and 2 x 6 grids)."""
    from f2l.face.fit import sky_visibility
    from f2l.io.shards import unpack_visibility

    grid = LatLongGrid(*hw)
    bits = np.random.default_rng(1).integers(0, 256, (300, -(-grid.size // 8)), dtype=np.uint8)
    vis = unpack_visibility(bits, grid.size).reshape(300, *hw)[:, : hw[0] // 2]
    sa = grid.solid_angles.reshape(hw)[: hw[0] // 2]
    np.testing.assert_allclose(sky_visibility(bits, grid), (vis * sa).sum((1, 2)) / sa.sum(), rtol=0, atol=1e-14)
    assert sky_visibility(np.full((1, bits.shape[1]), 255, np.uint8), grid)[0] == pytest.approx(1.0, abs=1e-14)


def test_an_overexposed_face_is_refused_as_clipped(photo_dir, tmp_path):
    """The astronaut x1.5 (her skin near 90% saturated): most of her skin clips; the face is refused with the
    share of clipped skin, not fitted from the few pixels left."""
    from PIL import Image

    a = np.asarray(Image.open(photo_dir / "astronaut.png").convert("RGB")).astype(np.float64)
    Image.fromarray(np.clip(a * 1.5, 0, 255).astype(np.uint8)).save(tmp_path / "bright.png")
    res = invoke("fit-faces", tmp_path / "bright.png", "--out", tmp_path / "out", "--grid", GRID, "--json")
    assert res.exit_code == 0, res.output
    row = status_rows(tmp_path / "out")["bright.png"]
    rejected = json.loads(row["rejected_json"])
    assert row["status"] == "rejected" and [r["reason"] for r in rejected] == ["clipped"], row
    share = re.search(r"(\d+)% of its skin is clipped", rejected[0]["message"])
    assert share is not None and int(share.group(1)) > 50


def test_a_greyscale_photo_is_flagged(photo_dir, tmp_path):
    """A greyscale photo says nothing about the light's colour: its record and status say so; the
    colour photo's do not."""
    from PIL import Image

    Image.open(photo_dir / "astronaut.png").convert("L").save(tmp_path / "grey.png")
    res = invoke("fit-faces", tmp_path / "grey.png", photo_dir / "astronaut.png", "--out", tmp_path / "out",
                 "--grid", GRID, "--json")
    assert res.exit_code == 0, res.output
    rows = status_rows(tmp_path / "out")
    assert rows["grey.png"]["status"] == "ok" and "greyscale" in rows["grey.png"]["message"]
    assert "greyscale" not in rows["astronaut.png"]["message"]
    flags = {Path(r.source_path).name: r.meta["greyscale"] for r in iter_records(tmp_path / "out")}
    assert flags == {"grey.png": True, "astronaut.png": False}
