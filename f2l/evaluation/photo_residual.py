"""How well a probe explains a face photo under f2l's forward model: does the photo prefer the truth?

For a face record (pixels, unit normals, visibility bits on the lighting grid) and a full-sphere
probe ``l`` (DESIGN convention, ground rows included), the Lambertian shading of pixel p is
``s_p = (T l)_p`` (:class:`f2l.transport.Transport`, paper eq. 3). With the skin's RGB albedo
(times the exposure) ``k`` left free per channel, the photo residual is

    r(l) = min_k  Σ_p,c |o_pc − k_c s_pc|  /  Σ_p,c o_pc,

over the record's usable pixels (:func:`f2l.estimate.observation.usable_pixels`: skin mask, not
clipped, not black). Each ``k_c`` is the s-weighted median of ``o_pc / s_pc`` (the exact L1
minimiser); r is scale-invariant in ``l`` and in the photo. ``f2l eval real`` scores both the
estimate's probe and the truth through the same record: where an estimate's sun is far off and its
residual is no larger than the truth's, the photo (as f2l reads it) does not point at the true
sun, and no search or optimiser change can fix that case; only the forward model, the face's
geometry or the priors can.
"""

from __future__ import annotations

import numpy as np

from f2l.estimate.observation import FaceObservation, usable_pixels
from f2l.evaluation.highlight import glossy_highlight
from f2l.lighting.grid import LatLongGrid
from f2l.transport import Transport

__all__ = ["best_scale_l1", "photo_residual", "ideal_photo", "PhotoResidual", "IDEAL_PEAK"]

IDEAL_PEAK = 0.8  # the ideal photo's brightest pixel: below the estimator's clipped level (0.95)


def best_scale_l1(observed: np.ndarray, shading: np.ndarray) -> float:
    """argmin_k Σ |o − k s| for 1-D arrays (s >= 0): the s-weighted median of o / s over s > 0
    (0 when no shading is positive)."""
    o = np.asarray(observed, np.float64)
    s = np.asarray(shading, np.float64)
    pos = s > 0
    if not pos.any():
        return 0.0
    ratio, weight = o[pos] / s[pos], s[pos]
    order = np.argsort(ratio, kind="stable")
    cum = np.cumsum(weight[order])
    return float(ratio[order][np.searchsorted(cum, 0.5 * cum[-1])])


def photo_residual(observed: np.ndarray, shading: np.ndarray) -> float:
    """r of the module docstring for (N, 3) observed linear RGB and (N, 3) shading; NaN when the
    observation has no energy."""
    o = np.asarray(observed, np.float64)
    s = np.asarray(shading, np.float64)
    total = float(o.sum())
    if not total > 0 or not np.isfinite(s).all():
        return float("nan")
    fitted = np.stack([best_scale_l1(o[:, c], s[:, c]) * s[:, c] for c in range(o.shape[1])], 1)
    return float(np.abs(o - fitted).sum() / total)


def ideal_photo(record, probe: np.ndarray, threads: int = 2, gloss=None) -> np.ndarray:
    """f2l's own forward model of ``record``'s photo under ``probe`` (H, W, 3, its grid): (N, 3) float32.

    Every pixel is ``k_c (T l)_pc`` (Lambertian, the record's normals and visibility), with the
    skin's RGB albedo ``k`` the photo's per-channel L1 optimum (:func:`best_scale_l1` over its
    usable pixels, as in the photo residual) and one exposure putting the brightest masked pixel at
    :data:`IDEAL_PEAK`: no specular, interreflection, texture, clipping, noise or quantisation.
    Estimating from it measures what the lighting model and its priors can do on that geometry
    when the photo holds nothing the model leaves out.

    With ``gloss`` (:class:`f2l.evaluation.highlight.Gloss`) the masked pixels also get the skin's
    glossy highlight of the whole probe (:func:`f2l.evaluation.highlight.glossy_highlight`, the
    record's 3-D points for the view), at the exposure ``median_c(k_c / albedo_c)``."""
    grid = LatLongGrid(record.grid_height, record.grid_width)
    p = np.asarray(probe, np.float64)
    if p.shape != grid.shape + (3,):
        raise ValueError(f"probe {p.shape} is not on the record's {grid.height}x{grid.width} grid")
    observed = np.asarray(record.observed_rgb, np.float64)
    obs = FaceObservation(normals=record.normals, observed_rgb=record.observed_rgb, mask=record.mask,
                          visibility_bits=record.visibility_bits, grid=grid, face_id=record.face_id)
    idx = usable_pixels(obs)
    transport = Transport(np.asarray(record.visibility_bits), np.asarray(record.normals), grid, threads=threads)
    shading = transport.matmul(p.reshape(-1, 3), dtype=np.float64)
    k = np.array([best_scale_l1(observed[idx, c], shading[idx, c]) for c in range(3)])
    photo = np.maximum(shading * k, 0.0)
    mask = np.asarray(record.mask, bool)
    if gloss is not None:
        exposure = float(np.median(k / np.asarray(gloss.albedo_rgb, np.float64)))
        bits = np.asarray(record.visibility_bits)
        photo[mask] += exposure * glossy_highlight(np.asarray(record.normals)[mask], np.asarray(record.points)[mask],
                                                   bits[mask], grid, p, gloss.roughness, gloss.f0)
    peak = float(photo[mask].max(initial=0.0))
    if not peak > 0:
        raise ValueError(f"{record.face_id}: the probe leaves every masked pixel black")
    return (photo * (IDEAL_PEAK / peak)).astype(np.float32)


class PhotoResidual:
    """One record's usable pixels and transport: ``residual(probe)`` for (H, W, 3) probes on its grid."""

    def __init__(self, record, threads: int = 2) -> None:
        self.grid = LatLongGrid(record.grid_height, record.grid_width)
        obs = FaceObservation(normals=record.normals, observed_rgb=record.observed_rgb, mask=record.mask,
                              visibility_bits=record.visibility_bits, grid=self.grid, face_id=record.face_id)
        idx = usable_pixels(obs)
        self.observed = np.asarray(record.observed_rgb, np.float64)[idx]
        self.transport = Transport(np.asarray(record.visibility_bits)[idx], np.asarray(record.normals)[idx],
                                   self.grid, threads=threads)

    def residual(self, probe: np.ndarray) -> float:
        p = np.asarray(probe, np.float64)
        if p.shape != self.grid.shape + (3,):
            raise ValueError(f"probe {p.shape} is not on the record's {self.grid.height}x{self.grid.width} grid")
        shading = self.transport.matmul(p.reshape(-1, 3), dtype=np.float64)
        return photo_residual(self.observed, shading)
