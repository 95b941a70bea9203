"""One light for several faces with a latent-sky model (capability ``latent-sky``; called by
``f2l.estimate.joint.estimate_joint`` for groups of more than one face).

The method of f2l.estimate.latent over F faces: one :class:`LatentSkyProblem` per face (float32),
a shared code z and sun azimuth phi (one decoded sky per start and evaluation), and per face its
own psi_i = rho_i e^{z_0,e(i)} (3, as log psi: albedo x exposure, all its data term sees) and
ground albedo rho_g,i = sigmoid(x_g,i). The faces of one exposure group e (one photo) share the
exposure z_0,e = max over the group's faces of log max(psi_i) + softplus(u_e), so every rho_i =
psi_i e^{-z_0,e} <= 1 and is set by the albedo prior alone, as for one face. Objective:

    sum_i w_i [D_i(z, phi, psi_i, rho_g,i) + w_rho skin-NLL(rho_i)] + w_l code_prior_nll(z),

D_i face i's data term (``LatentSkyProblem.data_term``), w_i from ``joint_common.face_weights``
(summing to the number of faces), the code prior once. A fixed albedo (``cfg.fixed_albedo``)
freezes u; the group's exposure is then its faces' mean log(psi_i / rho).

Starts: every (code, azimuth) of the search is scored by sum_i w_i c_i, c_i face i's coarse score
(its relative residual with its own least-squares psi, ``LatentSkyProblem.coarse_scores``); the
best ``SEARCH_REFINE`` are scored again through each face's full transport (summed the same way),
and the best ``sun_starts`` distinct ones (``latent.pick_starts``) start L-BFGS, with each face's
own best light of its own search (``refine_search``) where distinct from them: a light that is
merely passable for every face can out-score, in the search's metric, one that is right for most
(the clipped pixels, in the objective only, tell them apart). As for one face: all starts for
``sun_all_starts_iters`` iterations, then the best alone for the rest of ``max_iter``.

Faces that disagree (in another's shadow, under a hat) are left out, as f2l.estimate.joint does,
in the search's metric (full transport, least-squares psi, ground albedo ``ground_albedo_init``):
a face's ``agreement`` with a light is its score under that light over its score under the best
light of its own search. Before the fit, each face's own best light is tried on every face; the
light most faces stay within ``disagree_ratio`` of wins (ties: the lower mean ratio) and the faces
beyond it are left out. After each fit, while the worst used face's agreement with the fitted
light exceeds ``disagree_ratio``, it is left out and the rest fitted afresh. A group left with one
face is that face's :func:`f2l.estimate.estimator.estimate`, bit for bit. Agreements are measured
(and reported) with ``disagree_ratio`` None too; then no face is left out.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch
import torch.nn.functional as F

from f2l.estimate.config import EstimateResult, EstimatorConfig
from f2l.estimate.estimator import estimate
from f2l.estimate import joint_common
from f2l.estimate.joint_common import DARK_RATIO, DISAGREE_RATIO, FaceShare, JointResult, darkness, face_noise, face_weights
from f2l.estimate.latent import (SEARCH_REFINE, LatentSkyProblem, _probe_with_ground, fit_starts, latent_params,
                                 latent_sun_uncertainty, pick_starts)
from f2l.estimate.observation import EstimationError, FaceObservation
from f2l.estimate.skin import albedo_prior_nll, skin_albedo_mean


def estimate_joint_latent(observations: list[FaceObservation], model, cfg: EstimatorConfig | None = None,
                          exposure_group: list | None = None, pixel_rc: list | None = None,
                          disagree_ratio: float | None = DISAGREE_RATIO) -> JointResult:
    """One light for ``observations`` with a latent-sky model (module docstring). Arguments as
    :func:`f2l.estimate.joint.estimate_joint`. Raises EstimationError when no face can be used."""
    t_start = time.perf_counter()
    cfg = cfg or EstimatorConfig()
    n = len(observations)
    if n == 0:
        raise EstimationError("joint estimate: no faces")
    groups = _exposure_indices(exposure_group if exposure_group is not None else [0] * n)
    noise = [face_noise(o, None if pixel_rc is None else pixel_rc[i]) for i, o in enumerate(observations)]
    shares = [FaceShare(face_id=o.face_id, weight=0.0) for o in observations]
    problems: dict[int, LatentSkyProblem] = {}
    torch.set_num_threads(max(1, cfg.threads))
    for i, o in enumerate(observations):
        if n == 1:
            break
        try:
            problems[i] = LatentSkyProblem(o, model, cfg)
        except EstimationError as exc:
            shares[i].used, shares[i].reason = False, f"bad_face: {exc}"
    precompute_s = time.perf_counter() - t_start
    active = [0] if n == 1 else sorted(problems)
    if not active:
        raise EstimationError("joint estimate: no usable face (" + "; ".join(s.reason for s in shares) + ")")
    t_search = time.perf_counter()
    g0 = cfg.ground_albedo_init
    coarse = {i: p.coarse_scores(g0) for i, p in problems.items()} if len(active) > 1 else {}
    own = {i: problems[i].refine_search(c, g0) for i, c in coarse.items()}
    lights = _own_lights(problems, own, g0) if own else {}
    search_s = time.perf_counter() - t_search
    agreement: dict[int, float] = {}
    if disagree_ratio is not None and len(active) > 2:  # a pair has no majority
        support = _consensus(lights, own, active, disagree_ratio)
        if support is not None:  # two faces or more agree on one light
            agreement.update(support)
            for i in active:
                if support[i] > disagree_ratio:
                    _leave_out(shares[i], support[i], disagree_ratio, " under the light most faces agree with")
            active = [i for i in active if support[i] <= disagree_ratio]
    while True:
        if len(active) == 1:
            result, fit = estimate(observations[active[0]], model, cfg), None
            break
        weights = face_weights([observations[i] for i in active], cfg, [noise[i] for i in active])
        result, fit = _fit([problems[i] for i in active], weights, _exposure_indices(groups[active]),
                           [coarse[i] for i in active], [lights[i] for i in active], active, model, cfg)
        result.timings["search_s"] += search_s
        sky = problems[active[0]].shape_sky(torch.as_tensor(fit["code"][None], dtype=torch.float32),
                                            torch.tensor([fit["azimuth"]], dtype=torch.float32)).detach()
        agreement.update({i: _ratio(problems[i], sky, own[i], g0) for i in problems})
        if disagree_ratio is None:
            break
        shade = darkness({i: fit["albedo"][j] for j, i in enumerate(active)}, {i: int(groups[i]) for i in active})
        worst = max(active, key=lambda i: agreement[i])
        if agreement[worst] > disagree_ratio:
            if len(active) == 2:  # no majority: each face keeps its own light (the darker one leaves)
                a, b = active
                if abs(shade[a] - shade[b]) > 1e-9:
                    worst = min(active, key=lambda i: shade[i])
                else:  # no photo-mates to compare with (one face a photo): the one that sees its sun less
                    worst = min(active, key=lambda i: _own_sun_lit(problems[i], lights[i]))
                shares[worst].used = False
                shares[worst].reason = (f"the group's two faces disagree (residual {max(agreement[a], agreement[b]):.2f}x "
                                        f"its own best, limit {disagree_ratio:.2f}): each keeps its own estimate")
            else:
                _leave_out(shares[worst], agreement[worst], disagree_ratio, "")
        else:
            worst = min(active, key=lambda i: shade[i])
            if shade[worst] >= DARK_RATIO:
                break
            shares[worst].used = False
            shares[worst].reason = (f"too dark for the group's light: its albedo is {shade[worst]:.2f}x its "
                                    f"photo's other faces' median (limit {DARK_RATIO:.2f}), as a face in shade is; left out")
        active = [i for i in active if i != worst]
    for i, s in enumerate(shares):
        s.agreement = agreement.get(i)
    if fit is None:  # one face left: its own estimate
        s = shares[active[0]]
        s.weight, s.albedo, s.ground_albedo = 1.0, result.albedo, result.ground_albedo
    else:
        for j, i in enumerate(active):
            s = shares[i]
            s.weight, s.albedo, s.ground_albedo = float(fit["weights"][j]), fit["albedo"][j], float(fit["ground"][j])
            s.gain, s.data = float(fit["gain"][j]), float(fit["data"][j])
        result.timings["precompute_s"] = precompute_s
        # the sun's cones, as a single face's, from the search's scores summed over the faces as the
        # joint starts weigh them, and every face's pixels
        combined = sum(float(w) * coarse[i] for w, i in zip(fit["weights"], active))
        normals = np.concatenate([np.asarray(observations[i].normals)[np.asarray(observations[i].mask, bool)]
                                  for i in active])
        result.sun_uncertainty = latent_sun_uncertainty(problems[active[0]], combined, result.sun_direction, normals)
    result.runtime_s = time.perf_counter() - t_start
    result.timings.update(total_s=result.runtime_s, faces=float(len(active)))
    return JointResult(result, shares)


def _leave_out(share: FaceShare, ratio: float, limit: float, where: str) -> None:
    """Mark a face as left out for disagreeing (``ratio`` its agreement; the reason joint.py gives)."""
    share.used = False
    share.reason = f"disagrees with the group's light: residual {ratio:.2f}x its own best{where} (limit {limit:.2f}); left out"


def _exposure_indices(groups) -> np.ndarray:
    """Exposure groups as 0, 1, ... in order of first appearance (the first face's group is 0)."""
    _, first, inverse = np.unique(np.asarray(groups), return_index=True, return_inverse=True)
    rank = np.empty(len(first), np.int64)
    rank[np.argsort(first)] = np.arange(len(first))
    return rank[inverse.reshape(-1)]


def _ratio(p: LatentSkyProblem, sky: torch.Tensor, own: list[dict], ground_albedo: float) -> float:
    """The face's score under the sky (1, 3, rows, W) over its score under its own search's best."""
    return float(p.full_scores(sky, ground_albedo)[1][0]) / max(own[0]["score"], 1e-12)


def _own_sun_lit(p: LatentSkyProblem, light: dict) -> float:
    """The share of the face's pixels facing the sun (the brightest texel) of its own best light
    (as :func:`f2l.estimate.joint_faces.own_sun_lit` for compact-sun models)."""
    from f2l.estimate.uncertainty import lit_fraction

    sky = p.rotated_candidates([light["k"]], [light["j"]])[0]  # (3, rows, W)
    texel = int(torch.einsum("c,crw->rw", p.luma.to(sky.dtype), sky).reshape(-1).argmax())
    return lit_fraction(p.normals, p.grid.directions_flat[texel])


def _own_lights(problems: dict[int, LatentSkyProblem], own: dict[int, list[dict]], ground_albedo: float) -> dict[int, dict]:
    """Each face's own best light of its search (k, j, code, azimuth) with every face's
    least-squares psi (3,) and score under it ("psi", "score": dicts by face)."""
    faces = sorted(own)
    skies = problems[faces[0]].rotated_candidates([own[i][0]["k"] for i in faces], [own[i][0]["j"] for i in faces])
    fits = {j: problems[j].full_scores(skies, ground_albedo) for j in faces}  # psi (L, 3), score (L,)
    return {i: {**{key: own[i][0][key] for key in ("k", "j", "code", "azimuth")},
                "psi": {j: fits[j][0][a].numpy().astype(np.float64) for j in faces},
                "score": {j: float(fits[j][1][a]) for j in faces}} for a, i in enumerate(faces)}


def _consensus(lights: dict[int, dict], own: dict[int, list[dict]], active: list[int],
               limit: float) -> dict[int, float] | None:
    """Each face's agreement with the light most faces agree with, among the faces' own best
    lights of the search (module docstring); None when no light suits two faces
    (``joint_common.CONSENSUS_MIN_VOTES``, as f2l.estimate.joint_faces.consensus)."""
    def ratio(a: int, j: int) -> float:
        return lights[a]["score"][j] / max(own[j][0]["score"], 1e-12)

    votes = {a: sum(ratio(a, j) <= limit for j in active) for a in active}
    best = min(active, key=lambda a: (-votes[a], float(np.mean([ratio(a, j) for j in active]))))
    return {j: ratio(best, j) for j in active} if votes[best] >= joint_common.CONSENSUS_MIN_VOTES else None


def _joint_starts(probs: list[LatentSkyProblem], weights: np.ndarray, coarse: list[torch.Tensor], lights: list[dict],
                  faces: list[int], cfg: EstimatorConfig) -> list[dict]:
    """The search's candidates scored over all faces, the best ``sun_starts`` distinct ones, then
    the faces' own best lights (``lights``, of faces ``faces``) distinct from those (module
    docstring), as ``pick_starts`` reads them; "psi" (F, 3) holds each face's least-squares psi."""
    total = sum(float(w) * c for w, c in zip(weights, coarse))  # (K, A)
    A = total.shape[1]
    best = torch.argsort(total.reshape(-1))[:SEARCH_REFINE]
    k_idx, j_idx = (best // A).tolist(), (best % A).tolist()
    skies = probs[0].rotated_candidates(k_idx, j_idx)
    fitted = [p.full_scores(skies, cfg.ground_albedo_init) for p in probs]
    psi = torch.stack([f[0] for f in fitted], 1).numpy().astype(np.float64)  # (R, F, 3)
    score = sum(float(w) * f[1] for w, f in zip(weights, fitted)).numpy()
    codes, _ = probs[0].candidate_skies()
    out = [{"k": k, "j": j, "code": codes[k], "azimuth": probs[0].search_azimuth(j), "psi": psi[r],
            "score": float(score[r])} for r, (k, j) in enumerate(zip(k_idx, j_idx))]
    picked = pick_starts(sorted(out, key=lambda c: c["score"]), max(1, cfg.sun_starts))
    extra = [{**{key: light[key] for key in ("k", "j", "code", "azimuth")},
              "psi": np.stack([light["psi"][i] for i in faces]),
              "score": float(sum(float(w) * light["score"][i] for w, i in zip(weights, faces)))} for light in lights]
    return pick_starts(picked + sorted(extra, key=lambda c: c["score"]), len(picked) + len(extra))


def _fit(probs: list[LatentSkyProblem], weights: np.ndarray, groups: np.ndarray, coarse: list[torch.Tensor],
         lights: list[dict], faces: list[int], model, cfg: EstimatorConfig) -> tuple[EstimateResult, dict]:
    """The joint fit of F >= 2 faces (module docstring): the group's result and the faces' parts."""
    t_start = time.perf_counter()
    torch.set_num_threads(max(1, cfg.threads))
    starts = _joint_starts(probs, weights, coarse, lights, faces, cfg)
    search_s = time.perf_counter() - t_start
    torch.set_num_threads(1)  # small batched tensors: one intra-op thread (f2l.estimate.estimator)
    nf, E, B = len(probs), int(groups.max()) + 1, len(starts)
    members = [torch.as_tensor(np.flatnonzero(groups == e)) for e in range(E)]
    face_group = torch.as_tensor(groups)
    w = [float(x) for x in weights]
    rho_skin = np.asarray(cfg.fixed_albedo if cfg.fixed_albedo is not None else skin_albedo_mean(), dtype=np.float64)
    z0 = torch.tensor(np.stack([c["code"] for c in starts]), dtype=torch.float32)
    phi0 = torch.tensor([c["azimuth"] for c in starts], dtype=torch.float32)
    psi0 = np.stack([np.maximum(c["psi"], 1e-6 * np.maximum(c["psi"].max(1, keepdims=True), 1e-12)) for c in starts])
    logpsi0 = torch.tensor(np.log(psi0), dtype=torch.float32)  # (B, F, 3)
    sp = max(-math.log(float(np.clip(rho_skin.max(), 1e-3, 1 - 1e-3))), 1e-3)
    u0 = torch.full((B, E), math.log(math.expm1(sp)), dtype=torch.float32)
    g = float(np.clip(cfg.ground_albedo_init, 1e-3, 1 - 1e-3))
    xg0 = torch.full((B, nf), math.log(g / (1 - g)), dtype=torch.float32)
    fixed = None if cfg.fixed_albedo is None else torch.as_tensor(rho_skin, dtype=torch.float32)

    def unpack(zs, phi, logpsi, u, xg):
        """psi (B, F, 3), rho (B, F, 3), log exposure per group (B, E), ground albedo (B, F)."""
        if fixed is None:
            top = logpsi.max(2).values  # (B, F)
            log_exposure = torch.stack([top[:, m].max(1).values for m in members], 1) + F.softplus(u)
            rho = torch.exp(logpsi - log_exposure[:, face_group, None])
        else:
            rho = fixed.expand(len(zs), nf, 3)
            per_face = (logpsi - torch.log(fixed)).mean(2)
            log_exposure = torch.stack([per_face[:, m].mean(1) for m in members], 1)
        return torch.exp(logpsi), rho, log_exposure, torch.sigmoid(xg)

    def faces_data(zs, phi, psi, rho_g):
        sky = probs[0].shape_sky(zs, phi)
        return torch.stack([p.data_term(sky, psi[:, i], rho_g[:, i]) for i, p in enumerate(probs)], 1)  # (B, F)

    def objective(zs, phi, logpsi, u, xg):
        psi, rho, _, rho_g = unpack(zs, phi, logpsi, u, xg)
        per_face = faces_data(zs, phi, psi, rho_g)
        data = sum(w[i] * per_face[:, i] for i in range(nf))
        total = data + cfg.light_prior_weight * model.code_prior_nll(zs)
        if fixed is None:
            total = total + sum(w[i] * cfg.albedo_prior_weight * albedo_prior_nll(rho[:, i]) for i in range(nf))
        return total, data

    t_fit = time.perf_counter()
    variables, iterations, converged, total = fit_starts(objective, (z0, phi0, logpsi0, u0, xg0), cfg,
                                                         fixed is not None)
    fit_s = time.perf_counter() - t_fit
    zs, phi = variables[:2]
    with torch.no_grad():
        psi, rho, log_exposure, rho_g = unpack(*variables)
        per_face = faces_data(zs, phi, psi, rho_g)[0].double().numpy()
    wn = np.asarray(w) / np.sum(w)
    albedo, ground = rho[0].double().numpy(), rho_g[0].double().numpy()
    params = latent_params(model, float(log_exposure[0, 0]), zs[0], phi[0])
    probe = _probe_with_ground(model, params, float((wn * ground).sum()))
    if not np.isfinite(probe).all():
        raise EstimationError("joint estimate: probe is not finite")
    runtime = time.perf_counter() - t_start
    result = EstimateResult(
        params=params, param_names=list(model.param_names), albedo=(wn[:, None] * albedo).sum(0),
        ground_albedo=float((wn * ground).sum()), loss=float(total[0]), iterations=iterations, converged=converged,
        runtime_s=runtime, probe=probe, sun_direction=model.sun_direction(params),
        timings={"precompute_s": 0.0, "search_s": search_s, "fit_s": fit_s, "total_s": runtime,
                 "starts": float(len(starts))},
        start_losses=[c["score"] for c in starts], num_pixels_used=int(sum(p.idx.size for p in probs)))
    gain = np.exp(log_exposure[0].double().numpy() - float(log_exposure[0, 0]))[groups]
    fit = {"weights": w, "albedo": list(albedo), "ground": ground, "gain": gain, "data": per_face,
           "code": zs[0].numpy(), "azimuth": float(phi[0])}
    return result, fit
