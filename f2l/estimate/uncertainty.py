"""The sun's uncertainty of one compact-sun estimate: credible cones over its direction and a
predicted relit-scene error, from the evidence the estimate already computed (no refit).

Evidence. The global sun search (f2l.estimate.sun_search) scored every candidate sun texel d_i
(a ~5.6° lattice over the sky) × sky shape s by its weighted squared residual R_is. Over those
candidates, the posterior over the sun's direction is

    p_i ∝ Σ_s exp(-τ (R_is - R_min) / R_min),      τ = ``TEMPERATURE`` (cross-validated),

the relative excess residual as in the elevation profile (f2l.estimate.sun_profile). The
profile's pinned refits (same azimuth, elevations 10-85°) can join as further mass points with
the profile's own posterior weights, mixed in with weight ``PROFILE_SHARE`` (0 by default: their
posterior nearly always sits on one refit, so they narrowed the cones without ranking better).

Posterior cones. Each mass point is spread as a 2-D Gaussian of ``LATTICE_SIGMA_DEG`` per axis (the
lattice's resolution: a point stands for its cell) in the tangent plane of the estimate's sun ĉ,
at the point's log-map offset (its angle from ĉ, towards it); the posterior cone radius p_q is the
weighted q-quantile of the distances from ĉ of ``SPREAD_POINTS`` fixed Gaussian offsets per point:
the angular radius around the estimate holding a share q of the mass.

Calibrated cones. The search's residuals see the sun through f2l's own forward model; on
path-traced faces the error comes mostly from what that model misses, and the posterior cone alone
neither covers it nor ranks the faces by it (docs/experiments/uncertainty.md). So the reported
radius is r_q = k_q exp(β · x), x = [1, ln p_90, lit, overcast]: ``lit`` the share of the face's
pixels facing the estimated sun (n · ĉ > 0; a sun behind the head lights few), ``overcast`` 1 when
the fit judged the light overcast (sun share below ``sun_core_min_share``, no profile). β
(``CONE_COEFFICIENTS``) is the least-squares fit of ln Sun-ang on x over the tuning faces (``make
eval-real``'s tuning part and ``make eval-framings``' seed-0 renders), k_q (``CONE_QUANTILES``) the
q-quantiles of Sun-ang / exp(β · x) there: the tuning faces' cones hold the true sun for 68% / 90%
of them by construction, and ``make eval-real``'s reporting part and held-out maps say whether that
holds (f2l.evaluation.calibration).

Predicted relit error. ``predicted_mae_s`` is a linear regression of the relit-scene MAE (s)
(f2l.metrics.render_metrics) on [1, r_90 / 90°, lit, the search's relative residual R_min / |y|²],
fitted by least squares on the same tuning faces (``MAE_COEFFICIENTS``).

Latent-sky models (f2l.estimate.latent.latent_sun_uncertainty). The mass points are the
coarse search's candidates, every search code at every azimuth step, each at its decoded sky's
brightest texel and scored by its relative L1 residual squared (standing where a squared residual
stands); there is no elevation profile and no overcast judgement (that feature is 0). The same
procedure calibrates them on the same tuning faces estimated with the built-in latent sky
(``LATENT_CONE_COEFFICIENTS``, ``LATENT_CONE_QUANTILES``, ``LATENT_MAE_COEFFICIENTS``). The probe of
a latent sky is not spread.

Conventions: unit directions, +Y up (the grid's), radii in degrees, at most 180°.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["SunUncertainty", "TEMPERATURE", "PROFILE_SHARE", "LATTICE_SIGMA_DEG", "CONE_COEFFICIENTS", "CONE_QUANTILES",
           "MAE_COEFFICIENTS", "LATENT_CONE_COEFFICIENTS", "LATENT_CONE_QUANTILES", "LATENT_MAE_COEFFICIENTS",
           "direction_posterior", "cone_radii_deg", "lit_fraction", "cone_features", "mae_features",
           "calibrated_cones_deg", "predicted_mae_s", "sun_uncertainty"]

TEMPERATURE = 30.0  # tau of the search posterior (chosen by cross-validation on the tuning part)
PROFILE_SHARE = 0.0  # the elevation profile's share of the posterior's mass (tried 0.5: too sharp to help)
LATTICE_SIGMA_DEG = 1.6  # per-axis spread of a mass point: a 5.6° lattice cell's standard deviation
SPREAD_POINTS = 32
MIN_WEIGHT = 1e-6  # mass points below this share of the largest are left out (they move no quantile)
LEVELS = (0.68, 0.90)
# fitted (f2l.evaluation.calibration.fit_uncertainty_model) on every tuning-only sunny face there is: the
# 56 of `make eval-real`'s tuning part and the 147 of `make eval-framings`' seed-0 renders (full, half and
# group framings, each face alone), with the defaults of 2026-11-28 (the built-in sun model's prior
# marginalised over the sun's elevation), tau = 30; docs/experiments/uncertainty.md "Calibrated on 203
# tuning faces" and "Recalibrated after the prior's change"
CONE_COEFFICIENTS = (1.744, 0.2035, -0.5819, 0.7590)  # beta over [1, ln p_90, lit, overcast]
CONE_QUANTILES = (1.445, 2.985)  # k_68, k_90
MAE_COEFFICIENTS = (0.06844, 0.2936, -0.05000, 0.3098)  # over [1, r_90 / 90°, lit, relative residual]
# latent-sky models (f2l.estimate.latent: the coarse search's candidates, no overcast feature), fitted the
# same way on the built-in latent sky's estimates of the same tuning faces, tau = 30;
# docs/experiments/uncertainty.md "Latent skies"
LATENT_CONE_COEFFICIENTS = (1.146, 0.5568, -0.7375, 0.0)
LATENT_CONE_QUANTILES = (1.495, 2.777)
LATENT_MAE_COEFFICIENTS = (0.02328, 0.3150, -0.02478, 2.752)


@dataclass
class SunUncertainty:
    """One estimate's sun uncertainty: calibrated cone radii (deg) meant to hold the true sun with
    68% and 90% probability around the estimate's sun, the predicted relit-scene MAE (s), and
    what they were computed from: the posterior cones (deg), the lit share, whether the fit was
    overcast, the search's best relative residual, the face's mask pixels. ``evidence`` keeps the
    posterior's inputs for calibration (f2l.evaluation.calibration); it is not written anywhere."""

    cone68_deg: float
    cone90_deg: float
    predicted_mae_s: float
    posterior68_deg: float
    posterior90_deg: float
    lit_fraction: float
    overcast_fit: bool
    relative_residual: float
    num_pixels: int
    evidence: dict | None = None


def direction_posterior(totals: np.ndarray, temperature: float = TEMPERATURE) -> np.ndarray:
    """Per candidate direction (rows of ``totals``, (k, S) residuals over sky shapes) the
    posterior weight Σ_s exp(-τ (R - R_min) / R_min), normalised; non-finite residuals weigh 0.

    >>> direction_posterior(np.array([[1.0, 2.0], [1.0, np.inf]]), 0.0).round(3).tolist()
    [0.667, 0.333]
    """
    totals = np.asarray(totals, np.float64).reshape(len(totals), -1)
    finite = np.isfinite(totals)
    lo = float(totals[finite].min())
    excess = np.where(finite, totals - lo, 0.0) / max(abs(lo), 1e-300)
    w = np.where(finite, np.exp(-temperature * excess), 0.0).sum(1)
    return w / w.sum()


def _tangent_offsets_deg(center: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(k, 2) log-map offsets (deg) of unit ``directions`` in the tangent plane at ``center``."""
    c = np.asarray(center, np.float64) / np.linalg.norm(center)
    helper = np.array([0.0, 1.0, 0.0]) if abs(c[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(helper, c)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(c, e1)
    d = np.asarray(directions, np.float64)
    angle = np.arccos(np.clip(d @ c, -1.0, 1.0))
    x, y = d @ e1, d @ e2
    norm = np.hypot(x, y)
    scale = np.where(norm > 1e-12, angle / np.maximum(norm, 1e-12), 0.0)
    return np.degrees(np.stack([x * scale, y * scale], 1))


def _gaussian_offsets(n: int) -> np.ndarray:
    """(n, 2) fixed offsets with a unit 2-D Gaussian's radial quantiles on golden-angle bearings."""
    j = np.arange(n) + 0.5
    radius = np.sqrt(-2.0 * np.log1p(-j / n))
    bearing = j * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([radius * np.cos(bearing), radius * np.sin(bearing)], 1)


_OFFSETS = _gaussian_offsets(SPREAD_POINTS)


def cone_radii_deg(center: np.ndarray, directions: np.ndarray, weights: np.ndarray,
                   levels=LEVELS, sigma_deg: float = LATTICE_SIGMA_DEG) -> tuple[float, ...]:
    """Angular radii (deg) around unit ``center`` holding each of ``levels`` of the mass of the
    points ``directions`` (k, 3) with ``weights`` (k,), each spread as a 2-D Gaussian of
    ``sigma_deg`` per axis in the tangent plane at ``center`` (module docstring)."""
    w = np.asarray(weights, np.float64)
    keep = w > MIN_WEIGHT * w.max()
    offsets = _tangent_offsets_deg(center, np.asarray(directions, np.float64)[keep])
    spread = offsets[:, None, :] + sigma_deg * _OFFSETS[None, :, :]  # (k', M, 2)
    dist = np.hypot(spread[..., 0], spread[..., 1]).reshape(-1)
    mass = np.repeat(w[keep] / w[keep].sum() / SPREAD_POINTS, SPREAD_POINTS)
    order = np.argsort(dist)
    cdf = np.cumsum(mass[order])
    return tuple(float(min(dist[order][min(int(np.searchsorted(cdf, q)), len(dist) - 1)], 180.0)) for q in levels)


def lit_fraction(normals: np.ndarray, sun_direction: np.ndarray) -> float:
    """The share of the unit ``normals`` (N, 3) facing ``sun_direction`` (n · d > 0).

    >>> lit_fraction(np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]), np.array([0.0, 0.0, -1.0]))
    0.0
    """
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    return float(np.mean(n @ np.asarray(sun_direction, np.float64) > 0.0)) if len(n) else 0.0


def cone_features(posterior90_deg: float, lit: float, overcast_fit: bool) -> np.ndarray:
    """The calibrated cone's features [1, ln p_90, lit, overcast] (p_90 floored at 0.1°)."""
    return np.array([1.0, math.log(max(posterior90_deg, 0.1)), lit, float(overcast_fit)])


def calibrated_cones_deg(posterior90_deg: float, lit: float, overcast_fit: bool, coefficients=CONE_COEFFICIENTS,
                         quantiles=CONE_QUANTILES) -> tuple[float, float]:
    """(r_68, r_90) = k_q exp(β · x) (module docstring), at most 180°."""
    scale = math.exp(float(cone_features(posterior90_deg, lit, overcast_fit) @ np.asarray(coefficients)))
    return tuple(min(float(k) * scale, 180.0) for k in quantiles)


def mae_features(cone90_deg: float, lit: float, relative_residual: float) -> np.ndarray:
    """The relit-error regression's features [1, r_90 / 90°, lit, relative residual]."""
    return np.array([1.0, cone90_deg / 90.0, lit, relative_residual])


def predicted_mae_s(cone90_deg: float, lit: float, relative_residual: float, coefficients=MAE_COEFFICIENTS) -> float:
    """The predicted relit-scene MAE (s) (module docstring), floored at 0."""
    return max(float(mae_features(cone90_deg, lit, relative_residual) @ np.asarray(coefficients)), 0.0)


def sun_uncertainty(sun_direction: np.ndarray, candidate_directions: np.ndarray, totals: np.ndarray, yy: float,
                    normals: np.ndarray, overcast_fit: bool, profile_directions: np.ndarray | None = None,
                    profile_weights: np.ndarray | None = None, temperature: float = TEMPERATURE,
                    profile_share: float = PROFILE_SHARE, cone_coefficients=CONE_COEFFICIENTS,
                    cone_quantiles=CONE_QUANTILES, mae_coefficients=MAE_COEFFICIENTS) -> SunUncertainty:
    """The uncertainty of an estimate whose sun is ``sun_direction`` (unit, 3): the search's
    ``candidate_directions`` (k, 3) and residuals ``totals`` (k, S) with the observation's weighted
    squared norm ``yy``; the face's mask ``normals`` (N, 3); whether the fit judged the light
    overcast; the profile's directions (K, 3) and weights (K,) when it ran."""
    dirs = np.asarray(candidate_directions, np.float64)
    w = direction_posterior(totals, temperature)
    if profile_directions is not None and profile_weights is not None and len(profile_weights) and profile_share > 0:
        pw = np.asarray(profile_weights, np.float64)
        dirs = np.concatenate([dirs, np.asarray(profile_directions, np.float64)])
        w = np.concatenate([(1.0 - profile_share) * w, profile_share * pw / pw.sum()])
    p68, p90 = cone_radii_deg(sun_direction, dirs, w)
    lit = lit_fraction(normals, sun_direction)
    r68, r90 = calibrated_cones_deg(p90, lit, overcast_fit, cone_coefficients, cone_quantiles)
    rel = float(np.nanmin(totals) / max(yy, 1e-300))
    return SunUncertainty(
        cone68_deg=r68, cone90_deg=r90, predicted_mae_s=predicted_mae_s(r90, lit, rel, mae_coefficients),
        posterior68_deg=p68, posterior90_deg=p90, lit_fraction=lit, overcast_fit=bool(overcast_fit),
        relative_residual=rel, num_pixels=len(normals),
        evidence={"candidate_directions": np.asarray(candidate_directions, np.float64),
                  "totals": np.asarray(totals, np.float64), "yy": float(yy), "normals": np.asarray(normals, np.float32),
                  "profile_directions": profile_directions, "profile_weights": profile_weights})
