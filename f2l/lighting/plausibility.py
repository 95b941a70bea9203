"""Is this lat-long probe fit to be ground truth (or an "ok" result)?

A probe that becomes ground truth, or leaves make-probes with status "ok", must be:

- a full-sphere lat-long array (H, W, 3) with W = 2H and H even;
- finite and non-negative everywhere (radiance);
- not black: the upper hemisphere's mean radiance is above zero;
- covered: texels with any light (or, where the caller passes it, the coverage mask of what the
  cameras saw) fill at least :data:`MIN_SKY_COVERAGE` of the upper hemisphere's solid angle.

:func:`probe_problem` returns the first reason a probe fails, or None; it never raises on the
array's content, so callers turn the reason into a per-record status.
"""

from __future__ import annotations

import numpy as np

__all__ = ["MIN_SKY_COVERAGE", "probe_problem"]

MIN_SKY_COVERAGE = 0.25
"""Least fraction of the upper hemisphere's solid angle a probe must cover (a zenith fisheye of
180° covers all of it; a rectilinear view alone covers a fifth or less and is no probe)."""


def probe_problem(probe: np.ndarray, *, coverage: np.ndarray | None = None,
                  min_sky_coverage: float = MIN_SKY_COVERAGE) -> str | None:
    """The first reason ``probe`` (H, W, 3) cannot serve as a probe (module doc), or None.
    ``coverage``: optional (H, W) mask of texels a camera saw.

    >>> print(probe_problem(np.ones((16, 32, 3))))
    None
    >>> probe_problem(np.zeros((16, 32, 3)))
    'black: no light in the upper hemisphere'
    >>> probe_problem(np.ones((16, 16, 3)))
    'a 16x16 image is not a full-sphere lat-long probe (width = 2 x height, height even)'
    >>> seen = np.zeros((16, 32), bool)
    >>> seen[:2] = True  # the cameras saw only the two rows around the zenith
    >>> probe_problem(np.ones((16, 32, 3)), coverage=seen)
    'covers 7.6% of the upper hemisphere (at least 25% needed)'
    """
    from f2l.lighting.grid import LatLongGrid

    p = np.asarray(probe)
    if p.ndim != 3 or p.shape[2] != 3:
        return f"not an RGB image (shape {p.shape})"
    h, w = p.shape[:2]
    if h < 2 or h % 2 or w != 2 * h:
        return f"a {h}x{w} image is not a full-sphere lat-long probe (width = 2 x height, height even)"
    if not np.issubdtype(p.dtype, np.floating) and not np.issubdtype(p.dtype, np.integer):
        return f"pixel type {p.dtype} is not numeric"
    finite = np.isfinite(p)
    if not finite.all():
        return f"{int((~finite).any(axis=2).sum())} texels are NaN or infinite"
    low = float(p.min())
    if low < -1e-6:
        return f"negative radiance (min {low:g})"
    grid = LatLongGrid(h, w)
    sky = grid.sky_rows
    sa = grid.solid_angles[:sky]
    lit = p[:sky].max(axis=2) > 0
    if coverage is not None:
        lit &= np.asarray(coverage, bool)[:sky]
    if float(p[:sky].max()) <= 0:
        return "black: no light in the upper hemisphere"
    fraction = float((sa * lit).sum() / sa.sum())
    if fraction < min_sky_coverage:
        return (f"covers {100 * fraction:.1f}% of the upper hemisphere (at least "
                f"{100 * min_sky_coverage:.0f}% needed)")
    return None
