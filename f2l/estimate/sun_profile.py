"""The sun's elevation profile of compact-sun fits (``EstimatorConfig.sun_elevation_profile_deg``).

After the fit, its best start is copied once per listed elevation (those within
``MIN_GAP_DEG`` of its own left out), each copy's sun pinned there and the rest refined for
``cfg.sun_profile_iters`` L-BFGS iterations in one batch. Over the fit and its copies, with
objectives L, the posterior weights are

    w_k ∝ exp(-T (L_k - L_min) / L_min),      T = cfg.sun_profile_temperature,

the estimate's sun direction is the normalised Σ w_k d_k (d_k the copies' sun directions), its
probe the mixture Σ w_k l_k (the estimator renders it), and its parameters those of the lowest
L. Where the face's shading fixes the elevation the weights fall on one start; where it does not
(a sun behind the head) the direction hedges between the elevations the face allows. Why it is
needed: the free fit stalls in elevation (docs/results/eval_real.md, "Does the photo prefer the truth?").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from f2l.estimate.config import EstimatorConfig
from f2l.estimate.lbfgs import run_lbfgs

MIN_GAP_DEG = 2.5  # a pin this close to the fit's own elevation adds nothing


@dataclass
class ElevationPosterior:
    """The fit (row 0) and its pinned copies: their parameters, albedos, ground albedos,
    objectives, highlight k_s (None without ``sun_specular``), the lowest objective's row, the
    posterior weights, the posterior-mean sun direction (3,) and each row's sun direction (K, 3)."""

    params: torch.Tensor
    albedo: torch.Tensor
    ground_albedo: torch.Tensor
    totals: np.ndarray
    ks: torch.Tensor | None
    best: int
    weights: np.ndarray
    sun_direction: np.ndarray
    directions: np.ndarray | None = None  # (K, 3) each row's sun direction (f2l.estimate.uncertainty)


def posterior_weights(totals: np.ndarray, temperature: float) -> np.ndarray:
    """Weights exp(-temperature (L - L_min) / L_min) over objective values, normalised
    (non-finite values weigh 0)."""
    finite = np.isfinite(totals)
    lo = float(np.min(totals[finite]))
    w = np.where(finite, np.exp(-temperature * (np.where(finite, totals, lo) - lo) / max(abs(lo), 1e-12)), 0.0)
    return w / w.sum()


def pinned_copies(prob, unpack, variables, cfg: EstimatorConfig, model):
    """The fitted start (``variables``, one row) copied with its sun's elevation pinned at each of
    ``cfg.sun_elevation_profile_deg`` and the rest refined: (params, albedo, ground albedo,
    totals (K,)), or None when no elevation is left."""
    el_idx = model.sun_layout.elevation
    with torch.no_grad():
        fitted = float(unpack(*variables)[0][0, el_idx])
    pins = [math.radians(e) for e in cfg.sun_elevation_profile_deg
            if abs(math.radians(e) - fitted) > math.radians(MIN_GAP_DEG)]
    if not pins:
        return None
    pin = torch.as_tensor(pins, dtype=variables[0].dtype)[:, None]

    def unpack_pinned(x_theta, x_gnd, x_rho):
        params, rho, rho_g = unpack(x_theta, x_gnd, x_rho)
        return torch.cat([params[:, :el_idx], pin, params[:, el_idx + 1 :]], 1), rho, rho_g

    copies = tuple(v.expand(len(pins), *v.shape[1:]).clone() for v in variables)
    copies, _ = run_lbfgs(prob, unpack_pinned, copies, cfg, cfg.sun_profile_iters)
    with torch.no_grad():
        params, rho, rho_g = unpack_pinned(*copies)
        total, _ = prob.objective(params, rho, rho_g)
    return params, rho, rho_g, total.numpy()


def elevation_posterior(prob, unpack, variables, fit, best: int, cfg: EstimatorConfig, model) -> ElevationPosterior | None:
    """The posterior over the sun's elevation of a finished fit: ``variables`` its unconstrained
    starts, ``fit`` = (params, albedo, ground albedo, totals, ks) of those starts, ``best`` the
    lowest objective's start. None when no pinned copy is left."""
    params, rho, rho_g, totals, ks = fit
    pinned = pinned_copies(prob, unpack, tuple(v[best : best + 1] for v in variables), cfg, model)
    if pinned is None:
        return None
    keep = slice(best, best + 1)
    params = torch.cat([params[keep], pinned[0]])
    totals = np.concatenate([totals[keep], pinned[3]])
    if ks is not None:  # the last objective evaluated was the copies'
        ks = torch.cat([ks[keep], prob.last_ks])
    weights = posterior_weights(totals, cfg.sun_profile_temperature)
    lowest = int(np.nanargmin(totals))
    dirs = np.stack([model.sun_direction(p.numpy().astype(np.float64)) for p in params])
    mean = (weights[:, None] * dirs).sum(0)
    norm = float(np.linalg.norm(mean))
    return ElevationPosterior(params=params, albedo=torch.cat([rho[keep], pinned[1]]),
                              ground_albedo=torch.cat([rho_g[keep], pinned[2]]), totals=totals, ks=ks,
                              best=lowest, weights=weights, sun_direction=mean / norm if norm > 1e-9 else dirs[lowest],
                              directions=dirs)
