"""Tests for f2l.lighting.sh (real SH, polar axis +Y, theta = atan2(x, -z), no CS phase)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.polynomial import legendre as npleg
from scipy.special import lpmv

from f2l.lighting import sh
from f2l.lighting.grid import LatLongGrid, direction_from_angles, rotate_y

RNG = np.random.default_rng(1234)


def _random_dirs(n: int) -> np.ndarray:
    d = RNG.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_num_coeffs_and_index():
    assert [sh.num_coeffs(o) for o in range(5)] == [1, 4, 9, 16, 25]
    assert sh.sh_index(0, 0) == 0 and sh.sh_index(1, -1) == 1 and sh.sh_index(2, 2) == 8
    assert list(sh.sh_band_of_index(9)) == [0, 1, 1, 1, 2, 2, 2, 2, 2]
    with pytest.raises(ValueError):
        sh.num_coeffs(-1)


def test_explicit_low_order_formulas():
    d = _random_dirs(50)
    x, y, z = d.T
    Y = sh.sh_basis(d, 2)
    c1 = math.sqrt(3.0 / (4.0 * math.pi))
    np.testing.assert_allclose(Y[:, 0], 1.0 / (2.0 * math.sqrt(math.pi)), rtol=1e-14)
    np.testing.assert_allclose(Y[:, 1], c1 * x, atol=1e-14)  # Y_1,-1: sin(theta) sin(phi) = x
    np.testing.assert_allclose(Y[:, 2], c1 * y, atol=1e-14)  # Y_1,0
    np.testing.assert_allclose(Y[:, 3], -c1 * z, atol=1e-14)  # Y_1,1: cos(theta) sin(phi) = -z
    # Band 2 (no Condon-Shortley phase): Y_2,-2 ~ 2 x (-z), Y_2,-1 ~ x y, Y_2,0 ~ 3y^2 - 1.
    c2 = 0.5 * math.sqrt(15.0 / math.pi)
    np.testing.assert_allclose(Y[:, 4], c2 * x * (-z), atol=1e-14)
    np.testing.assert_allclose(Y[:, 5], c2 * x * y, atol=1e-14)
    np.testing.assert_allclose(Y[:, 6], 0.25 * math.sqrt(5.0 / math.pi) * (3 * y * y - 1), atol=1e-14)
    np.testing.assert_allclose(Y[:, 7], c2 * y * (-z), atol=1e-14)
    np.testing.assert_allclose(Y[:, 8], 0.5 * c2 * (z * z - x * x), atol=1e-14)
    # The camera's viewing direction (-Z) is theta = 0, where Y_11 is positive.
    assert sh.sh_basis(np.array([0.0, 0.0, -1.0]), 1)[3] > 0


def test_matches_scipy_reference_to_order_6():
    order = 6
    d = _random_dirs(200)
    d[0] = [0.0, 1.0, 0.0]  # poles
    d[1] = [0.0, -1.0, 0.0]
    Y = sh.sh_basis(d, order)
    phi = np.arccos(np.clip(d[:, 1], -1, 1))
    theta = np.arctan2(d[:, 0], -d[:, 2])
    for l in range(order + 1):  # noqa: E741
        for m in range(-l, l + 1):
            am = abs(m)
            n_lm = math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - am) / math.factorial(l + am))
            p = lpmv(am, l, np.cos(phi)) * (-1.0) ** am  # undo scipy's Condon-Shortley phase
            az = {1: math.sqrt(2) * np.cos(m * theta), 0: 1.0, -1: math.sqrt(2) * np.sin(am * theta)}
            ref = n_lm * p * az[int(np.sign(m))]
            np.testing.assert_allclose(Y[:, l * (l + 1) + m], ref, atol=1e-12)


def test_basis_shapes_and_high_order_is_finite():
    d = _random_dirs(12).reshape(3, 4, 3)
    assert sh.sh_basis(d, 4).shape == (3, 4, 25)
    # Stable recursion: high orders stay finite, and sum_m Y_lm^2 = (2l + 1) / (4 pi).
    Y = sh.sh_basis(_random_dirs(20), 60)
    assert np.all(np.isfinite(Y))
    l = 60  # noqa: E741
    band = Y[:, l * l : (l + 1) ** 2]
    np.testing.assert_allclose((band**2).sum(axis=1), (2 * l + 1) / (4 * math.pi), rtol=1e-10)


def test_orthonormality_by_quadrature():
    grid = LatLongGrid(256, 512)
    B = sh.sh_basis_grid(grid, 6)
    gram = B.T @ (B * grid.solid_angles_flat[:, None])
    np.testing.assert_allclose(gram, np.eye(49), atol=1e-4)


def test_basis_grid_is_cached_and_readonly():
    grid = LatLongGrid(16, 32)
    a = sh.sh_basis_grid(grid, 2)
    assert a is sh.sh_basis_grid(LatLongGrid(16, 32), 2)
    assert a.shape == (16 * 32, 9) and not a.flags.writeable
    np.testing.assert_allclose(a, sh.sh_basis(grid.directions_flat, 2))


def test_texel_mean_basis_matches_subsampling():
    grid = LatLongGrid(8, 16)
    mean = sh.sh_texel_mean_grid(grid, 4)
    assert mean.shape == (128, 25) and not mean.flags.writeable
    s = 40  # brute force: average centre values of a 40x40 sub-grid in each texel (O(1/s^2))
    fine = LatLongGrid(8 * s, 16 * s)
    weighted = sh.sh_basis_grid(fine, 4) * fine.solid_angles_flat[:, None]
    brute = weighted.reshape(8, s, 16, s, 25).sum(axis=(1, 3)).reshape(-1, 25)
    np.testing.assert_allclose(mean, brute / grid.solid_angles_flat[:, None], atol=1e-4)
    # Integrates each Y_k exactly: int Y_00 = sqrt(4 pi), the others vanish.
    integral = grid.solid_angles_flat @ mean
    # a 128-term float64 dot product in any order: |error| <= 128 * 2^-53 * sum|w mean| = 5e-14
    np.testing.assert_allclose(integral, np.eye(25)[0] * math.sqrt(4 * math.pi), atol=1e-13)


def test_project_constant_is_exact():
    grid = LatLongGrid(32, 64)
    c = sh.project(np.full((32, 64, 3), 2.5), grid, 4)
    assert c.shape == (25, 3)
    np.testing.assert_allclose(c[0], 2.5 * math.sqrt(4 * math.pi), rtol=1e-13)
    np.testing.assert_allclose(c[1:], 0.0, atol=1e-13)
    np.testing.assert_allclose(sh.reconstruct(c, grid), 2.5, rtol=1e-13)
    # Midpoint rule: c_00 exact, even m = 0 bands leak O((pi/H)^2); odd bands and m != 0 exact.
    cp = sh.project(np.full((32, 64), 2.5), grid, 4, quadrature="point")
    assert cp.shape == (25,)
    assert cp[0] == pytest.approx(2.5 * math.sqrt(4 * math.pi), rel=1e-13)
    np.testing.assert_allclose(cp[1:], 0.0, atol=5e-3 * 2.5)
    band = sh.sh_band_of_index(25)
    exact_zero = np.array([(l % 2 == 1) or k != l * (l + 1) for k, l in enumerate(band)])
    np.testing.assert_allclose(cp[exact_zero], 0.0, atol=1e-12)
    assert sh.reconstruct(cp, grid).shape == (32, 64)
    with pytest.raises(ValueError):
        sh.project(np.ones((16, 64)), grid, 2)
    with pytest.raises(ValueError):
        sh.project(np.ones((32, 64)), grid, 2, quadrature="simpson")


def test_project_reconstruct_band_limited():
    grid = LatLongGrid(256, 512)
    coeffs = RNG.normal(size=(25, 3))
    probe = sh.reconstruct(coeffs, grid)
    assert probe.shape == (256, 512, 3)
    for quadrature, tol in (("texel", 2e-4), ("point", 5e-5)):
        back = sh.project(probe, grid, 4, quadrature=quadrature)
        np.testing.assert_allclose(back, coeffs, atol=tol * np.abs(coeffs).max())
    # Reconstruct is linear and exact at texel centres.
    np.testing.assert_allclose(probe.reshape(-1, 3), sh.sh_basis(grid.directions_flat, 4) @ coeffs, atol=1e-12)


def test_lambert_band_factors():
    a = sh.lambert_band_factors(8)
    expected = [math.pi, 2 * math.pi / 3, math.pi / 4, 0.0, -math.pi / 24, 0.0, math.pi / 64, 0.0]
    np.testing.assert_allclose(a[:8], expected, atol=1e-15)
    # Funk-Hecke: A_l = 2 pi int_0^1 t P_l(t) dt, by Gauss-Legendre on [0, 1] (exact for polys).
    t, w = npleg.leggauss(20)
    t, w = 0.5 * (t + 1), 0.5 * w
    for l in range(9):  # noqa: E741
        p_l = npleg.legval(t, [0] * l + [1])
        assert a[l] == pytest.approx(2 * math.pi * np.sum(w * t * p_l), abs=1e-13)


def test_irradiance_of_constant_radiance_is_pi():
    # Exactly pi from the exact coefficient vector (c_00 = sqrt(4 pi), rest 0) and a probe.
    c = np.zeros((25, 3))
    c[0] = math.sqrt(4 * math.pi)
    irr = sh.irradiance_coeffs(c, 4)
    np.testing.assert_allclose(sh.sh_basis(_random_dirs(30), 4) @ irr, math.pi, rtol=1e-14)
    grid = LatLongGrid(64, 128)
    irr = sh.irradiance_coeffs(sh.project(np.ones((*grid.shape, 3)), grid, 4), 4)
    np.testing.assert_allclose(sh.reconstruct(irr, grid), math.pi, rtol=1e-13)
    irr = sh.irradiance_coeffs(sh.project(np.ones(grid.shape), grid, 4, quadrature="point"), 4)
    np.testing.assert_allclose(sh.reconstruct(irr, grid), math.pi, rtol=2e-4)
    with pytest.raises(ValueError):
        sh.irradiance_coeffs(c, 2)


def test_irradiance_of_band1_radiance():
    """Radiance Y_1m gives irradiance (2 pi / 3) Y_1m; checked by brute-force convolution."""
    grid = LatLongGrid(128, 256)
    normals = _random_dirs(40)
    omega = grid.directions_flat
    kernel = np.maximum(0.0, normals @ omega.T) * grid.solid_angles_flat  # (N, L)
    for k in (1, 2, 3):
        radiance = sh.sh_basis_grid(grid, 1)[:, k]
        brute = kernel @ radiance
        analytic = (2 * math.pi / 3) * sh.sh_basis(normals, 1)[:, k]
        np.testing.assert_allclose(brute, analytic, atol=2e-4)
        coeffs = np.zeros(4)
        coeffs[k] = 1.0
        irr = sh.irradiance_coeffs(coeffs)
        np.testing.assert_allclose(sh.sh_basis(normals, 1) @ irr, analytic, atol=1e-14)


def test_irradiance_of_narrow_light():
    grid = LatLongGrid(128, 256)
    order = 4
    row, col = 30, 170
    power = 7.0  # radiance * solid angle of the single lit texel
    probe = np.zeros(grid.shape)
    probe[row, col] = power / grid.solid_angles[row, col]
    w = grid.directions[row, col]
    coeffs = sh.project(probe, grid, order, quadrature="point")
    np.testing.assert_allclose(coeffs, power * sh.sh_basis(w, order), rtol=1e-12)
    # The texel rule sees the texel as a small area light: same to O(texel size^2).
    np.testing.assert_allclose(sh.project(probe, grid, order), coeffs, atol=1e-3 * power)

    normals = _random_dirs(60)
    irr_sh = sh.sh_basis(normals, order) @ sh.irradiance_coeffs(coeffs, order)

    # (a) Brute-force convolution of the band-limited radiance with max(0, n.w).
    fine = LatLongGrid(192, 384)
    radiance_bl = sh.reconstruct(coeffs, fine).reshape(-1)
    kernel = np.maximum(0.0, normals @ fine.directions_flat.T) * fine.solid_angles_flat
    np.testing.assert_allclose(kernel @ radiance_bl, irr_sh, atol=2e-3 * power)

    # (b) Independent 1-D Legendre expansion of the clamped cosine truncated at l = order.
    t_q, w_q = npleg.leggauss(400)
    clamped = np.maximum(0.0, t_q)
    cos_nw = normals @ w
    expansion = np.zeros_like(cos_nw)
    for l in range(order + 1):  # noqa: E741
        p_l = [0] * l + [1]
        c_l = 2 * math.pi * np.sum(w_q * clamped * npleg.legval(t_q, p_l))
        expansion += (2 * l + 1) / (4 * math.pi) * c_l * npleg.legval(cos_nw, p_l)
    np.testing.assert_allclose(irr_sh, power * expansion, atol=1e-4 * power)

    # (c) Against the exact clamped cosine, within the order-4 truncation error (max 0.0586).
    np.testing.assert_allclose(irr_sh, power * np.maximum(0.0, cos_nw), atol=0.06 * power)
    facing = cos_nw > 0.5
    np.testing.assert_allclose(irr_sh[facing], power * cos_nw[facing], atol=0.03 * power)


@pytest.mark.parametrize("cols", [1, 5, -13, 64])
def test_rotate_y_coeffs_matches_column_roll(cols):
    grid = LatLongGrid(32, 128)
    probe = RNG.random((32, 128, 3))
    probe[5, 40] += 50.0
    angle = cols * 2 * math.pi / grid.width
    rotated = rotate_y(probe, angle)
    for quadrature in ("texel", "point"):
        c_rot = sh.project(rotated, grid, 4, quadrature=quadrature)
        c_sh = sh.rotate_y_coeffs(sh.project(probe, grid, 4, quadrature=quadrature), angle)
        np.testing.assert_allclose(c_sh, c_rot, atol=1e-10)


def test_rotate_y_coeffs_moves_a_light():
    order = 6
    w = direction_from_angles(0.4, 0.3)
    angle = 1.1
    c = sh.rotate_y_coeffs(sh.sh_basis(w, order), angle)  # delta light at w, rotated
    np.testing.assert_allclose(c, sh.sh_basis(direction_from_angles(0.4, 0.3 - angle), order), atol=1e-13)
    # Rotation composes and is orthogonal (norm preserved).
    c2 = sh.rotate_y_coeffs(sh.rotate_y_coeffs(c, 0.5), -0.5 - angle)
    np.testing.assert_allclose(c2, sh.sh_basis(w, order), atol=1e-13)
    assert np.linalg.norm(c) == pytest.approx(np.linalg.norm(sh.sh_basis(w, order)))
