"""Which pixels of the forehead's hairline band are skin (``FitOptions.hairline = "colour"``).

The upper forehead is where a high sun, and a sun behind the head, lights the face most, and
where hair falls. ``f2l.face.regions`` marks that band (``hairline``); a band pixel is kept as
skin when its colour is that of the ``neighbours`` nearest usable skin pixels in the image, which
share its light (the face's far side, or its sunlit side, may not: a blue sky turns shaded skin as
neutral as grey hair):

* chromaticity: ``c = (ln R/G, ln B/G)`` within ``max_chroma`` of their median. Black and grey
  hair (neutral) and blond hair (yellower than skin) are 0.4–0.8 from skin under one light;
* luminance: ``Y`` at least ``dark_factor`` × their median ``Y`` (dark hair has a third to a
  tenth of the skin's albedo, and its chromaticity can be the skin's);

and no band pixel that fails is within ``edge`` of it (pixels on the hair's edge mix the two).
A clipped band pixel, or one with a channel at or above ``saturated`` (linear; sun models read
channels from 0.95 as clipped), has no reliable colour: it is tested on its luminance alone (and
does not make its neighbours fail), so that the sunlit forehead a high sun clips stays in as the
lower bound sun models read it as (``EstimatorConfig.clipped_bounds``).

In the shade of a blue sky skin is nearly neutral, so there light hair passes; dark hair does not.
On ``make eval-real`` (Anny heads, whose hair starts above the band) the band was left out whole
until 2026-11-27; reading it took the tuning part's mean Sun-ang from 11.7 to 10.3 deg (sunsky)
and from 17.1 to 10.8 deg (ae), the reporting part's from 14.8 to 14.2 and 19.9 to 16.9 (docs/experiments/accuracy_issue16.md,
"What each change bought").
"""

from __future__ import annotations

import numpy as np

REC709_Y = np.array([0.2126, 0.7152, 0.0722])
MIN_REFERENCE = 50  # fewer skin pixels than this: the band stays excluded


def log_chroma(rgb: np.ndarray, floor: float = 1e-6) -> np.ndarray:
    """(N, 2) ``(ln R/G, ln B/G)`` of linear RGB (N, 3), channels floored at ``floor``."""
    x = np.maximum(np.asarray(rgb, np.float64), floor)
    return np.log(x[:, [0, 2]] / x[:, [1]])


def skin_coloured(candidate_rgb: np.ndarray, candidate_xy: np.ndarray, skin_rgb: np.ndarray,
                  skin_xy: np.ndarray, *, max_chroma: float = 0.25, dark_factor: float = 0.5,
                  neighbours: int = 16, edge: float = 1.5,
                  candidate_clipped: np.ndarray | None = None, saturated: float = 0.9) -> np.ndarray:
    """(M,) bool: which of ``candidate_rgb`` (M, 3; linear) at image points ``candidate_xy``
    (M, 2) have the colour of ``skin_rgb`` (K, 3; the face's usable skin) at ``skin_xy`` (K, 2);
    ``edge`` in the units of the points; ``candidate_clipped`` (M,) bool marks clipped candidates.
    All False when K < ``MIN_REFERENCE``."""
    from scipy.spatial import cKDTree

    cand = np.asarray(candidate_rgb, np.float64).reshape(-1, 3)
    skin = np.asarray(skin_rgb, np.float64).reshape(-1, 3)
    good = np.isfinite(skin).all(1) & (skin > 0).all(1)
    skin, skin_xy = skin[good], np.asarray(skin_xy, np.float64).reshape(-1, 2)[good]
    if len(skin) < MIN_REFERENCE or len(cand) == 0:
        return np.zeros(len(cand), bool)
    finite = np.isfinite(cand).all(1)
    cand = np.where(finite[:, None], cand, 1.0)
    cand_xy = np.asarray(candidate_xy, np.float64).reshape(-1, 2)
    _, near = cKDTree(skin_xy).query(cand_xy, k=min(neighbours, len(skin)))
    near = near.reshape(len(cand), -1)
    chroma_near = np.median(log_chroma(skin)[near], axis=1)
    y_near = np.median((skin @ REC709_Y)[near], axis=1)
    clipped = cand.max(1) >= saturated
    if candidate_clipped is not None:
        clipped |= np.asarray(candidate_clipped, bool)
    close = clipped | (np.linalg.norm(log_chroma(cand) - chroma_near, axis=1) <= max_chroma)
    keep = finite & close & (cand @ REC709_Y >= dark_factor * y_near)
    failed = ~keep & ~(clipped & finite)
    if edge > 0 and failed.any():
        d, _ = cKDTree(cand_xy[failed]).query(cand_xy, k=1)
        keep &= d > edge
    return keep
