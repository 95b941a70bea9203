"""One light for several faces: the joint estimate (faces of one photo, or of one session).

Faces under the same sky see it from several sides and cast their shadows in different
directions. The joint estimate fits one set of lighting parameters theta to all of them, with a
skin albedo rho_i and a ground albedo rho_g,i per face and a log exposure per exposure group
(photo) after the first:

    L(theta, rho, rho_g, e) = sum_i w_i [D_i(gain_i theta, rho_i, rho_g,i) + psi_rho(rho_i)]
                              + w_l psi_l(theta) (+ the sun-elevation prior, the negativity term),

D_i face i's data term (``FaceProblem.data_term``: mean Charbonnier / mean observation), the
model's own prior counted once, gain_i = exp(e_group(i)) multiplying the light's intensities.
The weights w_i (summing to the number of faces) follow what each face can tell: its usable
pixels (capped as the fit caps them) over its relative noise plus a model-misfit floor,
n_i / (sigma_i^2 + SIGMA_MODEL^2).

Sun models (capability ``compact-sun``) score every sun direction and sky shape against all the
faces at once (``sun_search.combine``), are fitted in psi = mean apparent albedo x weight, and end
with the sun's elevation profile, as one face is (f2l.estimate.estimator). Linear models start from
the stacked least squares, other models from their initial points; all then run the same batched
L-BFGS. Latent-sky models have their own joint fit (f2l.estimate.latent_joint).

Faces that disagree with the group's light (in another's shadow, under a hat, lit by a reflector,
showing none of the sun) are left out and the rest refitted (f2l.estimate.joint_faces).

The result without a face is the result of the group without that face, bit for bit. A group of one
is :func:`f2l.estimate.estimator.estimate`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from f2l.estimate import joint_faces, sun_search
from f2l.estimate.config import EstimateResult, EstimatorConfig
from f2l.estimate.estimator import _sun_share, estimate, fitted_starts
from f2l.estimate.joint_common import (DISAGREE_RATIO, FaceShare, JointResult, JointUnsupported,  # noqa: F401
                                       face_noise, face_weights)
from f2l.estimate.latent_joint import estimate_joint_latent
from f2l.estimate.lbfgs import minimise, run_lbfgs
from f2l.estimate.observation import EstimationError, FaceObservation
from f2l.estimate.params import BoxTransform
from f2l.estimate.problem import FaceProblem
from f2l.estimate.skin import skin_albedo_mean
from f2l.estimate.sun_profile import elevation_posterior
from f2l.estimate.sun_spread import spread_sky_radiance
from f2l.estimate.uncertainty import sun_uncertainty
from f2l.models.base import LightingModel
from f2l.models.capabilities import LatentSky

LINEAR_MIN_ITERS = 50
EXTRA_ITERS_PER_GAIN = 12  # and for each exposure gain (photos after the first): they start at 1


class JointProblem:
    """Several faces' problems under one light: the objective of the module docstring, in the
    form the estimator's L-BFGS and elevation profile use (``objective(params, albedo, side)``,
    albedo (B, K, 3), side (B, K + E - 1): the ground albedos, then the log gains)."""

    def __init__(self, problems: list[FaceProblem], weights: np.ndarray, exposure_group: np.ndarray):
        self.faces = problems
        self.first = problems[0]
        self.model, self.cfg = self.first.model, self.first.cfg
        self.weights = [float(w) for w in weights]
        self.group = np.asarray(exposure_group, np.int64)
        self.num_gains = int(self.group.max())  # exposure groups after the first
        self.hybrid = self.first.hybrid
        self.spec = None
        self.last_data = None
        self.extra_prior = None  # optional params (B, P) -> (B,) added once (a video's temporal prior)
        self.share_parts = False  # evaluate the light's parts once for all faces (objective)
        self.albedo_group = None  # (K,) ints: faces sharing one skin albedo (_fit), or None
        if self.num_gains:
            self.intensity = intensity_mask(self.model)

    @property
    def K(self) -> int:
        return len(self.faces)

    def gains(self, side: torch.Tensor) -> torch.Tensor:
        """(B, K) exposure gain of each face: exp of its group's log gain (the first group's is 0)."""
        logs = torch.cat([side.new_zeros(len(side), 1), side[:, self.K :]], 1)
        return torch.exp(logs[:, torch.as_tensor(self.group)])

    def face_params(self, params: torch.Tensor, gain: torch.Tensor) -> torch.Tensor:
        """The light as face i sees it: the intensities scaled by its gain (B,)."""
        if not self.num_gains:
            return params
        mask = torch.as_tensor(self.intensity)
        return torch.where(mask[None], params * gain[:, None], params)

    def objective(self, params, albedo, side):
        """Per-start joint objective (B,) and its weighted data term (B,); keeps each face's data
        term of the last call (``last_data``, (K, B))."""
        total = self.first.light_prior(params)
        gains = self.gains(side) if self.num_gains else None
        data, per_face, rad0 = 0.0, [], None
        # one light, one evaluation of its parts for all faces (a compact-sun model without gains;
        # ``share_parts``: the gradients then sum in another order, so results move in the last bits)
        share = self.share_parts and gains is None and self.hybrid is not None and self.K > 1
        parts = self.model.light_parts(params) if share else None
        for i, prob in enumerate(self.faces):
            p_i = params if gains is None else self.face_params(params, gains[:, i])
            d_i, rad = prob.data_term(p_i, albedo[:, i], side[:, i], parts)
            if i == 0:
                rad0 = rad
            a_i = prob.albedo_term(albedo[:, i])
            data = data + self.weights[i] * d_i
            total = total + self.weights[i] * (d_i if a_i is None else d_i + a_i)
            per_face.append(d_i.detach())
        extra = None if self.extra_prior is None else self.extra_prior(params)
        for term in (self.first.sun_elevation_term(params), self.first.negativity_term(params, rad0), extra):
            if term is not None:
                total = total + term
        self.last_data = torch.stack(per_face)
        return total, data


def intensity_mask(model: LightingModel) -> np.ndarray:
    """Which parameters scale with the light's intensity: every coefficient of a linear model,
    the sky and sun weights of a compact-sun one, else the non-negative parameters unbounded above
    (as the estimator's start scaling reads them). Raises :class:`JointUnsupported` if none."""
    from f2l.models.capabilities import CompactSun, LinearRadiance

    P = len(model.param_names)
    if isinstance(model, LinearRadiance):
        return np.ones(P, bool)
    if isinstance(model, CompactSun):
        mask = np.zeros(P, bool)
        mask[list(model.sun_layout.sky_rgb) + list(model.sun_layout.sun_rgb)] = True
        return mask
    lo, hi = model.bounds()
    mask = np.isfinite(lo) & (lo >= 0) & ~np.isfinite(hi)
    if not mask.any():
        raise JointUnsupported(f"model {model.name!r} has no intensity parameters: faces of different photos "
                               "(different exposures) cannot share its light")
    return mask


def estimate_joint(observations: list[FaceObservation], model: LightingModel, config: EstimatorConfig | None = None,
                   exposure_group: list[int] | None = None, pixel_rc: list | None = None,
                   disagree_ratio: float | None = DISAGREE_RATIO, albedo_group: list[int] | None = None,
                   share_parts: bool = False) -> JointResult:
    """One light for ``observations`` (module docstring).

    ``exposure_group`` (K,) ints: faces with the same number were taken with the same exposure
    (one photo); None: all one photo. ``pixel_rc``: each face's pixel positions, for its noise.
    ``disagree_ratio`` None keeps every face. ``albedo_group`` (K,) ints: faces with the same
    number share one skin albedo (one person in several frames); None: each face its own (not for
    latent-sky models). ``share_parts``: evaluate the light once for all faces per step (faster;
    the gradients sum in another order, so the result moves in its last bits). Raises
    EstimationError when no face can be used."""
    t_start = time.perf_counter()
    cfg = config or EstimatorConfig()
    K = len(observations)
    if K == 0:
        raise EstimationError("joint estimate: no faces")
    if isinstance(model, LatentSky) and K > 1:
        return estimate_joint_latent(observations, model, cfg, exposure_group=exposure_group, pixel_rc=pixel_rc,
                                     disagree_ratio=disagree_ratio)  # f2l.estimate.latent_joint
    groups = _renumber(exposure_group if exposure_group is not None else [0] * K)
    noise = [face_noise(o, None if pixel_rc is None else pixel_rc[i]) for i, o in enumerate(observations)]
    if cfg.neighbour_shadows and K > 1:  # the photo's other heads shade each face (f2l.estimate.neighbours)
        from f2l.estimate.neighbours import with_neighbours

        observations, _ = with_neighbours(list(observations), [int(g) for g in groups])
    shares = [FaceShare(face_id=o.face_id, weight=0.0) for o in observations]
    torch.set_num_threads(max(1, cfg.threads))
    problems: dict[int, FaceProblem] = {}
    for i, o in enumerate(observations):
        if K == 1:
            break
        try:
            problems[i] = FaceProblem(o, model, cfg, torch.float64)
        except EstimationError as exc:
            shares[i].used, shares[i].reason = False, f"bad_face: {exc}"
    active = list(range(K)) if K == 1 else sorted(problems)
    if len(active) > 1 and problems[active[0]].hybrid is not None:  # one sun search setup for all faces
        setup = problems[active[0]].search_setup()
        for i in active:
            problems[i]._setup = setup
    if not active:
        raise EstimationError("joint estimate: no usable face (" + "; ".join(s.reason for s in shares) + ")")
    torch.set_num_threads(1)
    seen_agreement: dict[int, float] = {}
    seen_sun: dict[int, tuple[float, float]] = {}
    seen_dark: dict[int, float] = {}
    if disagree_ratio is not None and len(active) > 2 and problems[active[0]].hybrid is not None:
        support = joint_faces.consensus(problems, active, cfg, disagree_ratio) or {i: 0.0 for i in active}
        for i in active:
            if support[i] > disagree_ratio:
                shares[i].used = False
                shares[i].reason = (f"disagrees with the group's light: residual {support[i]:.2f}x its own best under "
                                    f"the light most faces agree with (limit {disagree_ratio:.2f}); left out")
        active = [i for i in active if support[i] <= disagree_ratio]
    while True:
        result, fit = _fit_group([observations[i] for i in active], [problems.get(i) for i in active], model, cfg,
                                 [noise[i] for i in active], groups[active],
                                 None if albedo_group is None else [albedo_group[i] for i in active], share_parts)
        if fit is None:
            break
        agreement = joint_faces.agreements(problems, fit, cfg)
        seen = joint_faces.sun_seen_of(problems, fit, cfg)
        seen_agreement.update(agreement)
        seen_sun.update(seen)
        if disagree_ratio is None:
            break
        worst, why, shade = joint_faces.leaving(fit, active, groups, agreement, seen, disagree_ratio)
        seen_dark.update(shade)
        if worst is None:
            break
        shares[worst].used, shares[worst].reason = False, why
        active = [i for i in active if i != worst]
    for i, s in enumerate(shares):
        s.agreement = seen_agreement.get(i)
        s.sun_seen, s.sun_share = seen_sun.get(i, (None, None))
        s.darkness = seen_dark.get(i)
    if fit is None:  # one face left: its own estimate
        shares[active[0]].weight = 1.0
        shares[active[0]].albedo, shares[active[0]].ground_albedo = result.albedo, result.ground_albedo
    else:
        for j, i in enumerate(active):
            s = shares[i]
            s.weight, s.albedo, s.ground_albedo = fit.weights[j], fit.albedo[j], fit.ground[j]
            s.gain, s.data = fit.gain[j], fit.data[j]
    result.runtime_s = time.perf_counter() - t_start
    result.timings.update(total_s=result.runtime_s, faces=float(len(active)))
    return JointResult(result, shares)


def _renumber(groups) -> np.ndarray:
    """Exposure groups as 0, 1, ... in order of first appearance (the first face's group is 0)."""
    seen: dict = {}
    return np.array([seen.setdefault(g, len(seen)) for g in groups], np.int64)


@dataclass
class _Fit:
    """What the tests of f2l.estimate.joint_faces and the face rows need of a joint fit (keyed by
    face index; ``problems``, the fitted faces' problems, set after the fit)."""

    weights: list[float]
    params: np.ndarray
    albedo: dict
    ground: dict
    gain: dict
    data: dict
    index: list[int]


def _fit_group(observations, problems, model, cfg: EstimatorConfig, noise, groups,
               albedo_group=None, share_parts: bool = False) -> tuple[EstimateResult, _Fit | None]:
    """The joint fit of one set of faces; a set of one is the single-face estimate (bit for bit)."""
    if len(observations) == 1:
        return estimate(observations[0], model, cfg), None
    t_start = time.perf_counter()
    weights = face_weights(observations, cfg, noise)
    jp = JointProblem(problems, weights, _renumber(groups))
    jp.albedo_group = None if albedo_group is None else _renumber(albedo_group)
    jp.share_parts = share_parts
    # every face's pixels, in the one camera frame: the uncertainty's lit share pools them
    jp.normals = np.concatenate([np.asarray(o.normals, np.float64)[np.asarray(o.mask, bool)] for o in observations])
    return _fit(jp, model, cfg, t_start, [o.face_id for o in observations])


def refit_joint(observations: list[FaceObservation], model: LightingModel, start: np.ndarray,
                config: EstimatorConfig | None = None, *, extra_prior=None,
                exposure_group: list[int] | None = None, pixel_rc: list | None = None,
                problems: list | None = None, albedo_group: list[int] | None = None) -> tuple[EstimateResult, list[FaceShare]]:
    """One light for ``observations`` fitted from ``start`` (the model's parameters, e.g. the last
    window's light): no sun search, no disagreement tests, ``config.max_iter`` L-BFGS iterations
    (the elevation profile runs only if ``config.sun_elevation_profile_deg`` is set).
    ``extra_prior`` (params (B, P) tensor -> (B,)) is added to the objective once. Not for
    latent-sky models (raises :class:`JointUnsupported`). ``problems``: the faces' FaceProblems
    built before with this model and config (a clip's windows share faces); None builds them.
    ``albedo_group`` as :func:`estimate_joint`'s.
    Returns the result and each face's share."""
    t_start = time.perf_counter()
    cfg = config or EstimatorConfig()
    if isinstance(model, LatentSky):
        raise JointUnsupported(f"model {model.name!r}: a warm refit needs explicit light parameters")
    K = len(observations)
    if K == 0:
        raise EstimationError("joint refit: no faces")
    torch.set_num_threads(max(1, cfg.threads))
    problems = problems or [FaceProblem(o, model, cfg, torch.float64) for o in observations]
    if problems[0].hybrid is not None and K > 1:
        setup = problems[0].search_setup() if cfg.sun_elevation_profile_deg else None
        for p in problems:
            p._setup = setup
    torch.set_num_threads(1)
    noise = [face_noise(o, None if pixel_rc is None else pixel_rc[i]) for i, o in enumerate(observations)]
    weights = face_weights(observations, cfg, noise)
    jp = JointProblem(problems, weights, _renumber(exposure_group if exposure_group is not None else [0] * K))
    jp.extra_prior = extra_prior
    jp.share_parts = True
    jp.albedo_group = None if albedo_group is None else _renumber(albedo_group)
    result, fit = _fit(jp, model, cfg, t_start, [o.face_id for o in observations], start=start)
    shares = [FaceShare(face_id=o.face_id, weight=fit.weights[i], albedo=fit.albedo[i], ground_albedo=fit.ground[i],
                        gain=fit.gain[i], data=fit.data[i]) for i, o in enumerate(observations)]
    return result, shares


def _fit(jp: JointProblem, model, cfg: EstimatorConfig, t_start: float, face_ids,
         start: np.ndarray | None = None) -> tuple[EstimateResult, _Fit]:
    dtype = torch.float64
    first, K = jp.first, jp.K
    if jp.hybrid is not None:  # a fit before may have dropped the exact sun core (an overcast group)
        for p in jp.faces:
            p.hybrid.core_texels = cfg.sun_core_texels
    lo, hi = model.bounds()
    rho_start = np.asarray(cfg.fixed_albedo if cfg.fixed_albedo is not None else skin_albedo_mean(), np.float64)
    t_search = time.perf_counter()
    weight_idx = None
    combined = None  # the sun search's scores over all faces: the uncertainty's evidence
    if start is not None and jp.hybrid is None:
        theta0 = _inside(np.asarray(start, np.float64).reshape(1, -1), lo, hi)
    elif jp.hybrid is not None:
        if start is not None:  # the light's own parameters, as the search's starts give them
            theta0 = _inside(np.asarray(start, np.float64).reshape(1, -1), lo, hi)
        else:
            setup = joint_faces.shared_setup(first)
            scores = [joint_faces.face_scores(p, setup, cfg) for p in jp.faces]
            combined = sun_search.combine(scores, np.asarray(jp.weights))
            found = sun_search.pick(combined, first.grid)
            theta0 = first.starts_from(found, setup[1], rho_start)
        lo, hi = lo.copy(), hi.copy()
        lo[model.sun_layout.azimuth], hi[model.sun_layout.azimuth] = -np.inf, np.inf
        weight_idx = list(model.sun_layout.sky_rgb) + list(model.sun_layout.sun_rgb)
        theta0[:, weight_idx] *= np.tile(first.apparent(rho_start), 2)
    elif first.linear:
        theta0 = _stacked_least_squares(jp, rho_start, cfg.ground_albedo_init)[None]
    else:
        theta0 = np.asarray(model.initial_points(), np.float64)
    search_s = time.perf_counter() - t_search
    box = BoxTransform(lo, hi)
    B = len(theta0)
    rho0 = np.clip(rho_start, 1e-3, 1 - 1e-3)
    g0 = np.clip(cfg.ground_albedo_init, 1e-3, 1 - 1e-3)
    x_theta = torch.tensor(box.to_unconstrained(theta0), dtype=dtype)
    tied = None if jp.albedo_group is None else torch.as_tensor(jp.albedo_group)
    n_rho = K if tied is None else int(tied.max()) + 1
    x_rho = torch.tensor(np.broadcast_to(np.log(rho0) - np.log1p(-rho0), (B, n_rho, 3)).copy(), dtype=dtype)
    log_gain0 = np.zeros(jp.num_gains)  # the search's per-face scales start the gains worse (module docstring)
    x_side = torch.tensor(np.concatenate([np.full((B, K), np.log(g0) - np.log1p(-g0)),
                                          np.broadcast_to(log_gain0, (B, jp.num_gains))], 1), dtype=dtype)
    fixed_rho = None if cfg.fixed_albedo is None else torch.as_tensor(rho0, dtype=dtype)

    def unpack(x_theta, x_side, x_rho):
        params = box.to_params(x_theta)
        rho = torch.sigmoid(x_rho) if fixed_rho is None else fixed_rho.expand(len(x_theta), K, 3)
        if tied is not None and fixed_rho is None:
            rho = rho[:, tied]
        if weight_idx is not None:  # psi = the faces' mean apparent albedo x weight
            seen = jp.first.apparent(rho).mean(1).repeat(1, 2)
            params = params.index_copy(1, torch.as_tensor(weight_idx), params[:, weight_idx] / seen)
        side = torch.cat([torch.sigmoid(x_side[:, :K]), x_side[:, K:]], 1)
        return params, rho, side

    if start is None and not first.linear and jp.hybrid is None:  # scale the model's starts to the observations
        with torch.no_grad():
            params, rho, side = unpack(x_theta, x_side, x_rho)
            ratios = []
            for i, p in enumerate(jp.faces):
                tl, _ = p.light_transport(params, side[:, i])
                pred = (p.apparent(rho[:, i])[:, None, :] * tl).mean((1, 2)).numpy()
                ratios.append(p.target_scale / np.maximum(pred, 1e-12))
        theta0 = theta0.copy()
        intensity = np.isfinite(lo) & (lo >= 0) & ~np.isfinite(hi)
        theta0[:, intensity] *= np.mean(ratios, axis=0)[:, None]
        x_theta = torch.tensor(box.to_unconstrained(theta0), dtype=dtype)

    t_fit = time.perf_counter()
    variables = (x_theta, x_side, x_rho)
    budget = cfg.max_iter + EXTRA_ITERS_PER_GAIN * jp.num_gains
    budget = max(budget, LINEAR_MIN_ITERS) if first.linear else budget
    iterations, sun_core = 0, 1.0 if jp.hybrid is not None else 0.0
    if jp.hybrid is not None and B > 1 and 0 < cfg.sun_all_starts_iters < budget:
        variables, its = run_lbfgs(jp, unpack, variables, cfg, cfg.sun_all_starts_iters)
        iterations, budget = iterations + its, budget - its
        with torch.no_grad():
            total, _ = jp.objective(*unpack(*variables))
        keep = int(np.nanargmin(total.numpy()))
        variables = tuple(v[keep : keep + 1].clone() for v in variables)
        if cfg.sun_core_min_share > 0:
            with torch.no_grad():
                share = _sun_share(model, unpack(*variables)[0][0].numpy())
            if share < cfg.sun_core_min_share:
                for p in jp.faces:
                    p.hybrid.core_texels = 0
                sun_core = 0.0
    if jp.hybrid is not None:
        variables, its = run_lbfgs(jp, unpack, variables, cfg, budget)
    else:
        variables, its = minimise(lambda *v: jp.objective(*unpack(*v)), variables, budget, cfg.tolerance,
                                  frozen=() if cfg.fixed_albedo is None else (2,))
    iterations += its
    converged = its < budget
    params, rho, side, totals, best = fitted_starts(jp, unpack, variables, "joint optimisation")
    fit_s = time.perf_counter() - t_fit
    profile_s, sun_direction, mix, profile_dirs = 0.0, None, None, None
    if jp.hybrid is not None and sun_core > 0 and cfg.sun_elevation_profile_deg:
        t_profile = time.perf_counter()
        post = elevation_posterior(jp, unpack, variables, (params, rho, side, totals, None), best, cfg, model)
        if post is not None:
            params, rho, side, totals = post.params, post.albedo, post.ground_albedo, post.totals
            best, mix, sun_direction, profile_dirs = post.best, post.weights, post.sun_direction, post.directions
        profile_s = time.perf_counter() - t_profile
    best_np = params[best].numpy().astype(np.float64)
    if sun_direction is None:
        sun_direction = model.sun_direction(best_np)
    # the sun's cones, as a single face's (f2l.estimate.uncertainty) from the combined search's
    # scores and every face's pixels; none for a refit from a given light (no search)
    uncertainty = None if combined is None or sun_direction is None else sun_uncertainty(
        sun_direction, first.grid.directions_flat[combined.texels], combined.total, combined.yy,
        getattr(jp, "normals", np.zeros((0, 3))), sun_core == 0.0, profile_dirs, mix)
    spread_kappa = None
    with torch.no_grad():
        _, _ = jp.objective(params[best : best + 1], rho[best : best + 1], side[best : best + 1])
        per_face = jp.last_data[:, 0].numpy()
        w = torch.as_tensor(jp.weights, dtype=dtype)
        chosen = [best] if mix is None else [i for i in range(len(totals)) if mix[i] >= 1e-9 * mix.max()]  # as estimate()
        rads = first.radiance(params[chosen]).clone()
        if cfg.sun_spread > 0 and uncertainty is not None and sun_core > 0:  # the sun spread, as estimate()
            radius = np.radians(cfg.sun_spread * uncertainty.cone68_deg)
            rads[:, : first.L_sky], kappas = spread_sky_radiance(model, params[chosen], radius)
            spread_kappa = float(kappas[0 if mix is None else chosen.index(best)])
        if first.sky:
            rho_g = (side[chosen][:, :K] * w).sum(1) / w.sum()  # the faces' weighted ground albedo
            e_h = (first.e_sky[None, :, None] * rads[:, : first.L_sky]).sum(1)
            rads[:, first.L_sky :] = rho_g[:, None, None] / np.pi * e_h[:, None, :]
        rads = rads.clamp_min(0.0)
        rad = rads[0] if mix is None else torch.einsum("b,blc->lc", torch.as_tensor(mix[chosen], dtype=rads.dtype), rads)
    grid = first.grid
    probe = rad.numpy().reshape(grid.height, grid.width, 3).astype(np.float32)
    if not np.isfinite(probe).all():
        raise EstimationError("joint estimate: probe is not finite")
    gains = jp.gains(side[best : best + 1])[0].numpy() if jp.num_gains else np.ones(K)
    albedo = rho[best].numpy().astype(np.float64)
    wn = np.asarray(jp.weights) / np.sum(jp.weights)
    runtime = time.perf_counter() - t_start
    result = EstimateResult(
        params=best_np, param_names=list(model.param_names), albedo=(wn[:, None] * albedo).sum(0),
        ground_albedo=float((wn * side[best, :K].numpy()).sum()) if first.sky else None,
        loss=float(totals[best]), iterations=iterations, converged=bool(converged), runtime_s=runtime,
        probe=probe, sun_direction=sun_direction,
        timings={"precompute_s": sum(p.precompute_s for p in jp.faces), "search_s": search_s, "fit_s": fit_s,
                 "profile_s": profile_s, "total_s": runtime, "sun_core": sun_core},
        start_losses=[float(v) for v in totals], num_pixels_used=int(sum(p.idx.size for p in jp.faces)),
        sun_uncertainty=uncertainty, sun_spread_kappa=spread_kappa)
    index = list(range(K))
    fit = _Fit(weights=list(jp.weights), params=best_np, albedo=dict(zip(index, albedo)),
               ground=dict(zip(index, side[best, :K].numpy().astype(float) if first.sky else [None] * K)),
               gain=dict(zip(index, gains.astype(float))), data=dict(zip(index, per_face.astype(float))), index=index)
    fit.problems = jp.faces
    return result, fit


def _inside(theta: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``theta`` moved just inside the model's finite bounds (a start on a bound has no unconstrained value)."""
    span = np.where(np.isfinite(hi - lo), hi - lo, 1.0)
    return np.clip(theta, np.where(np.isfinite(lo), lo + 1e-6 * span, -np.inf),
                   np.where(np.isfinite(hi), hi - 1e-6 * span, np.inf))


def _stacked_least_squares(jp: JointProblem, albedo: np.ndarray, ground_albedo: float) -> np.ndarray:
    """theta minimising sum_i (w_i / scale_i^2) ||rho ⊙ (A_i theta) - s_i*||^2 (small ridge), for a
    linear model (the single face's ``least_squares_start`` over the stacked faces)."""
    lhs, rhs = 0.0, 0.0
    for w, p in zip(jp.weights, jp.faces):
        A = p.TB.numpy()
        if p.sky:
            A = A + p.g.numpy()[:, None] * (ground_albedo / np.pi) * p.eB.numpy()[None, :]
        c = w / p.target_scale**2
        lhs = lhs + c * (A.T @ A)
        rhs = rhs + c * (A.T @ (p.target.numpy() / p.apparent(albedo)[None, :]))
    ridge = 1e-8 * np.trace(lhs) / lhs.shape[1]
    return np.linalg.solve(lhs + ridge * np.eye(lhs.shape[1]), rhs).reshape(-1)
