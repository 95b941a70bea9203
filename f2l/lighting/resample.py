"""Energy-preserving area resampling between lat-long resolutions.

A probe texel stores the mean radiance over its cell [theta_0, theta_1] x [mu_1, mu_0] with
mu = cos(phi) (solid angle = d_theta * d_mu). Resampling treats the probe as piecewise constant
and takes, for every target texel, the exact area-weighted mean over it:

    out[i, k] = sum_{j, l} R[i, j] C[k, l] in[j, l]
    R[i, j] = |row_i  ∩ row_j|_mu    / |row_i|_mu       (overlap in cos(phi))
    C[k, l] = |col_k  ∩ col_l|_theta / |col_k|_theta    (overlap in azimuth)

Rows of R and C sum to 1 (constants stay constant) and, summed over targets, the overlaps of a
source cell add up to its extent, so the integral sum(L dOmega) is preserved exactly (to
rounding) for any pair of resolutions, integer ratio or not, up or down. Upsampling by an
integer factor and then downsampling back is the identity.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

__all__ = ["resample", "row_overlap_matrix", "column_overlap_matrix"]


def _overlap_matrix(target_edges: np.ndarray, source_edges: np.ndarray) -> np.ndarray:
    """M[i, j] = |[t_i, t_i+1] ∩ [s_j, s_j+1]| / |[t_i, t_i+1]| for increasing edge arrays."""
    lo = np.maximum(target_edges[:-1, None], source_edges[None, :-1])
    hi = np.minimum(target_edges[1:, None], source_edges[None, 1:])
    overlap = np.clip(hi - lo, 0.0, None)
    return overlap / np.diff(target_edges)[:, None]


def _mu_edges(height: int) -> np.ndarray:
    """Increasing row edges in -cos(phi) (row 0 at the zenith, -cos(0) = -1)."""
    return -np.cos(np.linspace(0.0, np.pi, height + 1))


@lru_cache(maxsize=64)
def _row_matrix(height_out: int, height_in: int) -> np.ndarray:
    m = _overlap_matrix(_mu_edges(height_out), _mu_edges(height_in))
    m.setflags(write=False)
    return m


@lru_cache(maxsize=64)
def _column_matrix(width_out: int, width_in: int) -> np.ndarray:
    # Column edges as fractions of a turn, theta = 2 pi (u - 1/2); overlaps are scale-free.
    m = _overlap_matrix(np.linspace(0.0, 1.0, width_out + 1), np.linspace(0.0, 1.0, width_in + 1))
    m.setflags(write=False)
    return m


def row_overlap_matrix(height_out: int, height_in: int) -> np.ndarray:
    """Row resampling matrix R (height_out, height_in), overlap in cos(phi); read-only."""
    return _row_matrix(_check_size(height_out, "height"), _check_size(height_in, "height"))


def column_overlap_matrix(width_out: int, width_in: int) -> np.ndarray:
    """Column resampling matrix C (width_out, width_in), overlap in theta; read-only."""
    return _column_matrix(_check_size(width_out, "width"), _check_size(width_in, "width"))


def _check_size(n: int, what: str) -> int:
    if int(n) != n or n < 1:
        raise ValueError(f"{what} must be a positive integer, got {n!r}")
    return int(n)


def resample(probe: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resample a lat-long probe (H, W, C) or (H, W) to (height, width[, C]).

    Exact area averaging (see module docstring): preserves sum(L dOmega) per channel and
    constants. Computed in float64; float32/float16 input is returned in its own dtype, any
    other input as float64.
    """
    src = np.asarray(probe)
    if src.ndim not in (2, 3):
        raise ValueError(f"probe must be (H, W) or (H, W, C), got shape {src.shape}")
    rows = row_overlap_matrix(height, src.shape[0])
    cols = column_overlap_matrix(width, src.shape[1])
    x = src.astype(np.float64, copy=False)
    if x.ndim == 2:
        out = rows @ x @ cols.T
    else:
        out = np.einsum("ij,jlc,kl->ikc", rows, x, cols, optimize=True)
    if np.issubdtype(src.dtype, np.floating) and src.dtype != np.float64:
        return out.astype(src.dtype)
    return out
