"""Where the sun is in a lat-long probe: luminance, the brightest upper texel, caps around a
direction, and the sun's direction as the luminance-weighted mean of the texels near the brightest
one. Used by capture (a probe's sun) and by the §5.1 metrics (:mod:`f2l.metrics.lighting`, which
re-exports them). Conventions: :mod:`f2l.lighting.grid`; luminance Y = 0.2126 R + 0.7152 G + 0.0722 B
(Rec.709).

References
----------
- Calian, Lalonde, Gotardo, Simon, Matthews, Mitchell. "From Faces to Outdoor Light Probes."
  Computer Graphics Forum (Eurographics) 37(2), 2018 (§5.1: the 13° sun region of the metrics).
"""

from __future__ import annotations

import math

import numpy as np

from f2l.lighting.grid import LatLongGrid

__all__ = ["LUMA_709", "SUN_CAP_DEG", "SUN_WINDOW_DEG", "luminance", "brightest_direction", "cap_mask",
           "sun_direction"]

LUMA_709 = np.array([0.2126, 0.7152, 0.0722])
SUN_CAP_DEG = 13.0
SUN_WINDOW_DEG = 5.0


def _check(probe: np.ndarray, grid: LatLongGrid) -> np.ndarray:
    p = np.asarray(probe, dtype=np.float64)
    if p.shape != (grid.height, grid.width, 3):
        raise ValueError(f"probe shape {p.shape} does not match grid {grid.height}x{grid.width}x3")
    return p


def luminance(probe: np.ndarray) -> np.ndarray:
    """Rec.709 luminance Y of (..., 3) linear RGB.

    >>> luminance(np.eye(3)).tolist()
    [0.2126, 0.7152, 0.0722]
    >>> round(float(luminance([1.0, 1.0, 1.0])), 12)  # white has unit luminance
    1.0
    """
    return np.asarray(probe, dtype=np.float64) @ LUMA_709


def brightest_direction(probe: np.ndarray, grid: LatLongGrid) -> tuple[tuple[int, int], np.ndarray]:
    """(row, col) and centre direction of the max-luminance upper texel (ties: first row-major).

    >>> grid = LatLongGrid(16, 32)
    >>> probe = np.full((16, 32, 3), 0.1)
    >>> probe[3, 20] = 50.0
    >>> probe[12, 5] = 90.0  # below the horizon: never the sun
    >>> (row, col), direction = brightest_direction(probe, grid)
    >>> (row, col), bool(np.allclose(direction, grid.directions[3, 20]))
    ((3, 20), True)
    """
    p = _check(probe, grid)
    y = np.where(grid.upper_mask, luminance(p), -np.inf)
    y = np.where(np.isnan(y), -np.inf, y)
    idx = int(np.argmax(y))
    rc = divmod(idx, grid.width)
    return (int(rc[0]), int(rc[1])), np.array(grid.directions_flat[idx])


def cap_mask(grid: LatLongGrid, direction: np.ndarray, radius_deg: float = SUN_CAP_DEG) -> np.ndarray:
    """(H, W) bool: texels whose centre is within ``radius_deg`` of ``direction`` (any hemisphere).

    >>> mask = cap_mask(LatLongGrid(16, 32), np.array([0.0, 1.0, 0.0]), radius_deg=20.0)
    >>> mask.shape, bool(mask[0].all()), bool(mask[2].any())  # around the zenith: the first row only
    ((16, 32), True, False)
    """
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    return grid.directions @ d >= math.cos(math.radians(radius_deg))


def sun_direction(
    probe: np.ndarray, grid: LatLongGrid, window_deg: float = SUN_WINDOW_DEG
) -> np.ndarray:
    """Sun direction (3,), unit: normalised ``Σ w ω`` over upper texels within ``window_deg`` of the
    brightest upper texel, ``w = max(Y, 0) dΩ`` (Y = Rec.709 luminance). Falls back to the
    brightest texel's centre if all weights are zero.

    >>> grid = LatLongGrid(16, 32)
    >>> probe = np.full((16, 32, 3), 0.1)
    >>> probe[3, 20] = 50.0
    >>> np.round(sun_direction(probe, grid), 4)
    array([ 0.4904,  0.773 , -0.4025])
    >>> round(float(np.linalg.norm(sun_direction(probe, grid))), 12)
    1.0
    """
    p = _check(probe, grid)
    _, d0 = brightest_direction(p, grid)
    sel = cap_mask(grid, d0, window_deg) & grid.upper_mask
    w = np.maximum(luminance(p), 0.0) * grid.solid_angles * sel
    w = np.nan_to_num(w, nan=0.0, posinf=0.0)
    v = np.tensordot(w, grid.directions, axes=([0, 1], [0, 1]))
    n = np.linalg.norm(v)
    return v / n if n > 0 else d0
