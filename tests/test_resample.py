"""Tests for f2l.lighting.resample (energy-preserving lat-long area resampling)."""

from __future__ import annotations

import numpy as np
import pytest

from f2l.lighting.grid import LatLongGrid
from f2l.lighting.resample import column_overlap_matrix, resample, row_overlap_matrix

RNG = np.random.default_rng(7)


def _energy(probe: np.ndarray) -> np.ndarray:
    """Per-channel integral sum(L dOmega) on the probe's own grid."""
    grid = LatLongGrid(*probe.shape[:2])
    return np.tensordot(grid.solid_angles, probe, axes=([0, 1], [0, 1]))


def _hdr_probe(height: int, width: int, channels: int = 3) -> np.ndarray:
    probe = RNG.random((height, width, channels)) * 10.0
    probe[height // 5, width // 3] = [5e6, 4e6, 3e6][:channels]  # a 'sun'
    return probe


@pytest.mark.parametrize(
    "src, dst",
    [((64, 128), (32, 64)), ((64, 128), (48, 100)), ((16, 32), (64, 128)), ((64, 128), (22, 54))],
)
def test_energy_preserved(src, dst):
    probe = _hdr_probe(*src)
    out = resample(probe, *dst)
    assert out.shape == (*dst, 3) and out.dtype == np.float64
    np.testing.assert_allclose(_energy(out), _energy(probe), rtol=1e-10)
    assert out.min() >= 0.0  # convex combinations of non-negative radiance


@pytest.mark.parametrize("dst", [(32, 64), (48, 100), (64, 128), (128, 256), (10, 7)])
def test_constant_preserved(dst):
    probe = np.full((64, 128, 3), 3.25)
    np.testing.assert_allclose(resample(probe, *dst), 3.25, rtol=1e-13)


def test_upsample_then_downsample_is_identity():
    probe = _hdr_probe(16, 32)
    up = resample(probe, 64, 128)
    np.testing.assert_allclose(resample(up, 16, 32), probe, rtol=1e-12)
    # Integer upsampling replicates each texel (piecewise-constant radiance).
    np.testing.assert_allclose(up[0:4, 0:4], np.broadcast_to(probe[0, 0], (4, 4, 3)), rtol=1e-13)


def test_same_size_is_identity_and_2d_input():
    probe = RNG.random((32, 64))
    np.testing.assert_array_equal(resample(probe, 32, 64), probe)
    out = resample(probe, 16, 48)
    assert out.shape == (16, 48)
    np.testing.assert_allclose(_energy(out[..., None]), _energy(probe[..., None]), rtol=1e-10)


def test_downsample_is_area_weighted_mean():
    # 2x downsampling of rows near the pole weights by cos(phi) extents, not equally.
    probe = np.zeros((4, 2))
    probe[0] = 1.0  # polar row: small solid angle
    out = resample(probe, 2, 2)
    g4 = LatLongGrid(4, 2)
    expected = g4.row_solid_angles[0] / (g4.row_solid_angles[0] + g4.row_solid_angles[1])
    np.testing.assert_allclose(out[0], expected, rtol=1e-13)
    np.testing.assert_allclose(out[1], 0.0, atol=1e-15)


def test_matrices_rows_sum_to_one_and_dtype():
    for a, b in [(48, 64), (64, 48), (7, 13)]:
        np.testing.assert_allclose(row_overlap_matrix(a, b).sum(axis=1), 1.0, rtol=1e-13)
        np.testing.assert_allclose(column_overlap_matrix(a, b).sum(axis=1), 1.0, rtol=1e-13)
    assert resample(np.ones((8, 16, 3), np.float32), 4, 8).dtype == np.float32
    with pytest.raises(ValueError):
        resample(np.ones((8, 16, 3)), 0, 8)
    with pytest.raises(ValueError):
        resample(np.ones(8), 4, 8)
