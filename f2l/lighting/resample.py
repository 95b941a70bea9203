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

:class:`BandResampler` computes the same ``out`` from horizontal bands of the source, fed in
order, holding only one band and the output: an image too large to decode at once (a 20000 x 10000
float EXR is 2.4 GB) is resampled in O(band + output) memory. Its weights are the entries of R and
C above, computed for the overlapping blocks only, so it agrees with :func:`resample` to rounding.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

__all__ = ["resample", "row_overlap_matrix", "column_overlap_matrix", "BandResampler"]


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
    """Row resampling matrix R (height_out, height_in), overlap in cos(phi); read-only.

    Halving 4 rows: each target row takes its two source rows in proportion to their solid angle
    (the row nearer the horizon is the larger):

    >>> np.round(row_overlap_matrix(2, 4), 3)
    array([[0.293, 0.707, 0.   , 0.   ],
           [0.   , 0.   , 0.707, 0.293]])
    """
    return _row_matrix(_check_size(height_out, "height"), _check_size(height_in, "height"))


def column_overlap_matrix(width_out: int, width_in: int) -> np.ndarray:
    """Column resampling matrix C (width_out, width_in), overlap in theta; read-only.

    >>> column_overlap_matrix(2, 4)
    array([[0.5, 0.5, 0. , 0. ],
           [0. , 0. , 0.5, 0.5]])
    >>> column_overlap_matrix(3, 7).sum(axis=1).round(12).tolist()  # rows sum to 1
    [1.0, 1.0, 1.0]
    """
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

    >>> from f2l.lighting.grid import LatLongGrid
    >>> probe = np.random.default_rng(0).random((16, 32, 3)).astype(np.float32)
    >>> small = resample(probe, 8, 16)
    >>> small.shape, small.dtype
    ((8, 16, 3), dtype('float32'))
    >>> energy = lambda p: (p * LatLongGrid(*p.shape[:2]).solid_angles[..., None]).sum(axis=(0, 1))
    >>> bool(np.allclose(energy(small), energy(probe), rtol=1e-5))  # sum(L dOmega) is kept
    True
    >>> np.unique(resample(np.full((4, 8), 2.0), 6, 10).round(12)).tolist()  # constants stay constant
    [2.0]
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


def _overlap_block(target_edges: np.ndarray, source_edges: np.ndarray, j0: int, j1: int
                   ) -> tuple[int, np.ndarray]:
    """(k0, M): the block of the overlap matrix for source cells j0..j1-1 and the target cells
    k0..k0+len(M)-1 that can overlap them (every other entry of those columns is zero)."""
    lo, hi = source_edges[j0], source_edges[j1]
    k0 = max(int(np.searchsorted(target_edges, lo, side="right")) - 1, 0)
    k1 = min(int(np.searchsorted(target_edges, hi, side="left")), len(target_edges) - 1)
    k1 = max(k1, k0 + 1)
    return k0, _overlap_matrix(target_edges[k0:k1 + 1], source_edges[j0:j1 + 1])


class BandResampler:
    """:func:`resample` of a (height_in, width_in, C) lat-long image fed as row bands, top first.

    ``add(band)`` takes the next rows (b, width_in, C) of the source; ``result()`` returns the
    (height, width, C) float64 area average once every row has been added. Memory: the output
    plus one band and its column-resampled copy; columns are combined ``column_chunk`` source
    columns at a time.

    >>> probe = np.random.default_rng(1).random((16, 32, 3))
    >>> bands = BandResampler(16, 32, 8, 16, channels=3)
    >>> for top in range(0, 16, 4):
    ...     bands.add(probe[top:top + 4])
    >>> out = bands.result()
    >>> out.shape, bool(np.allclose(out, resample(probe, 8, 16)))
    ((8, 16, 3), True)
    """

    def __init__(self, height_in: int, width_in: int, height: int, width: int, channels: int = 3,
                 column_chunk: int = 4096):
        self.height_in = _check_size(height_in, "height")
        self.width_in = _check_size(width_in, "width")
        self.height = _check_size(height, "height")
        self.width = _check_size(width, "width")
        self._row_src, self._row_tgt = _mu_edges(self.height_in), _mu_edges(self.height)
        self._col_src = np.linspace(0.0, 1.0, self.width_in + 1)
        self._col_tgt = np.linspace(0.0, 1.0, self.width + 1)
        from scipy.sparse import csr_matrix

        # a source column overlaps one or two target columns when downsampling: sparse blocks
        self._col_blocks = [(k0, csr_matrix(m)) for k0, m in (
            _overlap_block(self._col_tgt, self._col_src, j, min(j + column_chunk, self.width_in))
            for j in range(0, self.width_in, max(1, int(column_chunk))))]
        self._out = np.zeros((self.height, self.width, int(channels)), np.float64)
        self.rows_done = 0

    def add(self, band: np.ndarray) -> None:
        band = np.asarray(band)
        b = band.shape[0]
        if band.ndim != 3 or band.shape[1] != self.width_in or band.shape[2] != self._out.shape[2]:
            raise ValueError(f"band must be (rows, {self.width_in}, {self._out.shape[2]}), got {band.shape}")
        if self.rows_done + b > self.height_in:
            raise ValueError(f"{self.rows_done + b} rows added to a {self.height_in}-row image")
        # (target columns, band rows x channels): each block a sparse product over its source columns
        c = band.shape[2]
        cols = np.zeros((self.width, b * c), np.float64)
        j0 = 0
        for k0, m in self._col_blocks:
            j1 = j0 + m.shape[1]
            x = np.ascontiguousarray(band[:, j0:j1].transpose(1, 0, 2), dtype=np.float64).reshape(j1 - j0, b * c)
            cols[k0:k0 + m.shape[0]] += m @ x
            j0 = j1
        cols = cols.reshape(self.width, b, c)
        i0, r = _overlap_block(self._row_tgt, self._row_src, self.rows_done, self.rows_done + b)
        self._out[i0:i0 + r.shape[0]] += np.tensordot(r, cols, axes=([1], [1]))
        self.rows_done += b

    def result(self) -> np.ndarray:
        if self.rows_done != self.height_in:
            raise ValueError(f"only {self.rows_done} of {self.height_in} rows were added")
        return self._out
