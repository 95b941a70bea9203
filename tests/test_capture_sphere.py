"""Sphere assembly: pycolmap-backed cameras in the f2l frame, render_view / assemble, mirror balls,
saturation, vignetting and rotation refinement (f2l.capture.cameras, f2l.capture.sphere).

Scenes are analytic skies (smooth gradient + circumsolar glow + a 1.5 deg sun of radiance 2e5,
optionally soft 'clouds') area-averaged onto a 128 x 256 probe; assemblies use the 64 x 128 grid
and are compared with the exact area resampling of that probe (f2l.lighting.resample).
"""

from __future__ import annotations

import dataclasses
import math
from functools import lru_cache

import numpy as np
import pycolmap
import pytest

from f2l.capture.cameras import (
    COLMAP_FROM_F2L, MirrorBallCamera, ViewCamera, Vignetting, apply_vignetting, correct_vignetting,
    equisolid_max_error_rad, mirror_ball_view, rotation_from_ypr, ypr_from_rotation,
)  # fmt: skip
from f2l.capture.sphere import View, assemble, refine_rotations, render_view
from f2l.lighting.grid import LatLongGrid, direction_from_angles
from f2l.lighting.resample import resample
from f2l.metrics.lighting import angle_deg, cap_mask, sun_direction

GRID = LatLongGrid(64, 128)
SUN_AZIMUTH_DEG = -60.0


def _sky(d: np.ndarray, sun: np.ndarray, clouds=()) -> np.ndarray:
    """Radiance (..., 3) of unit directions: gradient + glow, textured ground, a 1.5 deg sun."""
    y = d[..., 1]
    cos_g = d @ sun
    base = 0.3 + 0.7 * (1 - np.clip(y, 0, 1)) ** 2 + 1.5 * np.exp(-np.arccos(np.clip(cos_g, -1, 1)) / 0.35)
    for centre, amp, width in clouds:
        base = base * (1 + amp * np.exp((d @ centre - 1) / width**2))
    sky = base[..., None] * np.array([0.6, 0.8, 1.1])
    ground = (0.25 + 0.05 * np.sin(5 * np.arctan2(d[..., 0], -d[..., 2])))[..., None] * np.array([1.0, 0.8, 0.6])
    out = np.where((y > 0)[..., None], sky, ground)
    disc = (cos_g >= math.cos(math.radians(1.5))) & (y > 0)
    return out + (disc * 2e5)[..., None] * np.array([1.0, 0.95, 0.9])


@lru_cache(maxsize=8)
def _scene(elevation_deg: float, cloudy: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(probe 128 x 256 float32, sun direction); 2 x 2 point samples per texel, area-averaged."""
    sun = direction_from_angles(math.radians(elevation_deg), math.radians(SUN_AZIMUTH_DEG))
    clouds = ()
    if cloudy:
        rng = np.random.default_rng(3)
        centres = rng.normal(size=(25, 3))
        centres[:, 1] = np.abs(centres[:, 1])
        centres /= np.linalg.norm(centres, axis=1, keepdims=True)
        clouds = [(c, rng.uniform(-0.4, 0.6), rng.uniform(0.08, 0.2)) for c in centres]
    fine = LatLongGrid(256, 512)
    return resample(_sky(fine.directions, sun, clouds), 128, 256).astype(np.float32), sun


def _reference(probe: np.ndarray) -> np.ndarray:
    return resample(probe, GRID.height, GRID.width)


def _cap_energy(probe: np.ndarray, sun: np.ndarray, radius_deg: float = 5.0) -> float:
    return float(np.sum(probe.sum(-1) * GRID.solid_angles * cap_mask(GRID, sun, radius_deg)))


def _errors(result, ref: np.ndarray, sun: np.ndarray, region: np.ndarray | None = None) -> dict:
    """Median relative error outside an 8 deg sun cap, sun angle (deg), sun-cap energy ratio."""
    region = result.coverage if region is None else region
    keep = region & ~cap_mask(GRID, sun, 8.0)
    rel = np.abs(result.radiance - ref).max(-1) / ref.max(-1)
    return {
        "median_rel": float(np.median(rel[keep])),
        "sun_deg": angle_deg(sun_direction(result.radiance, GRID), sun_direction(ref, GRID)),
        "energy": _cap_energy(result.radiance, sun) / _cap_energy(ref, sun),
    }


def _rotation_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1)))


# -- cameras and frames --------------------------------------------------------------------
def test_colmap_frame_conversion_on_known_directions():
    cam = ViewCamera.pinhole(90.0, 200, 100)
    d = np.array([[0, 0, -1.0], [0.1, 0, -1], [0, 0.1, -1], [0, 0, 1.0]])
    px, ok = cam.direction_to_pixel(d / np.linalg.norm(d, axis=1, keepdims=True))
    assert ok.tolist() == [True, True, True, False]  # behind the camera: invalid
    np.testing.assert_allclose(px[0], [100, 50], atol=1e-9)  # forward -> principal point
    assert px[1, 0] > 100 and abs(px[1, 1] - 50) < 1e-9  # camera right -> image right
    assert px[2, 1] < 50 and abs(px[2, 0] - 100) < 1e-9  # up -> image up (smaller row)
    np.testing.assert_allclose(COLMAP_FROM_F2L @ [0, 0, -1], [0, 0, 1])  # f2l forward = COLMAP +Z
    np.testing.assert_allclose(COLMAP_FROM_F2L @ [0, 1, 0], [0, -1, 0])  # f2l up = COLMAP -Y

    centre = np.array([100.0, 50.0])
    east = ViewCamera.pinhole(90.0, 200, 100, yaw_deg=90.0)  # looks at +X
    np.testing.assert_allclose(east.direction_to_pixel(np.array([[1.0, 0, 0]]))[0][0], centre, atol=1e-9)
    up = ViewCamera.pinhole(90.0, 200, 100, pitch_deg=90.0)  # looks at the zenith, image-up = +Z
    np.testing.assert_allclose(up.direction_to_pixel(np.array([[0, 1.0, 0]]))[0][0], centre, atol=1e-9)
    assert up.direction_to_pixel(np.array([[0, 0.9, -0.1]]))[0][0, 1] > 50  # world -Z: image-down
    rolled = ViewCamera.pinhole(90.0, 200, 100, roll_deg=90.0)  # camera right side lifted to +Y
    assert rolled.direction_to_pixel(np.array([[0, 0.1, -1.0]]) / math.hypot(0.1, 1))[0][0, 0] > 100
    d, ok = east.pixel_to_direction(np.array([[100.0, 50.0]]))
    np.testing.assert_allclose(d[0], [1, 0, 0], atol=1e-12)


@pytest.mark.parametrize("ypr", [(10, 20, 30), (170, -80, 5), (-120, 45, -170), (0, 90, 20), (30, -90, 0)])
def test_yaw_pitch_roll_round_trip(ypr):
    r = rotation_from_ypr(*np.radians(ypr))
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(rotation_from_ypr(*ypr_from_rotation(r)), r, atol=1e-12)  # gimbal lock too
    np.testing.assert_allclose(-r[:, 2], direction_from_angles(math.radians(ypr[1]), math.radians(ypr[0])),
                               atol=1e-12)  # optical axis = (elevation pitch, azimuth yaw)


def test_pycolmap_quirks_are_handled():
    """The pycolmap 4.2.1 behaviour the wrappers rely on (documented in cameras.py)."""
    col = pycolmap.Camera(model="OPENCV_FISHEYE", width=400, height=400, params=[100, 100, 200, 200, 0, 0, 0, 0])
    px = col.img_from_cam(np.array([[0.1, 0, 1.0], [1, 0, 0.0], [0.3, 0, -1.0]]))
    assert np.isfinite(px[0]).all() and np.isnan(px[1:]).all()  # cheirality: z <= 0 -> NaN
    theta = np.radians([10.0, 45.0, 80.0, 89.0])
    px = col.img_from_cam(np.stack([np.sin(theta), 0 * theta, np.cos(theta)], axis=1))
    np.testing.assert_allclose(px[:, 0] - 200, 100 * theta, rtol=1e-12)  # k = 0: equidistant r = f theta
    beyond = np.array([[200 + 100 * math.radians(120.0), 200.0]])  # theta_d = 120 deg > 90 deg
    assert np.isfinite(col.cam_from_img(beyond)).all()  # pycolmap returns a (wrong) finite ray ...
    cam = ViewCamera.from_model("OPENCV_FISHEYE", 400, 400, [100, 100, 200, 200, 0, 0, 0, 0])
    assert not cam.pixel_to_direction(beyond)[1][0]  # ... which the wrapper rejects
    with pytest.raises(ValueError, match="needs params"):
        ViewCamera.from_model("OPENCV_FISHEYE", 400, 400, [100, 100, 200, 200])  # pycolmap accepts it
    with pytest.raises(ValueError, match="unknown"):
        ViewCamera.from_model("NO_SUCH_MODEL", 10, 10, [1, 5, 5])
    with pytest.raises(ValueError, match="180"):
        ViewCamera.equidistant(190.0, 100, 100)


ROUND_TRIP_CAMERAS = {
    "equidistant": ViewCamera.equidistant(180.0, 300, 300, yaw_deg=20, pitch_deg=60, roll_deg=10),
    "equisolid": ViewCamera.equisolid(170.0, 320, 240, yaw_deg=-40, pitch_deg=10),
    "pinhole": ViewCamera.pinhole(70.0, 300, 200, yaw_deg=100, pitch_deg=-20, roll_deg=-5),
    "opencv": ViewCamera.from_model("OPENCV", 300, 200, [250, 255, 151, 99, -0.1, 0.02, 1e-3, -1e-3], yaw_deg=5),
    "opencv_fisheye": ViewCamera.from_model("OPENCV_FISHEYE", 300, 300, [90, 91, 150, 149, -0.02, 0.001, 0, 0],
                                            pitch_deg=90, max_angle_deg=85),
    "radial_fisheye": ViewCamera.from_model("RADIAL_FISHEYE", 300, 300, [95, 150, 150, -0.01, 0.0005]),
    "thin_prism": ViewCamera.from_model("THIN_PRISM_FISHEYE", 300, 300,
                                        [95, 95, 150, 150, -0.01, 0, 1e-4, 1e-4, 0, 0, 1e-4, 1e-4]),
    "ball_ortho": mirror_ball_view(300, 300, (150, 150), 140, yaw_deg=30),
    "ball_perspective": mirror_ball_view(300, 300, (151, 149), 120, pitch_deg=-10, distance_over_radius=6.0),
}


@pytest.mark.parametrize("name", sorted(ROUND_TRIP_CAMERAS))
def test_pixel_direction_round_trip(name):
    cam = ROUND_TRIP_CAMERAS[name]
    px = np.random.default_rng(0).uniform(0, [cam.width, cam.height], size=(4000, 2))
    d, ok = cam.pixel_to_direction(px)
    assert ok.mean() > 0.4
    np.testing.assert_allclose(np.linalg.norm(d[ok], axis=1), 1.0, atol=1e-12)
    back, ok2 = cam.direction_to_pixel(d[ok])
    assert ok2.all()
    assert np.abs(back - px[ok]).max() < 1e-6
    assert np.isnan(d[~ok]).all()


def test_equidistant_and_equisolid_radii():
    theta = np.radians(np.linspace(0.0, 89.5, 60))
    d_cam = np.stack([np.sin(theta), 0 * theta, -np.cos(theta)], axis=1)  # f2l camera frame
    eqd = ViewCamera.equidistant(180.0, 300, 300)
    f = eqd.colmap.focal_length_x
    np.testing.assert_allclose(f, 150 / (math.pi / 2))
    r = eqd.cam_direction_to_pixel(d_cam)[0][:, 0] - 150
    np.testing.assert_allclose(r, f * theta, rtol=1e-12, atol=1e-9)
    eqs = ViewCamera.equisolid(180.0, 300, 300)
    f = eqs.colmap.focal_length_x
    r = eqs.cam_direction_to_pixel(d_cam)[0][:, 0] - 150
    theta_back = 2 * np.arcsin(r / (2 * f))  # invert r = 2 f sin(theta / 2)
    assert np.abs(theta_back - theta).max() < 1e-9  # fitted OPENCV_FISHEYE k1..k4
    assert equisolid_max_error_rad(math.pi / 2) < 1e-9
    edge = eqs.cam_direction_to_pixel(np.array([[1.0, 0, -1e-9], [1.0, 0, 0]]))
    assert edge[0][0, 0] == pytest.approx(300, abs=1e-6)  # the 180 deg circle touches the border
    assert not edge[1][1]  # exactly 90 deg (z = 0) fails pycolmap's cheirality test


def test_vignetting_apply_then_correct():
    img = np.random.default_rng(1).uniform(0.1, 5e4, size=(60, 80, 3)).astype(np.float32)
    vig = Vignetting(-0.3, 0.05, -0.02)
    dark = apply_vignetting(img, vig)
    assert dark.dtype == np.float32 and (dark <= img * 1.0000001).all()
    np.testing.assert_allclose(correct_vignetting(dark, vig), img, rtol=1e-6)
    g = vig.gain(60, 80)
    assert g[29:31, 39:41].min() > 0.999  # ~1 at the principal point
    assert g[0, 0] == pytest.approx(1 - 0.3 + 0.05 - 0.02, abs=0.02)  # r ~ 1 in the corner
    np.testing.assert_allclose(vig.gain(60, 80, principal_point=(10.0, 20.0))[19:21, 9:11], 1.0, atol=1e-3)
    with pytest.raises(ValueError, match="not positive"):
        correct_vignetting(img, Vignetting(-1.5))


# -- assembly --------------------------------------------------------------------------------
@pytest.mark.parametrize("elevation_deg", [30.0, 90.0, 0.0])
def test_zenith_fisheye_assembly(elevation_deg):
    probe, sun = _scene(elevation_deg)
    ref = _reference(probe)
    sky = ref[: GRID.sky_rows]
    assert sky.max() / sky.min() >= 1e5  # HDR: sun vs darkest sky
    cam = ViewCamera.equidistant(180.0, 256, 256, pitch_deg=90.0)
    image, valid = render_view(probe, cam, supersample=2)
    assert image.dtype == np.float32 and not valid[0, 0] and valid[128, 128]
    result = assemble([View(image, cam, valid.astype(np.float32), name="zenith")], GRID.height, GRID.width)
    assert result.radiance.dtype == np.float32 and result.radiance.shape == (64, 128, 3)
    assert result.coverage[: GRID.sky_rows].all()  # the whole sky ...
    assert not result.coverage[GRID.sky_rows :].any()  # ... and never the ground under the lens
    assert not result.radiance[GRID.sky_rows :].any() and not result.saturated.any()
    err = _errors(result, ref, sun)
    assert err["median_rel"] <= 0.02
    assert err["sun_deg"] <= 1.0
    assert abs(err["energy"] - 1.0) <= 0.05
    stats = result.view_stats[0]
    assert stats.name == "zenith" and stats.covered_solid_angle_sr == pytest.approx(2 * math.pi, rel=1e-9)


def test_high_resolution_view_keeps_sun_energy():
    """A view with ~10 x 10 pixels per texel is reduced to boxes before splatting (area average)."""
    probe, sun = _scene(45.0)
    ref = _reference(probe)
    cam = ViewCamera.equidistant(180.0, 640, 640, pitch_deg=90.0)
    image, _ = render_view(probe, cam, supersample=1)  # pixels (0.28 deg) << probe texels (1.4 deg)
    result = assemble([(image, cam)], GRID.height, GRID.width)
    assert result.view_stats[0].pyramid_level >= 1
    err = _errors(result, ref, sun)
    assert err["median_rel"] <= 0.02 and err["sun_deg"] <= 1.0 and abs(err["energy"] - 1.0) <= 0.05


def test_rectilinear_cube_covers_the_sphere():
    probe, sun = _scene(30.0)
    ref = _reference(probe)
    poses = [(0, 0), (90, 0), (180, 0), (270, 0), (0, 90), (0, -90)]
    views = []
    for yaw, pitch in poses:
        cam = ViewCamera.pinhole(100.0, 128, 128, yaw_deg=yaw, pitch_deg=pitch)
        views.append(View(render_view(probe, cam, supersample=2)[0], cam, name=f"y{yaw}p{pitch}"))
    result = assemble(views, GRID.height, GRID.width)
    assert result.coverage.all()
    err = _errors(result, ref, sun)
    assert err["median_rel"] <= 0.02 and err["sun_deg"] <= 1.0 and abs(err["energy"] - 1.0) <= 0.05
    for s in result.view_stats:  # symmetric rig: equal shares, views agree where they overlap
        assert s.weight_share == pytest.approx(1 / 6, abs=0.01)
        assert s.median_ratio_to_blend == pytest.approx(1.0, abs=0.01)


def test_two_fisheyes_cover_sphere():
    probe, sun = _scene(0.0)
    ref = _reference(probe)
    cams = [ViewCamera.equidistant(180.0, 256, 256, yaw_deg=yaw) for yaw in (0.0, 180.0)]  # back to back
    views = [(render_view(probe, c, supersample=2)[0], c) for c in cams]
    result = assemble(views, GRID.height, GRID.width)
    assert result.coverage.all()  # texels on the seam are partly seen by both
    err = _errors(result, ref, sun)
    assert err["median_rel"] <= 0.02 and err["sun_deg"] <= 1.0 and abs(err["energy"] - 1.0) <= 0.05


def test_mirror_ball_mapping_and_assembly():
    ball = mirror_ball_view(300, 300, (150, 150), 140, reflectance=0.7)
    s45 = 140 * math.sin(math.radians(45))  # psi = 90 deg at s = sin(45 deg)
    dirs = np.array([[0, 0, 1.0], [0, 1.0, 0], [1.0, 0, 0], [0, 0, -1.0]])
    px, ok = ball.direction_to_pixel(dirs)
    assert ok.tolist() == [True, True, True, False]  # the direction behind the ball is blind
    np.testing.assert_allclose(px[:3], [[150, 150], [150, 150 - s45], [150 + s45, 150]], atol=1e-9)
    persp = mirror_ball_view(300, 300, (150, 150), 140, distance_over_radius=5.0)
    np.testing.assert_allclose(persp.psi_of_s(np.array([0.0, 1.0])), [0.0, math.pi - math.asin(0.2)], atol=1e-9)
    assert np.all(np.diff(persp.psi_of_s(np.linspace(0, 1, 200))) > 0)
    assert isinstance(ball, MirrorBallCamera)

    probe, sun = _scene(30.0)
    ref = _reference(probe)
    ball = dataclasses.replace(ball, yaw_rad=math.radians(-150.0))  # camera faces away from the sun
    image, valid = render_view(probe, ball)
    result = assemble([(image, ball, valid.astype(np.float32))], GRID.height, GRID.width)
    blind = cap_mask(GRID, -ball.rotation[:, 2], 5.0)  # around the camera's viewing direction
    assert not result.coverage[blind].any() and result.coverage.mean() > 0.97
    err = _errors(result, ref, sun)  # reflectance divided out
    assert err["median_rel"] <= 0.02 and err["sun_deg"] <= 1.0 and abs(err["energy"] - 1.0) <= 0.05


def test_saturated_texels_are_flagged_lower_bounds():
    probe, sun = _scene(45.0)
    ref = _reference(probe)
    up = ViewCamera.equidistant(180.0, 256, 256, pitch_deg=90.0)
    image, _ = render_view(probe, up, supersample=2)

    def clipped(level: float) -> View:
        return View(np.minimum(image, level), up, saturated=image.max(-1) >= level, name=f"clip{level:g}")

    low = assemble([clipped(1e3)], GRID.height, GRID.width)
    flagged = low.saturated
    assert flagged.any() and not (flagged & ~cap_mask(GRID, sun, 6.0)).any()
    assert low.coverage[flagged].all() and low.weight_sum[flagged].max() == 0.0
    assert (low.radiance[flagged] <= 1e3 * 1.0001).all()  # means of clipped pixels only ...
    sun_sr = GRID.solid_angles * flagged
    assert np.sum(low.radiance.sum(-1) * sun_sr) < 0.1 * _cap_energy(ref, sun)  # ... a lower bound
    high = assemble([clipped(2e3)], GRID.height, GRID.width)
    both = assemble([clipped(1e3), clipped(2e3)], GRID.height, GRID.width)
    assert (both.saturated == (low.saturated | high.saturated)).all()
    f = low.saturated & high.saturated  # lower bounds only: the largest one is kept, not a mean
    np.testing.assert_allclose(both.radiance[f], np.maximum(low.radiance[f], high.radiance[f]), rtol=1e-6)

    side = ViewCamera.equidistant(120.0, 256, 256, yaw_deg=SUN_AZIMUTH_DEG, pitch_deg=40.0)
    good = View(render_view(probe, side, supersample=2)[0], side, name="unsaturated")
    fixed = assemble([clipped(1e3), good], GRID.height, GRID.width)
    assert not fixed.saturated.any()  # measurements replace lower bounds, never averaged with them
    assert abs(_cap_energy(fixed.radiance, sun) / _cap_energy(ref, sun) - 1.0) <= 0.05
    assert fixed.view_stats[0].saturated_texels == flagged.sum()


def test_bad_views_raise_naming_the_view():
    cam = ViewCamera.equidistant(180.0, 32, 32, pitch_deg=90.0)
    good = np.ones((32, 32, 3), np.float32)
    for bad_value in (np.nan, np.inf):
        bad = good.copy()
        bad[3, 4, 1] = bad_value
        with pytest.raises(ValueError, match=r"view 1 \('east'\).*NaN or infinite"):
            assemble([View(good, cam), View(bad, cam, name="east")], 16, 32)
    with pytest.raises(ValueError, match=r"view 0 .*camera is 32x32"):
        assemble([(np.ones((16, 32, 3), np.float32), cam)], 16, 32)
    with pytest.raises(ValueError, match="at least one view"):
        assemble([], 16, 32)


def test_refine_rotations_recovers_a_yaw_error():
    probe, _ = _scene(35.0, cloudy=True)
    cams = [ViewCamera.equidistant(150.0, 200, 200, yaw_deg=y, pitch_deg=30.0) for y in (0.0, 100.0)]
    views = [View(render_view(probe, c, supersample=2)[0], c, name=f"v{i}") for i, c in enumerate(cams)]
    wrong = dataclasses.replace(cams[1], yaw_rad=cams[1].yaw_rad + math.radians(2.0))
    assert _rotation_error_deg(wrong.rotation, cams[1].rotation) == pytest.approx(2.0, abs=1e-9)
    result = refine_rotations([views[0], dataclasses.replace(views[1], camera=wrong)])
    assert result.success and result.final_cost < 0.1 * result.initial_cost
    assert np.all(result.correction_rotvec_rad[0] == 0)  # the first view is the fixed reference
    np.testing.assert_allclose(result.views[0].camera.rotation, cams[0].rotation)
    assert _rotation_error_deg(result.views[1].camera.rotation, cams[1].rotation) <= 0.2
