"""What the estimator reads of a face, and which of its pixels count.

:class:`FaceObservation` holds a face record's arrays; :func:`usable_pixels` picks the pixels the
data term fits (in the skin mask, finite, not clipped, not black; optionally not a specular
highlight, :func:`highlight_pixels`), and :func:`clipped_pixels` the clipped skin pixels that sun
models read as censored observations (``EstimatorConfig.clipped_bounds``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from f2l.lighting.grid import LatLongGrid

__all__ = ["BLACK_LEVEL", "CLIP_LEVEL", "EstimationError", "FaceObservation", "clipped_pixels",
           "highlight_pixels", "usable_pixels"]

# Observed linear values at or above this are treated as clipped; at or below BLACK as black.
CLIP_LEVEL = 0.99
BLACK_LEVEL = 1e-4


class EstimationError(ValueError):
    """A face that cannot be estimated; the message says why."""


@dataclass
class FaceObservation:
    """What the estimator needs of a face record (arrays over the N face pixels)."""

    normals: np.ndarray  # (N, 3) unit
    observed_rgb: np.ndarray  # (N, 3) linear
    mask: np.ndarray  # (N,) bool
    visibility_bits: np.ndarray  # (N, ceil(L/8)) uint8
    grid: LatLongGrid
    face_id: str = ""
    points: np.ndarray | None = None  # (N, 3) camera frame (camera at the origin), for view directions


def highlight_pixels(rgb: np.ndarray, mad_factor: float) -> np.ndarray:
    """Which pixels look like a specular highlight (boolean (N,)): brighter than the median and
    less saturated than the face's median saturation by more than ``mad_factor`` robust standard
    deviations (1.4826 MAD). Dichromatic reflection (Shafer 1985): skin's diffuse colour is
    saturated, and a specular lobe adds the light's own, nearly grey, colour on top of it.
    Saturation is 1 − 3 min(r, g, b) / (r + g + b)."""
    v = np.asarray(rgb, dtype=np.float64)
    total = v.sum(axis=1)
    saturation = 1.0 - 3.0 * v.min(axis=1) / np.maximum(total, 1e-12)
    median = np.median(saturation)
    spread = 1.4826 * np.median(np.abs(saturation - median))
    return (saturation < median - mad_factor * spread) & (total > np.median(total))


def clipped_pixels(obs: FaceObservation, level: float, max_pixels: int | None = None) -> np.ndarray:
    """Indices of the clipped face pixels sun models read as censored observations
    (``EstimatorConfig.clipped_bounds``): outside the mask, finite, some but not all channels at
    or above ``level``; evenly thinned to half of ``max_pixels`` (None: all)."""
    rgb = np.asarray(obs.observed_rgb, np.float64)
    finite = np.isfinite(rgb).all(1)
    candidates = ~np.asarray(obs.mask, bool) & finite & (np.where(finite[:, None], rgb, 0.0).max(1) >= level) \
        & (np.where(finite[:, None], rgb, np.inf).min(1) < level)
    cidx = np.flatnonzero(candidates)
    limit = max(1, (max_pixels or cidx.size) // 2)
    if cidx.size > limit:
        cidx = cidx[np.round(np.linspace(0, cidx.size - 1, limit)).astype(np.int64)]
    return cidx


def usable_pixels(obs: FaceObservation, highlight_mad: float | None = None) -> np.ndarray:
    """Indices of pixels usable for fitting; raises EstimationError with counts when none are.

    With ``highlight_mad`` the pixels :func:`highlight_pixels` flags among the usable ones are
    left out too (``EstimatorConfig.highlight_mad``)."""
    rgb = np.asarray(obs.observed_rgb)
    n = rgb.shape[0]
    if n == 0:
        raise EstimationError("face has no pixels")
    finite = np.isfinite(rgb).all(1) & np.isfinite(obs.normals).all(1)
    if not finite.all():
        raise EstimationError(f"non-finite values in {int((~finite).sum())} of {n} pixels (NaN/inf in record)")
    clipped = (rgb >= CLIP_LEVEL).any(1)
    black = (rgb <= BLACK_LEVEL).all(1)
    keep = np.asarray(obs.mask, dtype=bool) & ~clipped & ~black
    if highlight_mad is not None and keep.sum() >= 100:
        candidates = np.flatnonzero(keep)
        keep[candidates[highlight_pixels(rgb[candidates], highlight_mad)]] = False
    if keep.sum() < 50:
        raise EstimationError(
            f"only {int(keep.sum())} usable pixels of {n} ({int(clipped.sum())} clipped, {int(black.sum())} black, "
            f"{int((~np.asarray(obs.mask, bool)).sum())} masked out): all-black or fully clipped face"
        )
    return np.flatnonzero(keep)
