"""Tests for f2l.lighting.grid (lat-long conventions, solid angles, rotation about +Y)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from f2l.lighting.grid import (
    LatLongGrid,
    angles_from_direction,
    direction_from_angles,
    rotate_y,
)

SIZES = [(2, 2), (8, 16), (32, 128), (64, 128), (100, 37)]


def _rot_y(angle_rad: float) -> np.ndarray:
    """Right-handed rotation about +Y: x' = x cos a + z sin a, z' = -x sin a + z cos a."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@pytest.mark.parametrize("shape", SIZES)
def test_solid_angles_sum_to_4pi(shape):
    grid = LatLongGrid(*shape)
    assert grid.solid_angles.shape == shape
    assert grid.solid_angles.sum() == pytest.approx(4 * math.pi, abs=1e-6)
    assert grid.solid_angles_flat.sum() == pytest.approx(4 * math.pi, abs=1e-6)
    assert np.all(grid.solid_angles > 0)
    # Upper hemisphere (first H/2 rows) is exactly 2 pi.
    assert grid.solid_angles[grid.upper_mask].sum() == pytest.approx(2 * math.pi, abs=1e-9)
    # Row formula: (2 pi / W)(cos phi0 - cos phi1).
    e = grid.phi_edges_rad
    np.testing.assert_allclose(grid.row_solid_angles, 2 * math.pi / shape[1] * (np.cos(e[:-1]) - np.cos(e[1:])))


@pytest.mark.parametrize("shape", SIZES)
def test_directions_are_unit_and_flattened_row_major(shape):
    grid = LatLongGrid(*shape)
    d = grid.directions
    assert d.shape == (*shape, 3) and d.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-14)
    np.testing.assert_array_equal(grid.directions_flat[shape[1] + 1], d[1, 1])
    assert not d.flags.writeable


def test_orientation_conventions():
    grid = LatLongGrid(64, 128)
    # Centre column edge (u = 0.5) at the equator row edge is exactly -Z; the nearest
    # texel centres straddle it symmetrically.
    uv = grid.direction_to_uv(np.array([0.0, 0.0, -1.0]))
    np.testing.assert_allclose(uv, [0.5, 0.5], atol=1e-15)
    assert grid.direction_to_texel(np.array([0.0, 1e-9, -1.0])) == (31, 64)
    centre = grid.directions[31:33, 63:65]  # 2x2 around (u, v) = (0.5, 0.5)
    np.testing.assert_allclose(centre.mean(axis=(0, 1)) / np.linalg.norm(centre.mean(axis=(0, 1))), [0, 0, -1], atol=1e-14)
    assert np.all(centre[..., 2] < -0.99)
    # Row 0 near +Y (zenith), last row near -Y.
    assert np.all(grid.directions[0, :, 1] > math.cos(math.pi / 64))
    assert np.all(grid.directions[-1, :, 1] < -math.cos(math.pi / 64))
    # Three quarters of the way across (theta = +pi/2) is +X, camera right; a quarter is -X.
    eq = grid.directions[31:33].mean(axis=0)
    assert eq[96][0] > 0.99 and eq[32][0] < -0.99
    # Rows 0 .. H/2-1 are the sky (y > 0).
    assert np.all(grid.directions[: grid.sky_rows, :, 1] > 0)
    assert np.all(grid.directions[grid.sky_rows :, :, 1] < 0)


def test_invalid_grids():
    with pytest.raises(ValueError):
        LatLongGrid(3, 8)
    with pytest.raises(ValueError):
        LatLongGrid(0, 8)


@pytest.mark.parametrize("shape", [(8, 16), (64, 128), (30, 45)])
def test_direction_to_texel_inverts_directions(shape):
    grid = LatLongGrid(*shape)
    rows, cols = grid.direction_to_texel(grid.directions)
    np.testing.assert_array_equal(rows, np.repeat(np.arange(shape[0])[:, None], shape[1], axis=1))
    np.testing.assert_array_equal(cols, np.repeat(np.arange(shape[1])[None, :], shape[0], axis=0))
    uv = grid.direction_to_uv(grid.directions)
    np.testing.assert_allclose(uv[..., 0], np.broadcast_to(grid.u, shape), atol=1e-13)
    np.testing.assert_allclose(uv[..., 1], np.broadcast_to(grid.v[:, None], shape), atol=1e-13)


def test_angles_round_trip():
    rng = np.random.default_rng(0)
    elevation = rng.uniform(-1.5, 1.5, 50)
    azimuth = rng.uniform(-3.1, 3.1, 50)
    d = direction_from_angles(elevation, azimuth)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)
    e2, a2 = angles_from_direction(d)
    np.testing.assert_allclose(e2, elevation, atol=1e-12)
    np.testing.assert_allclose(a2, azimuth, atol=1e-12)
    np.testing.assert_allclose(direction_from_angles(0.0, 0.0), [0, 0, -1], atol=1e-15)
    np.testing.assert_allclose(direction_from_angles(0.0, math.pi / 2), [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(direction_from_angles(math.pi / 2, 0.3), [0, 1, 0], atol=1e-15)


@pytest.mark.parametrize("k", [0, 1, 5, -3, 17, 64, 127, 130])
def test_rotate_y_whole_columns_is_roll_and_matches_rotation_matrix(k):
    grid = LatLongGrid(16, 128)
    rng = np.random.default_rng(k + 100)
    probe = rng.random((16, 128, 3))
    angle = k * 2 * math.pi / grid.width
    out = rotate_y(probe, angle)
    # Content at theta moves to theta - angle: a roll by -k columns.
    np.testing.assert_array_equal(out, np.roll(probe, -k, axis=1))
    # Same as rotating directions: out(d') = probe(R^-1 d'), with R = R_y(angle).
    source_dirs = grid.directions @ _rot_y(-angle).T
    rows, cols = grid.direction_to_texel(source_dirs)
    np.testing.assert_array_equal(out, probe[rows, cols])


def test_rotation_matrix_moves_azimuth_by_minus_angle():
    d = direction_from_angles(0.3, 0.7)
    _, az = angles_from_direction(_rot_y(0.5) @ d)
    assert az == pytest.approx(0.2)
    # A bright texel moves with R_y under rotate_y.
    grid = LatLongGrid(16, 64)
    probe = np.zeros((16, 64))
    probe[5, 40] = 1.0
    angle = 9 * 2 * math.pi / 64
    out = rotate_y(probe, angle)
    moved = grid.direction_to_texel(_rot_y(angle) @ grid.directions[5, 40])
    assert out[moved] == 1.0 and out.sum() == 1.0


@pytest.mark.parametrize("angle", [0.123, -2.0, 0.5 * 2 * math.pi / 64, 10.0])
def test_fractional_rotation_preserves_column_sum_and_interpolates(angle):
    grid = LatLongGrid(16, 64)
    probe = np.random.default_rng(3).random((16, 64, 3)) * 100
    out = rotate_y(probe, angle)
    assert out.shape == probe.shape
    np.testing.assert_allclose(out.sum(axis=1), probe.sum(axis=1), rtol=1e-12)
    # Energy (sum of L dOmega) is preserved too.
    np.testing.assert_allclose(
        np.tensordot(grid.solid_angles, out, axes=([0, 1], [0, 1])),
        np.tensordot(grid.solid_angles, probe, axes=([0, 1], [0, 1])),
        rtol=1e-12,
    )
    # Interpolates between the two neighbouring whole-column rotations.
    shift = -angle * 64 / (2 * math.pi)
    lo = np.roll(probe, int(math.floor(shift)), axis=1)
    hi = np.roll(probe, int(math.floor(shift)) + 1, axis=1)
    assert np.all(out >= np.minimum(lo, hi) - 1e-9) and np.all(out <= np.maximum(lo, hi) + 1e-9)
    # A full turn is the identity.
    np.testing.assert_allclose(rotate_y(probe, 2 * math.pi), probe, atol=1e-12)
