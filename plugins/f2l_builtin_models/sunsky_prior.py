"""Sun+Sky prior features, GMM starts and data-driven probe starts (paper §3.4).

Prior features of a parameter vector (numpy and torch, same formulas), all invariant to the
camera's heading (no azimuth) and to exposure (intensity ratios only):

    sun_elevation_rad
    log_turbidity               log t
    log_kappa                   log κ
    log_sun_to_sky              log(r + 1e-3), r = lum(w_sun) / (π lum(w_sky)): the sun's
                                irradiance at normal incidence over the irradiance of a uniform
                                sky of the same mean radiance (≈ 0 when overcast)
    sky_log_rg, sky_log_bg      log(w_sky_r / w_sky_g), log(w_sky_b / w_sky_g)
    sun_log_rg, sun_log_bg      the same for w_sun (ε = 1e-6 of lum(w_sun) added)

The estimator's prior term scores ``SCORED_FEATURES``, every feature but the elevation (the GMM
marginalised over it): no sun elevation is preferred.

GMM starts: each component mean becomes parameters with w_sky of luminance 1, w_sun from the
ratio and colours, at 4 azimuths (±45°, ±135°); the estimator rescales intensities to the
observation. Probe starts (``fit-probe``): the sun at the brightest upper-hemisphere texel, its
energy above the median sky in a cap of max(5°, 1.5 texels), κ ∈ {1024, 8192}, t = 3.
"""

from __future__ import annotations

import math

import numpy as np
import torch

FEATURE_NAMES = ["sun_elevation_rad", "log_turbidity", "log_kappa", "log_sun_to_sky",
                 "sky_log_rg", "sky_log_bg", "sun_log_rg", "sun_log_bg"]
# Floor on each feature's standard deviation in every GMM component (GmmPrior.widened):
# elevation 6 deg, turbidity x1.3, kappa x1.6, sun-to-sky ratio x1.6, colours 10%.
FEATURE_MIN_STD = (0.1, 0.25, 0.5, 0.5, 0.1, 0.1, 0.1, 0.1)
# The features the estimator's prior term scores: all but the sun's elevation, over which the GMM is
# marginalised (GmmPrior.marginal). The corpus draws the elevation uniformly (5-80 deg); six
# components over it leave a lumpy marginal (modes at 8, 14, 19, 33 and 66 deg, little mass at
# 40-55 deg or above 75 deg) that pulled suns the face cannot place (behind the head, hidden in
# their glow) toward those modes (docs/experiments/sun_profile.md, "The prior's elevation").
SCORED_FEATURES = tuple(name for name in FEATURE_NAMES if name != "sun_elevation_rad")
REC709_LUMA = (0.2126, 0.7152, 0.0722)
RATIO_FLOOR = 1e-3
START_AZIMUTHS_RAD = (-0.75 * math.pi, -0.25 * math.pi, 0.25 * math.pi, 0.75 * math.pi)


def features_numpy(params: np.ndarray) -> np.ndarray:
    """(n, 10) parameters -> (n, 8) prior features (module docstring)."""
    p = np.atleast_2d(np.asarray(params, dtype=np.float64))
    luma = np.asarray(REC709_LUMA)
    w_sky = np.maximum(p[:, 0:3], 1e-12)
    w_sun = np.maximum(p[:, 3:6], 0.0)
    lum_sky = w_sky @ luma
    lum_sun = w_sun @ luma
    sun = w_sun + 1e-6 * lum_sun[:, None] + 1e-300
    return np.column_stack([
        np.clip(p[:, 6], 0.0, 0.5 * math.pi),
        np.log(np.clip(p[:, 8], 1.7, 35.0)),
        np.log(np.clip(p[:, 9], 8.0, 8192.0)),
        np.log(lum_sun / (math.pi * lum_sky) + RATIO_FLOOR),
        np.log(w_sky[:, 0] / w_sky[:, 1]), np.log(w_sky[:, 2] / w_sky[:, 1]),
        np.log(sun[:, 0] / sun[:, 1]), np.log(sun[:, 2] / sun[:, 1]),
    ])


def features_torch(params: torch.Tensor) -> torch.Tensor:
    """(B, 10) -> (B, 8), the differentiable twin of :func:`features_numpy`."""
    luma = torch.as_tensor(REC709_LUMA, dtype=params.dtype, device=params.device)
    w_sky = params[:, 0:3].clamp_min(1e-12)
    w_sun = params[:, 3:6].clamp_min(0.0)
    lum_sky = w_sky @ luma
    lum_sun = w_sun @ luma
    sun = w_sun + 1e-6 * lum_sun[:, None] + 1e-300
    return torch.stack([
        params[:, 6].clamp(0.0, 0.5 * math.pi),
        torch.log(params[:, 8].clamp(1.7, 35.0)),
        torch.log(params[:, 9].clamp(8.0, 8192.0)),
        torch.log(lum_sun / (math.pi * lum_sky) + RATIO_FLOOR),
        torch.log(w_sky[:, 0] / w_sky[:, 1]), torch.log(w_sky[:, 2] / w_sky[:, 1]),
        torch.log(sun[:, 0] / sun[:, 1]), torch.log(sun[:, 2] / sun[:, 1]),
    ], dim=1)


def params_from_features(features: np.ndarray, azimuths=START_AZIMUTHS_RAD) -> np.ndarray:
    """(K, 8) features -> (K * len(azimuths), 10) parameters, w_sky of unit luminance."""
    f = np.atleast_2d(np.asarray(features, dtype=np.float64))
    luma = np.asarray(REC709_LUMA)
    out = []
    for row in f:
        el, log_t, log_k, log_r, s_rg, s_bg, u_rg, u_bg = row
        sky = np.array([math.exp(s_rg), 1.0, math.exp(s_bg)])
        sky /= sky @ luma
        sun = np.array([math.exp(u_rg), 1.0, math.exp(u_bg)])
        ratio = max(math.exp(log_r) - RATIO_FLOOR, 1e-4)
        sun *= ratio * math.pi / (sun @ luma)
        for az in azimuths:
            out.append([*sky, *sun, float(np.clip(el, 0.02, 0.5 * math.pi - 0.02)), az,
                        float(np.clip(math.exp(log_t), 1.7, 35.0)), float(np.clip(math.exp(log_k), 8.0, 8192.0))])
    return np.asarray(out, dtype=np.float64)


def probe_starts(grid, probe_flat: np.ndarray) -> np.ndarray:
    """(2, 10) starts for fitting a probe (L, 3): the sun at its brightest sky texel."""
    flat = np.asarray(probe_flat, dtype=np.float64)
    up = grid.upper_mask.reshape(-1)
    lum = flat @ np.asarray(REC709_LUMA)
    j = int(np.argmax(np.where(up, lum, -np.inf)))
    d = grid.directions_flat[j]
    elevation = math.asin(float(np.clip(d[1], 0.0, 1.0)))
    azimuth = math.atan2(float(d[0]), float(-d[2]))
    sky = np.maximum(np.median(flat[up], axis=0), 1e-9)
    texel_rad = math.pi / grid.height
    cap = up & (grid.directions_flat @ d > math.cos(max(math.radians(5.0), 1.5 * texel_rad)))
    e_sun = np.maximum(((flat[cap] - sky) * grid.solid_angles_flat[cap, None]).sum(axis=0), 1e-9)
    return np.array([[*sky, *e_sun, elevation, azimuth, 3.0, kappa] for kappa in (1024.0, 8192.0)])
