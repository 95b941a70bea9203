"""The skin's reflection of the environment (``EstimatorConfig.skin_reflection``, f2l.estimate.reflection)."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from f2l.estimate import EstimatorConfig, FaceObservation, estimate
from f2l.estimate.reflection import SkinReflection, sky_block_means_without_sun, sun_direction_of
from f2l.estimate.sky_transport import DEFAULT_BLOCK
from f2l.lighting.grid import LatLongGrid
from f2l.testing import check_model

GRID = LatLongGrid(32, 64)


def pixels(normals, views):
    """(normals, points) of pixels seen from ``views`` (unit, towards the camera): points = -view."""
    n = np.asarray(normals, float)
    v = np.asarray(views, float)
    return n / np.linalg.norm(n, axis=1, keepdims=True), -v / np.linalg.norm(v, axis=1, keepdims=True)


def test_a_uniform_sky_mirrored_straight_up_gives_pi_times_its_radiance():
    n, p = pixels([[0, 1, 0]], [[0, 1, 0]])  # mirror direction +Y
    refl = SkinReflection(n, p, GRID, DEFAULT_BLOCK, 16.0)
    nb = refl.num_blocks_in
    sky = torch.full((1, nb, 3), 2.0, dtype=torch.float64)
    out = refl.term(sky, torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64),
                    torch.zeros(1, 3, dtype=torch.float64))
    assert out.numpy() == pytest.approx(np.full((1, 1, 3), 2.0 * math.pi), rel=0.02)


@pytest.mark.parametrize("exponent", [1.0, 4.0, 16.0, 5.5])
def test_the_kernel_integrates_to_pi_over_the_sphere_for_any_mirror_direction(exponent):
    rng = np.random.default_rng(0)
    n, p = pixels(rng.normal(size=(40, 3)), rng.normal(size=(40, 3)))
    refl = SkinReflection(n, p, GRID, DEFAULT_BLOCK, exponent)
    total = refl.k_blocks.sum(1) + refl.k_ground
    assert total.numpy() == pytest.approx(np.full(40, math.pi), rel=0.03)


def test_the_sun_is_mirrored_exactly_and_not_where_the_mirror_looks_away():
    n, p = pixels([[0, 0, 1], [0, 0, 1]], [[0, 0, 1], [0.0, 0.6, 0.8]])
    refl = SkinReflection(n, p, GRID, DEFAULT_BLOCK, 16.0)
    r = refl.mirror.numpy()
    assert r[0] == pytest.approx([0, 0, 1])
    assert r[1] == pytest.approx([0, -0.6, 0.8])  # mirrored about the normal
    w_sun = torch.tensor([[1.0, 2.0, 3.0]], dtype=torch.float64)
    zero_sky = torch.zeros(1, refl.num_blocks_in, 3, dtype=torch.float64)
    out = refl.term(zero_sky, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), w_sun,
                    torch.zeros(1, 3, dtype=torch.float64)).numpy()[0]
    assert out[0] == pytest.approx(8.5 * np.array([1.0, 2.0, 3.0]))  # (p + 1) / 2 at the lobe's centre
    assert out[1] == pytest.approx(8.5 * 0.8**16 * np.array([1.0, 2.0, 3.0]))
    away = refl.term(zero_sky, torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64), w_sun,
                     torch.zeros(1, 3, dtype=torch.float64))
    assert float(away.abs().max()) == 0.0


def test_block_means_without_the_sun_are_the_skys_alone():
    from f2l.estimate.sky_transport import SkyTransport
    from f2l.transport.operator import Transport

    model = check_model("sunsky", GRID)
    n_pix = 8
    bits = np.full((n_pix, (GRID.size + 7) // 8), 255, np.uint8)
    normals = np.tile([[0.0, 0.0, 1.0]], (n_pix, 1))
    hybrid = SkyTransport(Transport(bits, normals, GRID), GRID)
    params = torch.tensor([[1.0, 1.2, 1.5, 30.0, 28.0, 25.0, 0.6, 0.3, 2.5, 3000.0]], dtype=torch.float64)
    rad, sun = model.radiance_parts(params)
    no_sun = params.clone()
    no_sun[:, 3:6] = 0.0
    sky_only, _ = model.radiance_parts(no_sun)
    L = GRID.sky_rows * GRID.width
    got = sky_block_means_without_sun(hybrid, rad[:, :L], sun)
    want = hybrid.block_means(sky_only[:, :L])
    assert got.numpy() == pytest.approx(want.numpy(), rel=1e-9, abs=1e-9)
    d = sun_direction_of(params, model.sun_layout).numpy()[0]
    assert d == pytest.approx(model.sun_direction(params.numpy()[0]), abs=1e-9)


def test_pooled_blocks_give_the_unpooled_term_on_a_sky_constant_over_them_and_near_it_on_a_smooth_one():
    grid = LatLongGrid(64, 128)  # pooled there (22.5 deg blocks), not on coarser grids
    rng = np.random.default_rng(3)
    n, p = pixels(rng.normal(size=(30, 3)) + [0, 2, 0], rng.normal(size=(30, 3)) + [0, 0, 2])
    pooled = SkinReflection(n, p, grid, DEFAULT_BLOCK, 16.0, pool=2)
    plain = SkinReflection(n, p, grid, DEFAULT_BLOCK, 16.0, pool=1)
    assert pooled.num_blocks_in == plain.num_blocks_in == plain.k_blocks.shape[1] == 4 * pooled.k_blocks.shape[1]
    assert SkinReflection(n, p, GRID, DEFAULT_BLOCK, 16.0, pool=2).k_blocks.shape[1] == GRID.sky_rows * GRID.width // 16
    nbr, nbc = grid.sky_rows // DEFAULT_BLOCK[0], grid.width // DEFAULT_BLOCK[1]
    zero = torch.zeros(1, 3, dtype=torch.float64)
    sun = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
    coarse = rng.uniform(0.5, 2.0, size=(nbr // 2, nbc // 2, 3))  # constant over each pooled block
    sky = torch.as_tensor(np.repeat(np.repeat(coarse, 2, 0), 2, 1).reshape(1, -1, 3))
    assert pooled.term(sky, sun, zero, zero).numpy() == pytest.approx(plain.term(sky, sun, zero, zero).numpy(), rel=1e-9)
    # brighter towards the horizon (x 1.8) and on one side (+-50%), bluer at the zenith: within 5%
    # of the plain blocks where the mirror grazes the horizon, 1.5% on average
    el = 1.0 - (np.arange(nbr)[:, None] + 0.5) / nbr
    az = (np.arange(nbc)[None, :] + 0.5) / nbc
    smooth = (1.0 + 0.8 * (1 - el) + 0.5 * np.cos(2 * np.pi * az))[:, :, None] * (1 + el[:, :, None] * [-0.2, 0, 0.3])
    sky = torch.as_tensor(smooth.reshape(1, -1, 3))
    got, want = pooled.term(sky, sun, zero, zero).numpy(), plain.term(sky, sun, zero, zero).numpy()
    assert got == pytest.approx(want, rel=0.05)
    assert np.abs(got / want - 1).mean() < 0.015


def test_the_transport_takes_block_means_computed_once_for_several_pixel_sets():
    from f2l.estimate.sky_transport import SkyTransport
    from f2l.transport.operator import Transport

    rng = np.random.default_rng(4)
    model = check_model("sunsky", GRID)
    bits = rng.integers(0, 256, size=(12, (GRID.size + 7) // 8), dtype=np.uint8)
    normals = rng.normal(size=(12, 3)) + [0, 0, 2]
    hybrid = SkyTransport(Transport(bits, normals / np.linalg.norm(normals, axis=1, keepdims=True), GRID), GRID)
    params = torch.tensor([[1.0, 1.2, 1.5, 30.0, 28.0, 25.0, 0.6, 0.3, 2.5, 3000.0]], dtype=torch.float64)
    rad, sun = model.radiance_parts(params)
    l_sky = rad[:, : GRID.sky_rows * GRID.width]
    shared = hybrid.apply(l_sky, sun, hybrid.block_means(l_sky))
    assert torch.equal(shared, hybrid.apply(l_sky, sun))


@pytest.fixture(scope="module")
def glossy_face():
    """A sunny own render with the reflection of its true probe added to the photo (g_r = 0.02)."""
    from f2l.synth.render import make_synthetic_set

    face = next(f for f in make_synthetic_set(4, GRID, 5, image_size=96, threads=1)
                if f.meta.get("sky", {}).get("kind") != "overcast")
    mask = np.asarray(face.mask)
    n = np.asarray(face.normals, float)
    v = -np.asarray(face.points, float)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    r = 2 * (n * v).sum(1, keepdims=True) * n - v
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    fine = LatLongGrid(*face.gt_probe.shape[:2])  # the truth's own grid, not the term's blocks
    k = 8.5 * np.clip(r @ fine.directions_flat.T, 0, None) ** 16 * fine.solid_angles_flat[None]
    mirrored = k @ face.gt_probe.reshape(-1, 3).astype(np.float64)
    photo = np.asarray(face.observed_rgb, float) + 0.02 * mirrored * mask[:, None]
    obs = FaceObservation(face.normals, photo, face.mask, face.visibility_bits, GRID, points=face.points)
    return obs, np.asarray(face.meta["sky"]["sun_direction"], float)


def angle_deg(a, b) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def test_the_estimator_reads_a_mirrored_environment_with_the_term_and_is_unchanged_without_it(glossy_face):
    obs, sun = glossy_face
    model = check_model("sunsky", GRID)
    base = EstimatorConfig(threads=1, skin_gloss=0.0, skin_reflection=0.0, sun_prior_from_capture=False)
    off = estimate(obs, model, base)
    on = estimate(obs, model, dataclasses.replace(base, skin_reflection=0.02))
    assert np.isfinite(on.probe).all() and on.probe.min() >= 0
    assert on.loss < off.loss  # the photo is explained better with the term
    assert angle_deg(on.sun_direction, sun) < 5.0
    # without 3-D points there is no view direction and so no term: the estimate is the plain one
    no_points = estimate(dataclasses.replace(obs, points=None), model, dataclasses.replace(base, skin_reflection=0.02))
    assert no_points.loss == pytest.approx(off.loss, rel=1e-12)
