"""Which face pixels are ray-cast and which reuse their neighbours' visibility.

Face pixels lie on the photo's pixel lattice (``pixel_rc``: integer row, column). With
``levels`` = k, pixels whose row and column are multiples of s = 2^k are *anchors*, ray-cast
directly. The other pixels are *interpolated*, level by level from s/2 down to 1: at step h,
the pixels on the h-lattice that are not on the 2h-lattice take their bits from the two or four
2h-lattice pixels around them at lattice distance h (odd row, even column in units of h: above
and below; even row, odd column: left and right; odd row and column: the four diagonals),
all of which are known by then. An interpolated pixel keeps a texel's bit only where all of its
sources agree on it (all visible, or all front-facing and occluded); every other front-facing
texel of it gets its own ray (see :func:`f2l.transport.visibility.compute_visibility`). A pixel
without its full set of sources (the mask's border) becomes an anchor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["LatticePlan", "plan_lattice"]

_PATTERNS = {  # (row parity, column parity) in units of h -> source offsets in units of h
    (1, 0): ((-1, 0), (1, 0), (-1, 0), (1, 0)),  # 2-source patterns list each source twice
    (0, 1): ((0, -1), (0, 1), (0, -1), (0, 1)),
    (1, 1): ((-1, -1), (-1, 1), (1, -1), (1, 1)),
}


@dataclass(frozen=True)
class LatticePlan:
    """anchors (a,) pixel indices ray-cast directly; steps: a list, coarse to fine, of
    (interpolated (m,) pixel indices, sources (m, 4) pixel indices) whose sources are anchors or
    pixels of earlier steps."""

    anchors: np.ndarray
    steps: list

    @property
    def num_interpolated(self) -> int:
        return int(sum(len(p) for p, _ in self.steps))


def plan_lattice(pixel_rc: np.ndarray, levels: int = 1) -> LatticePlan:
    """Split pixels on an integer lattice into anchors and interpolation steps (module doc).

    pixel_rc (N, 2) integer (row, column), non-negative and unique; levels >= 0 (0: all
    pixels are anchors).
    """
    rc = np.asarray(pixel_rc)
    if rc.ndim != 2 or rc.shape[1] != 2 or not np.issubdtype(rc.dtype, np.integer):
        raise ValueError(f"pixel_rc must be integer (N, 2), got {rc.shape} {rc.dtype}")
    n = len(rc)
    if n == 0 or levels <= 0:
        return LatticePlan(np.arange(n), [])
    rc = rc.astype(np.int64)
    if rc.min() < 0:
        raise ValueError("pixel_rc must be non-negative")
    pad = 1 << levels  # a border of -1 wide enough for every offset
    image = -np.ones((rc[:, 0].max() + 2 * pad + 1, rc[:, 1].max() + 2 * pad + 1), np.int64)
    r, c = rc[:, 0] + pad, rc[:, 1] + pad
    image[r, c] = np.arange(n)
    if (image >= 0).sum() != n:
        raise ValueError("pixel_rc holds repeated (row, column) pairs")
    known = np.zeros(n, bool)  # anchors and pixels of earlier steps
    step_of = np.full(n, -1)
    known[(rc[:, 0] % pad == 0) & (rc[:, 1] % pad == 0)] = True
    steps = []
    h = pad // 2
    while h >= 1:
        on_h = (rc[:, 0] % h == 0) & (rc[:, 1] % h == 0) & ~known
        sel = np.nonzero(on_h)[0]
        sources = -np.ones((len(sel), 4), np.int64)
        pr, pc = (rc[sel, 0] // h) % 2, (rc[sel, 1] // h) % 2
        for (a, b), offsets in _PATTERNS.items():
            rows = np.nonzero((pr == a) & (pc == b))[0]
            for k, (dr, dc) in enumerate(offsets):
                sources[rows, k] = image[r[sel[rows]] + dr * h, c[sel[rows]] + dc * h]
        # a source that is missing or was itself left without sources -> not interpolated
        ok = (sources >= 0).all(axis=1)
        ok[ok] = known[sources[ok]].all(axis=1)
        steps.append((sel[ok], sources[ok]))
        step_of[sel[ok]] = len(steps) - 1
        known[sel] = True  # interpolated or (below) promoted to anchor: known from now on
        h //= 2
    interpolated = step_of >= 0
    return LatticePlan(np.nonzero(~interpolated)[0], steps)
