"""Synthetic data: canonical face mesh, ground-truth skies, rendered faces."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest

from f2l.lighting.grid import LatLongGrid, direction_from_angles
from f2l.face import mesh as facemesh
from f2l.face.mesh import FaceMeshError, canonical_face_mesh, default_task_path, face_mesh
from f2l.synth.render import make_synthetic_set, render_face
from f2l.synth.skies import (
    clear_sky,
    horizontal_irradiance,
    overcast_sky,
    random_sky,
    sun_lobe_energy,
    sun_rgb_irradiance,
)

SMALL = LatLongGrid(16, 32)
ALBEDO = np.array([0.55, 0.38, 0.30])


# -- face mesh ----------------------------------------------------------------------------------
def test_canonical_mesh_parse():
    v, f, uv = canonical_face_mesh()
    assert v.shape == (468, 3) and v.dtype == np.float64
    assert f.shape == (898, 3) and f.dtype == np.int64
    assert uv.shape == (468, 2)
    assert f.min() == 0 and f.max() == 467
    assert np.all((uv >= 0) & (uv <= 1))
    # cm, +Y up, +Z out of the face: the nose tip (landmark 1) is near the front.
    assert 10 < np.ptp(v[:, 1]) < 25
    assert v[facemesh.NOSE_TIP_INDEX, 2] > np.percentile(v[:, 2], 95)
    assert canonical_face_mesh() is canonical_face_mesh()  # cached


def test_mesh_orientation_and_subdivision():
    import trimesh

    v, f, _ = canonical_face_mesh()
    m0 = trimesh.Trimesh(np.array(v), np.array(f), process=False)
    assert not m0.is_watertight  # an open face mask ...
    assert m0.is_winding_consistent  # ... consistently oriented
    assert (m0.face_normals[:, 2] > 0).mean() > 0.9
    m = face_mesh(2)
    assert len(m.faces) == 898 * 16
    assert m.is_winding_consistent
    n = m.vertex_normals
    near_nose = np.argmin(np.linalg.norm(m.vertices - v[facemesh.NOSE_TIP_INDEX], axis=1))
    assert n[near_nose, 2] > 0.5
    assert (n[:, 2] > 0).mean() > 0.99


def test_sha_mismatch_and_override(tmp_path, monkeypatch):
    src = default_task_path()
    good = tmp_path / "good.task"
    shutil.copy(src, good)
    v, _, _ = canonical_face_mesh(good)
    assert v.shape == (468, 3)
    bad = tmp_path / "bad.task"
    data = bytearray(good.read_bytes())
    data[-1] ^= 0xFF
    bad.write_bytes(bytes(data))
    with pytest.raises(FaceMeshError, match="SHA-256 mismatch"):
        canonical_face_mesh(bad)
    monkeypatch.setenv("F2L_FACE_LANDMARKER", str(bad))
    with pytest.raises(FaceMeshError, match="bad.task"):
        canonical_face_mesh()
    monkeypatch.setenv("F2L_FACE_LANDMARKER", str(tmp_path / "missing.task"))
    with pytest.raises(FaceMeshError, match="not found"):
        canonical_face_mesh()


# -- skies --------------------------------------------------------------------------------------
def _sun_positions(n, seed=0):
    rng = np.random.default_rng(seed)
    dirs = [
        np.array([0.0, 1.0, 0.0]),  # zenith
        np.array([0.0, -1.0, 0.0]),  # nadir
        direction_from_angles(0.0, 0.3),  # horizon
        direction_from_angles(0.0, -2.9),
        direction_from_angles(math.radians(89.3), 1.0),  # just off the zenith
    ]
    while len(dirs) < n:
        d = rng.normal(size=3)
        dirs.append(d / np.linalg.norm(d))
    return dirs


@pytest.mark.parametrize("kappa", [8.0, 1024.0, 8192.0])
@pytest.mark.parametrize("grid", [LatLongGrid(64, 128), LatLongGrid(32, 128)], ids=str)
def test_sun_lobe_energy(kappa, grid):
    for d in _sun_positions(50):
        e = sun_lobe_energy(grid, d, kappa)
        assert e.shape == grid.shape and np.all(np.isfinite(e)) and e.min() >= 0
        assert abs(float(np.sum(e * grid.solid_angles)) - 1.0) < 0.01
        # the lobe's peak is at the sun
        r, c = np.unravel_index(np.argmax(e), e.shape)
        assert grid.directions[r, c] @ d > math.cos(math.radians(4.0)) or kappa < 100


def _check_ground(grid, probe, rho):
    n = grid.sky_rows
    ground = probe[n:]
    assert np.allclose(ground, ground[0, 0][None, None], rtol=0, atol=0)
    sky_only = probe.astype(np.float64).copy()
    sky_only[n:] = 0
    e_h = horizontal_irradiance(grid, sky_only)
    np.testing.assert_allclose(ground[0, 0], rho / math.pi * e_h, rtol=1e-5)


@pytest.mark.parametrize("elev_deg", [5.0, 30.0, 80.0, 90.0])
def test_clear_sky(elev_deg):
    grid = LatLongGrid(64, 128)
    p = clear_sky(grid, math.radians(elev_deg), 1.2, turbidity=3.0, ground_albedo=0.3)
    assert p.dtype == np.float32 and p.shape == (64, 128, 3)
    assert np.all(np.isfinite(p)) and p.min() >= 0
    _check_ground(grid, p, 0.3)
    # the brightest texel is the sun, which dominates the sky
    sun = direction_from_angles(math.radians(elev_deg), 1.2)
    lum = p @ np.array([0.2126, 0.7152, 0.0722])
    r, c = np.unravel_index(np.argmax(lum), lum.shape)
    assert grid.directions[r, c] @ sun > math.cos(math.radians(3.0))
    # sky horizontal irradiance 0.15 - 0.25 of the sun's normal irradiance (luminance)
    sun_rgb = sun_rgb_irradiance(math.radians(elev_deg), 3.0)
    lobe = sun_lobe_energy(grid, sun, 8192.0)
    sky = p.astype(np.float64)
    sky[: grid.sky_rows] -= lobe[: grid.sky_rows, :, None] * sun_rgb
    ratio = (horizontal_irradiance(grid, sky) @ [0.2126, 0.7152, 0.0722]) / (
        sun_rgb @ [0.2126, 0.7152, 0.0722]
    )
    assert 0.14 < ratio < 0.26
    # blue away from the sun at the zenith-ish sky, for a low sun
    if elev_deg < 40:
        assert p[2, 0, 2] > p[2, 0, 0]


def test_overcast_and_random_sky():
    grid = LatLongGrid(32, 64)
    p = overcast_sky(grid, brightness=2.0, ground_albedo=0.2)
    assert np.all(np.isfinite(p)) and p.min() >= 0
    _check_ground(grid, p, 0.2)
    assert np.allclose(p[..., 0], p[..., 1]) and np.allclose(p[..., 1], p[..., 2])
    assert p[0, 0, 0] > p[grid.sky_rows - 1, 0, 0]  # zenith 3x brighter than the horizon
    kinds = set()
    for seed in range(12):
        probe, info = random_sky(grid, np.random.default_rng(seed), overcast_fraction=0.5)
        probe2, info2 = random_sky(grid, np.random.default_rng(seed), overcast_fraction=0.5)
        assert np.array_equal(probe, probe2) and info == info2
        assert np.all(np.isfinite(probe)) and probe.min() >= 0
        kinds.add(info["kind"])
        if info["kind"] == "clear":
            assert 5 <= info["sun_elevation_deg"] <= 80
            assert -180 <= info["sun_azimuth_deg"] <= 180
            assert 2 <= info["turbidity"] <= 6
            np.testing.assert_allclose(np.linalg.norm(info["sun_direction"]), 1.0)
    assert kinds == {"clear", "overcast"}


# -- rendering ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sunny_face():
    rng = np.random.default_rng(3)
    probe = clear_sky(SMALL, math.radians(35.0), math.radians(40.0), turbidity=3.0)
    return render_face(SMALL, probe, rng, image_size=64, albedo=ALBEDO, noise_sigma=0.002)


def test_render_record(sunny_face):
    f = sunny_face
    n = f.num_pixels
    assert f.photo_srgb.shape == (64, 64, 3) and f.photo_srgb.dtype == np.uint8
    assert 1500 < n < 3000  # ~ 1/4 of the ~8.5k pixels at 128^2
    assert f.pixel_rc.shape == (n, 2) and f.pixel_rc.dtype == np.int32
    assert f.points.shape == f.normals.shape == f.observed_rgb.shape == (n, 3)
    assert f.visibility_bits.shape == (n, (SMALL.size + 7) // 8)
    assert f.gt_probe.shape == (16, 32, 3) and f.gt_probe.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(f.normals, axis=1), 1.0, atol=1e-5)
    assert np.all(f.points[:, 2] < -40) and np.all(f.points[:, 2] > -80)
    # exposure: the 98th percentile of the clean face values is 0.85
    np.testing.assert_allclose(np.percentile(f.clean_rgb, 98), 0.85, rtol=1e-4)
    assert f.mask.mean() > 0.8


def test_quantisation(sunny_face):
    import colour

    f = sunny_face
    codes = f.photo_srgb[f.pixel_rc[:, 0], f.pixel_rc[:, 1]]
    expected = colour.cctf_decoding(codes / 255.0, function="sRGB").astype(np.float32)
    assert np.array_equal(f.observed_rgb, expected)
    clipped = (codes == 255).any(axis=1) | (codes <= 2).all(axis=1)
    assert np.array_equal(f.mask, ~clipped)


def test_constant_probe_unoccluded():
    """Under a constant white probe of radiance 1, shading = albedo x (T @ 1) <= albedo, equal to
    the unoccluded cosine integral where nothing is blocked and ~albedo on camera-facing cheeks."""
    grid = LatLongGrid(32, 64)
    probe = np.ones((32, 64, 3), np.float32)
    f = render_face(
        grid, probe, np.random.default_rng(0), image_size=48, albedo=[1.0, 1.0, 1.0],
        head_pose_deg=(0, 0, 0),
    )
    s = f.clean_rgb[:, 1].astype(np.float64) / f.meta["exposure_scale"]
    n = f.normals.astype(np.float64)
    cos = np.maximum(n @ grid.directions_flat.T, 0.0)
    unoccluded = (cos * grid.solid_angles_flat).sum(axis=1) / math.pi
    assert np.all(s <= unoccluded + 1e-4)
    assert np.all(unoccluded < 1.01)
    bits = np.unpackbits(f.visibility_bits, axis=1, count=grid.size, bitorder="little")
    free = ((bits == 1) == (cos > 0)).all(axis=1)
    assert free.mean() > 0.2
    np.testing.assert_allclose(s[free], unoccluded[free], rtol=1e-4)
    # camera-facing cheek pixels: right / left of the nose, below the eyes
    cheek = (n[:, 2] > 0.9) & (np.abs(f.points[:, 0]) > 3) & (f.points[:, 1] < 0)
    assert cheek.sum() > 10
    assert np.median(s[cheek]) > 0.97


def test_render_determinism():
    a = list(make_synthetic_set(2, SMALL, seed=7, image_size=40, albedo=ALBEDO, noise_sigma=0.01))
    b = list(make_synthetic_set(2, SMALL, seed=7, image_size=40, albedo=ALBEDO, noise_sigma=0.01))
    c = list(make_synthetic_set(1, SMALL, seed=8, image_size=40, noise_sigma=0.01))
    c2 = list(make_synthetic_set(1, SMALL, seed=8, image_size=40, noise_sigma=0.01))
    assert np.array_equal(c[0].albedo, c2[0].albedo) and np.array_equal(c[0].photo_srgb, c2[0].photo_srgb)
    assert np.all((c[0].albedo > 0) & (c[0].albedo <= 1))
    for x, y in zip(a, b):
        for name in ("photo_srgb", "pixel_rc", "points", "normals", "observed_rgb", "mask",
                     "visibility_bits", "gt_probe", "clean_rgb"):
            assert np.array_equal(getattr(x, name), getattr(y, name)), name
        assert x.meta == y.meta
    assert not np.array_equal(a[0].photo_srgb, c[0].photo_srgb)
    assert a[0].meta["index"] == 0 and a[1].meta["index"] == 1
    # ground truth is exposure-scaled to the observation's units
    assert a[0].meta["sky"]["kind"] in ("clear", "overcast")
