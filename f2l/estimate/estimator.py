"""The generic inverse-lighting estimator (paper §3.2): fits one face's problem
(``f2l.estimate.problem.FaceProblem``: forward model and objective) with every lighting model.

Bounds are handled by reparameterisation (``BoxTransform``); all starts are optimised together as
one batched problem with torch's L-BFGS (strong-Wolfe line search). Sun models start from the
global sun search (f2l.estimate.sun_search), are optimised in psi = albedo x weight, and end with
the sun's elevation profile (f2l.estimate.sun_profile) and the sun's uncertainty from the search's
scores (f2l.estimate.uncertainty). Linear models get least-squares starts and
IRLS (f2l.estimate.linear); latent-sky models their own batched search (f2l.estimate.latent).
"""

from __future__ import annotations

import functools
import time
from functools import lru_cache

import numpy as np
import torch

from f2l.estimate.config import EstimateResult, EstimatorConfig  # noqa: F401  (re-exported)
from f2l.estimate.latent import estimate_latent_sky
from f2l.estimate.lbfgs import run_lbfgs
from f2l.estimate.observation import (BLACK_LEVEL, CLIP_LEVEL, EstimationError, FaceObservation,  # noqa: F401
                                      clipped_pixels, highlight_pixels, usable_pixels)
from f2l.estimate.params import BoxTransform
from f2l.estimate.problem import FaceProblem
from f2l.estimate.skin import _albedo_gmm_terms, albedo_prior_nll, skin_albedo_gmm, skin_albedo_mean
from f2l.estimate import sun_search
from f2l.estimate.sun_profile import elevation_posterior
from f2l.estimate.sun_spread import spread_sky_radiance
from f2l.estimate.uncertainty import sun_uncertainty
from f2l.models.base import LightingModel
from f2l.models.capabilities import LatentSky


def _given_sun_starts(template: np.ndarray, directions: np.ndarray, layout) -> np.ndarray:
    """(k, P) copies of ``template`` with the sun moved to each of ``directions`` (k, 3) (unit,
    +Y up, azimuth 0 = -Z: the grid's convention), elevation kept inside (0, 90°) like the search's."""
    if directions.ndim != 2 or directions.shape[1] != 3 or not np.isfinite(directions).all() or len(directions) == 0:
        raise ValueError(f"sun_starts must be a non-empty (k, 3) array of finite directions, got shape {directions.shape}")
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    starts = np.repeat(template[None], len(d), axis=0)
    starts[:, layout.elevation] = np.clip(np.arcsin(np.clip(d[:, 1], -1, 1)), 0.01, 0.5 * np.pi - 0.01)
    starts[:, layout.azimuth] = np.arctan2(d[:, 0], -d[:, 2])
    return starts


def estimate(obs: FaceObservation, model: LightingModel, config: EstimatorConfig | None = None,
             sun_starts: np.ndarray | None = None) -> EstimateResult:
    """Estimate lighting, albedo and ground albedo for one face with ``model``.

    ``sun_starts`` ((k, 3) unit directions in the probe's frame; ``compact-sun`` models only): start
    the fit from these suns in place of the global search's candidates, each with the weights of
    the search's best one. A diagnostic (``f2l eval search`` starts fits at the true sun)."""
    cfg = config or EstimatorConfig()
    if isinstance(model, LatentSky) and sun_starts is None:  # decoded latent skies: batched start search
        return estimate_latent_sky(obs, model, cfg)  # (f2l.estimate.latent)
    t_start = time.perf_counter()
    dtype = torch.float64
    torch.set_num_threads(max(1, cfg.threads))
    prob = FaceProblem(obs, model, cfg, dtype)
    if sun_starts is not None and prob.hybrid is None:
        raise ValueError(f"sun_starts needs a compact-sun model over the sky; {model.name!r} is not one")
    # The fit's tensors are small (N x 3 per start): one intra-op thread is 10-50x faster than two
    # threads that spin against each other and against BLAS (measured; see docs/performance.md).
    torch.set_num_threads(1)

    if prob.linear and not prob.sky:
        return _estimate_linear(obs, model, cfg, prob, t_start)

    # ---- starting points -------------------------------------------------------------------------------
    lo, hi = model.bounds()
    box = BoxTransform(lo, hi)
    gmm = skin_albedo_gmm()
    if cfg.fixed_albedo is not None:
        albedo_starts = [np.asarray(cfg.fixed_albedo, dtype=np.float64)]
    else:
        order = np.argsort(-gmm["weights"])[: max(1, cfg.albedo_starts)]
        albedo_starts = [skin_albedo_mean()] + [np.exp(gmm["means"][j]) for j in order[1:]]
    starts_theta, starts_rho = [], []
    if prob.linear:
        for rho in albedo_starts:
            starts_theta.append(prob.least_squares_start(rho, cfg.ground_albedo_init))
            starts_rho.append(rho)
    t_search = time.perf_counter()
    scores = None  # the sun search's scores: the direction posterior's evidence (f2l.estimate.uncertainty)
    if prob.hybrid is not None:
        setup = prob.search_setup()  # FaceProblem.sun_search_starts, keeping the scores
        scores = prob.search_scores(setup, cfg.ground_albedo_init)
        prob.search_candidates = sun_search.pick(scores, prob.grid)
        initial = prob.starts_from(prob.search_candidates, setup[1], albedo_starts[0])
        if sun_starts is not None:
            initial = _given_sun_starts(initial[0], np.atleast_2d(np.asarray(sun_starts, np.float64)), model.sun_layout)
        # the azimuth is periodic: optimise it unbounded (a sigmoid would pin suns behind the head)
        lo, hi = lo.copy(), hi.copy()
        lo[model.sun_layout.azimuth], hi[model.sun_layout.azimuth] = -np.inf, np.inf
        box = BoxTransform(lo, hi)
    else:
        initial = [] if prob.linear else model.initial_points()
    search_s = time.perf_counter() - t_search
    for theta in initial:
        starts_theta.append(np.asarray(theta, dtype=np.float64))
        starts_rho.append(albedo_starts[0])
    theta0 = np.stack(starts_theta)
    rho0 = np.clip(np.stack(starts_rho), 1e-3, 1 - 1e-3)
    if not prob.linear and prob.hybrid is None:
        # scale non-linear starts so their mean shading matches the observation (cheap, one pass)
        with torch.no_grad():
            tl, _ = prob.light_transport(torch.as_tensor(theta0, dtype=dtype),
                                         torch.full((len(theta0),), cfg.ground_albedo_init, dtype=dtype))
            pred = (prob.apparent(torch.as_tensor(rho0, dtype=dtype))[:, None, :] * tl).mean((1, 2)).numpy()
        del tl
        scale = prob.target_scale / np.maximum(pred, 1e-12)
        theta0 = _scale_intensities(model, theta0, scale, lo, hi)

    # Sun models are optimised in psi = albedo x RGB weight (what the shading sees) rather than in
    # the weights: the albedo then moves only the priors, not the data term, and L-BFGS is not
    # slowed by the albedo-exposure ambiguity. Other models keep the weights.
    weight_idx = None
    if prob.hybrid is not None:
        weight_idx = list(model.sun_layout.sky_rgb) + list(model.sun_layout.sun_rgb)
        theta0 = theta0.copy()
        theta0[:, weight_idx] *= np.tile(prob.apparent(rho0), 2)
    x_theta = torch.tensor(box.to_unconstrained(theta0), dtype=dtype)
    x_rho = torch.tensor(np.log(rho0) - np.log1p(-rho0), dtype=dtype)
    g0 = np.clip(cfg.ground_albedo_init, 1e-3, 1 - 1e-3)
    x_gnd = torch.tensor(np.full(len(theta0), np.log(g0) - np.log1p(-g0)), dtype=dtype)
    fixed_rho = None if cfg.fixed_albedo is None else torch.as_tensor(np.asarray(cfg.fixed_albedo, np.float64), dtype=dtype)

    def unpack(x_theta, x_gnd, x_rho):
        params = box.to_params(x_theta)
        rho = torch.sigmoid(x_rho) if fixed_rho is None else fixed_rho.expand(len(x_theta), 3)
        if weight_idx is not None:
            seen = prob.apparent(rho).repeat(1, 2)
            params = torch.cat([params[:, :6] / seen, params[:, 6:]], 1) if weight_idx == list(range(6)) \
                else params.index_copy(1, torch.as_tensor(weight_idx), params[:, weight_idx] / seen)
        return params, rho, torch.sigmoid(x_gnd)

    t_fit = time.perf_counter()
    sun_core = 1.0 if prob.hybrid is not None else 0.0
    variables = (x_theta, x_gnd, x_rho)
    iterations = 0
    budget = cfg.max_iter
    if prob.hybrid is not None and len(theta0) > 1 and 0 < cfg.sun_all_starts_iters < budget:
        # every start for a few iterations, then only the best: batched L-BFGS shares one line
        # search, so a poor start slows the good one down (and costs its share of each step)
        variables, its = run_lbfgs(prob, unpack, variables, cfg, cfg.sun_all_starts_iters)
        iterations += its
        budget -= its
        with torch.no_grad():
            total, _ = prob.objective(*unpack(*variables))
        keep = int(np.nanargmin(total.numpy()))
        variables = tuple(v[keep : keep + 1].clone() for v in variables)
        if cfg.sun_core_min_share > 0:
            with torch.no_grad():
                share = _sun_share(model, unpack(*variables)[0][0].numpy())
            if share < cfg.sun_core_min_share:  # overcast solution: no exact sun visibility needed
                prob.hybrid.core_texels = 0
                sun_core = 0.0
    variables, its = run_lbfgs(prob, unpack, variables, cfg, budget)
    iterations += its
    params, rho, rho_g, totals, best = fitted_starts(prob, unpack, variables, "optimisation")
    fit_s = time.perf_counter() - t_fit
    converged = its < budget

    profile_s, sun_direction, weights, profile_dirs = 0.0, None, None, None
    ks = prob.last_ks if prob.spec is not None else None  # the highlight's k_s of each start (sun_specular)
    if prob.hybrid is not None and sun_core > 0 and cfg.sun_elevation_profile_deg:
        t_profile = time.perf_counter()
        post = elevation_posterior(prob, unpack, variables, (params, rho, rho_g, totals, ks), best, cfg, model)
        if post is not None:  # the fit and its pinned copies (f2l.estimate.sun_profile)
            params, rho, rho_g, totals, ks = post.params, post.albedo, post.ground_albedo, post.totals, post.ks
            best, weights, sun_direction, profile_dirs = post.best, post.weights, post.sun_direction, post.directions
        profile_s = time.perf_counter() - t_profile

    best_params = params[best : best + 1]
    best_np = best_params[0].numpy().astype(np.float64)
    if sun_direction is None:
        sun_direction = model.sun_direction(best_np)
    t_uncertainty = time.perf_counter()
    uncertainty = None if scores is None or sun_direction is None else sun_uncertainty(
        sun_direction, prob.grid.directions_flat[scores.texels], scores.total, scores.yy,
        np.asarray(obs.normals)[np.asarray(obs.mask, bool)], sun_core == 0.0, profile_dirs, weights)
    uncertainty_s = time.perf_counter() - t_uncertainty
    spread_kappa = None
    with torch.no_grad():
        # the profile's mixture over its components that weigh anything at float32 (weights below
        # 1e-9 of the largest move no texel of the probe): each costs a radiance and a spread lobe
        chosen = [best] if weights is None else [i for i in range(len(totals)) if weights[i] >= 1e-9 * weights.max()]
        spread = cfg.sun_spread > 0 and uncertainty is not None and sun_core > 0
        if spread and prob.sky:  # every row is written below: the sky's by the spread, the ground's from E_h
            rads = torch.zeros(len(chosen), prob.grid.size, 3, dtype=params.dtype)
        else:
            rads = prob.radiance(params[chosen]).clone()
        if spread:  # f2l.estimate.sun_spread
            radius = np.radians(cfg.sun_spread * uncertainty.cone68_deg)
            rads[:, : prob.L_sky], kappas = spread_sky_radiance(model, params[chosen], radius)
            spread_kappa = float(kappas[0 if weights is None else chosen.index(best)])
        if prob.sky:
            e_h = (prob.e_sky[None, :, None] * rads[:, : prob.L_sky]).sum(1)
            rads[:, prob.L_sky :] = rho_g[chosen][:, None, None] / np.pi * e_h[:, None, :]
        rads = rads.clamp_min(0.0)
        rad = rads[0] if weights is None else torch.einsum("b,blc->lc", torch.as_tensor(weights[chosen], dtype=rads.dtype), rads)
    probe = rad.numpy().reshape(obs.grid.height, obs.grid.width, 3).astype(np.float32)
    if not np.isfinite(probe).all():
        raise EstimationError("estimated probe is not finite")
    runtime = time.perf_counter() - t_start
    return EstimateResult(
        params=best_np,
        param_names=list(model.param_names),
        albedo=rho[best].numpy().astype(np.float64),
        ground_albedo=float(rho_g[best]) if prob.sky else None,
        loss=float(totals[best]),
        iterations=iterations,
        converged=bool(converged),
        runtime_s=runtime,
        probe=probe,
        sun_direction=sun_direction,
        timings={"precompute_s": prob.precompute_s, "search_s": search_s, "fit_s": fit_s, "profile_s": profile_s,
                 "uncertainty_s": uncertainty_s, "total_s": runtime, "sun_core": sun_core},
        start_losses=[float(v) for v in totals],
        num_pixels_used=int(prob.idx.size),
        specular_ks=float(ks[best]) if ks is not None else None,
        sun_uncertainty=uncertainty,
        sun_spread_kappa=spread_kappa,
    )


def fitted_starts(prob, unpack, variables, what: str):
    """The fitted starts' parameters (as ``unpack`` gives them), their objectives (numpy) and the
    lowest one's index; raises EstimationError naming ``what`` when no objective is finite."""
    with torch.no_grad():
        params, rho, side = unpack(*variables)
        total, _ = prob.objective(params, rho, side)
    totals = total.numpy()
    if not np.isfinite(totals).any():
        raise EstimationError(f"{what} diverged: objective is not finite for any start")
    return params, rho, side, totals, int(np.nanargmin(totals))


def _estimate_linear(obs, model, cfg: EstimatorConfig, prob: FaceProblem, t_start: float) -> EstimateResult:
    """Sphere-domain linear models: IRLS on psi = rho * theta, then the albedo split (linear.py).

    BLAS runs single-threaded here: the K x K systems and the 3-variable albedo split are too
    small to share, and waking OpenBLAS's second thread for each of them cost more than the
    whole fit on 2 cores (0.16 s against 0.09 s for 25 SH bands, docs/performance.md).
    """
    with _blas_controller().limit(limits=1, user_api="blas"):
        return _estimate_linear_fit(obs, model, cfg, prob, t_start)


@lru_cache(maxsize=1)
def _blas_controller():
    """threadpoolctl's controller, found once (discovering the libraries costs ~5 ms a call)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def _estimate_linear_fit(obs, model, cfg: EstimatorConfig, prob: FaceProblem, t_start: float) -> EstimateResult:
    from f2l.estimate import linear

    t_fit = time.perf_counter()
    A = prob.TB.numpy()
    y = prob.target.numpy()
    rho = np.asarray(cfg.fixed_albedo if cfg.fixed_albedo is not None else skin_albedo_mean(), dtype=np.float64)
    psi = prob.least_squares_start(np.ones(3), 0.0).reshape(-1, 3)
    total_iters, converged = 0, False
    for round_ in range(2):
        prior = linear.prior_diag_for(model, psi / rho[None, :], rho, cfg.light_prior_weight)
        iters = cfg.irls_iters[round_]
        solve = functools.partial(
            linear.solve_psi, neg_basis=prob.neg_basis.numpy(), neg_w=prob.neg_weights.numpy(),
            prior_diag=prior, eps=cfg.charbonnier_eps, scale=prob.target_scale,
            neg_weight=cfg.negativity_weight, tol=cfg.irls_tolerance, floor=cfg.irls_floor)
        warm = min(cfg.irls_warm_iters, iters - 1) if round_ == 0 and cfg.irls_warm_stride > 1 else 0
        if warm > 0 and len(A) >= 64 * cfg.irls_warm_stride:
            psi, its = solve(A=A[:: cfg.irls_warm_stride], y=y[:: cfg.irls_warm_stride], psi0=psi, iters=warm)
            total_iters += its
            iters -= warm
        psi, its = solve(A=A, y=y, psi0=psi, iters=iters)
        total_iters += its
        converged = its < iters
        if cfg.fixed_albedo is None and round_ == 0:
            rho = linear.solve_albedo(model, psi, rho, cfg.light_prior_weight, cfg.albedo_prior_weight,
                                      albedo_prior_nll, _albedo_gmm_terms())
    theta = (psi / rho[None, :]).reshape(-1)
    dtype = prob.dtype
    with torch.no_grad():
        params = torch.as_tensor(theta, dtype=dtype)[None]
        total, _ = prob.objective(params, torch.as_tensor(rho, dtype=dtype)[None], torch.zeros(1, dtype=dtype))
        rad = prob.radiance(params)[0]
    fit_s = time.perf_counter() - t_fit
    loss = float(total[0])
    if not np.isfinite(loss):
        raise EstimationError("optimisation diverged: objective is not finite")
    probe = np.maximum(rad.numpy(), 0.0).reshape(obs.grid.height, obs.grid.width, 3).astype(np.float32)
    runtime = time.perf_counter() - t_start
    return EstimateResult(
        params=theta, param_names=list(model.param_names), albedo=rho, ground_albedo=None, loss=loss,
        iterations=total_iters, converged=bool(converged), runtime_s=runtime, probe=probe,
        sun_direction=model.sun_direction(theta),
        timings={"precompute_s": prob.precompute_s, "fit_s": fit_s, "total_s": runtime},
        start_losses=[loss], num_pixels_used=int(prob.idx.size),
    )


def _sun_share(model, params: np.ndarray) -> float:
    """lum(w_sun) / (lum(w_sun) + pi lum(w_sky)): the sun's share of a horizontal plane's
    irradiance under a sun at the zenith and a uniform sky of the same mean radiance."""
    layout = model.sun_layout
    luma = np.array([0.2126, 0.7152, 0.0722])
    sun = float(np.maximum(params[list(layout.sun_rgb)], 0) @ luma)
    sky = float(np.maximum(params[list(layout.sky_rgb)], 0) @ luma)
    return sun / max(sun + np.pi * sky, 1e-300)


def _scale_intensities(model, theta0, scale, lo, hi):
    """Multiply the non-negative, unbounded-above parameters (intensities) by a per-start scale."""
    intensity = np.isfinite(lo) & (lo >= 0) & ~np.isfinite(hi)
    out = theta0.copy()
    out[:, intensity] *= scale[:, None]
    return out
