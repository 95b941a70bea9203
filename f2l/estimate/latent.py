"""Face estimation for decoded latent skies (capability ``latent-sky``; called by ``f2l.estimate.estimate``).

A latent-sky model (``f2l.models.capabilities.LatentSky``, e.g. the paper's learned sky model)
gives radiance l = e^{z_0} R(phi) D(z): a code z decoded to a unit-exposure sky, rotated by the
sun's azimuth phi (a roll of columns) and scaled by the exposure. Everything model-specific comes
through the capability: ``decode_sky``, ``search_codes``, ``code_prior_nll``, ``latent_layout``.

Forward model (paper §3.2 with l = R(phi) D(z)): shading s = rho ⊙ (T_sky l + g rho_g E_h / pi),
per channel, with the sky transport in the hybrid form of ``f2l.estimate.sky_transport``:
T_sky l = T_blk m(l) + sum_{w in core} (T - T~)[:, w] l_w, m the solid-angle-weighted means of
4 x 4-texel blocks and the core the ``sun_core_texels`` sky texels of most energy Y(l) dOmega
(chosen per start and evaluation, detached): exact visibility where the sun is, block-averaged
transport for the smooth rest; E_h = sum_sky max(0, w_y) l dOmega and g = T_gnd 1.

Unknowns and parameterisation (float32 throughout; decoders are float32):
- z (D), phi (1): the sky's code and its sun's azimuth;
- psi = rho e^{z_0} (3): albedo times exposure, which is all the data term sees (the exposure-
  albedo ambiguity is then not in the data term's conditioning, as for Sun+Sky), as log psi;
- z_0 = log max(psi) + softplus(u): the albedo rho = psi e^{-z_0} <= 1, set by the priors only;
- rho_g = sigmoid(x_g), the ground albedo.
Objective: mean Charbonnier(s - s*) / mean(s*) + w_l code_prior_nll(z) + w_rho skin-NLL(rho).

Starts (all batched through the decoder, one forward/backward per evaluation):
1. coarse search: the codes of ``model.search_codes()`` (decoded once per model's
   ``cache_key`` and grid, and cached) at every
   azimuth in steps of half a block (5.6 deg on 128 columns: block means of two sub-shifts, then
   rolls of whole block columns), each scored by the mean absolute residual of its least-squares
   psi through T_blk (+ ground): one (N x nb) x (nb x 3 K A) product;
2. the best ``SEARCH_REFINE`` candidates are scored again through the full transport (exact sun
   core: cast shadows), still without the decoder (the cached skies, rolled);
3. the best ``sun_starts`` distinct ones (>= 45 deg apart in azimuth, or other codes >= 15 deg
   apart) start torch L-BFGS (strong Wolfe): all of them for ``sun_all_starts_iters``
   iterations, then the best alone for the rest of ``max_iter``.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch
import torch.nn.functional as F

from f2l.estimate.config import EstimateResult, EstimatorConfig
from f2l.estimate.lbfgs import minimise
from f2l.estimate.observation import EstimationError, FaceObservation, clipped_pixels, usable_pixels
from f2l.estimate.skin import albedo_prior_nll, skin_albedo_mean
from f2l.models.capabilities import single_thread
from f2l.estimate.sky_transport import SkyTransport
from f2l.transport import Transport

BLOCK = (4, 4)
SEARCH_REFINE = 32
SEARCH_PIXELS = 512
_SEARCH_CACHE: dict[tuple, tuple[np.ndarray, torch.Tensor]] = {}
MIN_START_SEPARATION_RAD = math.radians(45.0)


class LatentSkyProblem:
    """Per-face precomputation and the batched forward model (module docstring)."""

    def __init__(self, obs: FaceObservation, model, cfg: EstimatorConfig) -> None:
        grid = obs.grid
        self.grid, self.model, self.cfg = grid, model, cfg
        idx = usable_pixels(obs, cfg.highlight_mad)
        if cfg.max_pixels and idx.size > cfg.max_pixels:
            idx = np.sort(np.random.default_rng(cfg.seed).choice(idx, cfg.max_pixels, replace=False))
        if cfg.sun_max_pixels and idx.size > cfg.sun_max_pixels:
            idx = idx[np.round(np.linspace(0, idx.size - 1, cfg.sun_max_pixels)).astype(np.int64)]
        self.idx = idx
        transport = Transport(obs.visibility_bits[idx], np.asarray(obs.normals, np.float64)[idx], grid)
        self.rows, self.width = grid.sky_rows, grid.width
        if self.rows % BLOCK[0] or self.width % (2 * BLOCK[1]):
            raise EstimationError(f"grid {grid.height}x{grid.width}: the sky rows and columns must split into "
                                  f"{BLOCK[0]}x{BLOCK[1]} blocks for the latent-sky transport")
        self.sky = SkyTransport(transport, grid, block=BLOCK, core_texels=cfg.sun_core_texels)
        self.normals = transport.normals  # (N, 3) unit, the used pixels'
        self.t_blk = self.sky.t_blk.float()  # (N, nb)
        self.nbr, self.nbc = self.sky.shape_blocks
        ground_rows = grid.height - self.rows
        g = transport.block_sums(ground_rows, (ground_rows, 4), first_row=self.rows).sum(1)
        self.g = torch.as_tensor(g, dtype=torch.float32)  # (N,) T_gnd 1
        lu = self.rows * self.width
        self.d_omega = torch.as_tensor(np.array(grid.solid_angles[: self.rows]), dtype=torch.float32)  # (rows, W)
        self.omega_b = self.sky.omega_b.float().reshape(self.nbr, self.nbc)
        up = np.maximum(grid.directions_flat[:lu, 1], 0.0) * grid.solid_angles_flat[:lu]
        self.e_sky = torch.as_tensor(up, dtype=torch.float32)  # E_h = e_sky . l
        self.target = torch.as_tensor(np.asarray(obs.observed_rgb, np.float64)[idx].T, dtype=torch.float32)  # (3, N)
        self.target_scale = float(self.target.mean().clamp_min(1e-12))
        self.luma = torch.tensor([0.2126, 0.7152, 0.0722])
        self.clip = self._clipped(obs, cfg)

    def _clipped(self, obs: FaceObservation, cfg: EstimatorConfig) -> dict | None:
        """The clipped face pixels' transport and targets (f2l.estimate.observation.clipped_pixels):
        clipped channels are lower bounds, the others observations."""
        if not cfg.clipped_bounds:
            return None
        cidx = clipped_pixels(obs, cfg.clipped_level, cfg.sun_max_pixels)
        if cidx.size == 0:
            return None
        grid = self.grid
        ct = Transport(obs.visibility_bits[cidx], np.asarray(obs.normals, np.float64)[cidx], grid)
        sky = SkyTransport(ct, grid, block=BLOCK, core_texels=cfg.sun_core_texels)
        ground_rows = grid.height - self.rows
        target = torch.as_tensor(np.asarray(obs.observed_rgb, np.float64)[cidx].T, dtype=torch.float32)
        return {"sky": sky, "t_blk": sky.t_blk.float(), "target": target, "bound": target >= cfg.clipped_level,
                "g": torch.as_tensor(ct.block_sums(ground_rows, (ground_rows, 4), first_row=self.rows).sum(1),
                                     dtype=torch.float32)}

    def clipped_term(self, sky: torch.Tensor, psi: torch.Tensor, ground_albedo: torch.Tensor) -> torch.Tensor:
        """Σ over clipped pixels and channels of the censored / ordinary Charbonnier terms, (B,)."""
        tl = self.transport(sky, ground_albedo, self.clip)
        r = psi[:, :, None] * tl - self.clip["target"][None]
        r = torch.where(self.clip["bound"][None], torch.clamp(r, max=0.0), r)
        return torch.sqrt(r * r + self.cfg.charbonnier_eps**2).sum((1, 2))

    # -- forward -----------------------------------------------------------------------------------------
    def shape_sky(self, z_shape: torch.Tensor, azimuth: torch.Tensor | None) -> torch.Tensor:
        """(B, 3, rows, W) sky of unit exposure on the grid: R(phi) D(z) (the model's ``decode_sky``)."""
        return self.model.decode_sky(z_shape, azimuth)

    def block_means(self, sky: torch.Tensor) -> torch.Tensor:
        """(B, 3, rows, W) -> (B, 3, nbr, nbc) solid-angle-weighted block means."""
        B = sky.shape[0]
        br, bc = BLOCK
        e = (sky * self.d_omega).reshape(B, 3, self.nbr, br, self.nbc, bc).sum((3, 5))
        return e / self.omega_b

    def ground(self, sky: torch.Tensor, ground_albedo: torch.Tensor, g: torch.Tensor | None = None) -> torch.Tensor:
        """(B, 3, N) ground bounce g rho_g E_h / pi."""
        e_h = sky.flatten(2) @ self.e_sky  # (B, 3)
        return (ground_albedo / math.pi)[:, None, None] * e_h[:, :, None] * (self.g if g is None else g)

    def transport(self, sky: torch.Tensor, ground_albedo: torch.Tensor, pixels: dict | None = None) -> torch.Tensor:
        """T l (B, 3, N) of sky radiance (B, 3, rows, W): blocks + exact core + ground, for the
        fitted pixels or another set (``pixels``: its ``sky`` transport, ``t_blk`` and ``g``)."""
        sky_t, t_blk, g = (self.sky, self.t_blk, self.g) if pixels is None else \
            (pixels["sky"], pixels["t_blk"], pixels["g"])
        B = sky.shape[0]
        m = self.block_means(sky).reshape(B * 3, -1)
        tl = (m @ t_blk.T).reshape(B, 3, -1)
        k = self.sky.core_texels
        if k > 0:
            flat = sky.flatten(2)  # (B, 3, Lu)
            energy = (self.luma @ flat.detach()) * self.d_omega.reshape(-1)  # (B, Lu)
            texels = torch.topk(energy, k, dim=1).indices  # (B, k)
            resid = sky_t.cache.rows(texels.numpy()).to(torch.float32)  # (B, k, N)
            core = torch.gather(flat, 2, texels[:, None, :].expand(B, 3, k))  # (B, 3, k)
            tl = tl + torch.bmm(core, resid)
        return tl + self.ground(sky, ground_albedo, g)

    # -- search -----------------------------------------------------------------------------------------
    def candidate_skies(self) -> tuple[np.ndarray, torch.Tensor]:
        """(codes (K, D), their unit-exposure skies (K, 3, rows, W), sun at azimuth 0), cached per
        process, model ``cache_key`` and grid (they do not depend on the face)."""
        key = (self.model.cache_key, self.grid.height, self.grid.width)
        if key not in _SEARCH_CACHE:
            with torch.no_grad(), single_thread():  # cached once: the same whatever the thread count
                codes = self.model.search_codes()
                _SEARCH_CACHE[key] = (codes, self.shape_sky(torch.as_tensor(codes, dtype=torch.float32), None))
        return _SEARCH_CACHE[key]

    @staticmethod
    def _psi_score(tl: torch.Tensor, y: torch.Tensor, scale: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Least-squares psi (..., 3) of shading tl (..., 3, N) against y (3, N) and the mean
        absolute residual (...,) / scale."""
        psi = ((tl * y).sum(-1) / (tl * tl).sum(-1).clamp_min(1e-30)).clamp_min(1e-12)
        return psi, (psi[..., None] * tl - y).abs().mean((-2, -1)) / scale

    @torch.no_grad()
    def search(self, ground_albedo: float, refine: int = SEARCH_REFINE) -> list[dict]:
        """Every (code, azimuth) scored through the block transport, the best ``refine`` again
        through the full one (module docstring); best first."""
        return self.refine_search(self.coarse_scores(ground_albedo), ground_albedo, refine)

    @torch.no_grad()
    def coarse_scores(self, ground_albedo: float) -> torch.Tensor:
        """(K, A) coarse score of every search code at every azimuth (step half a block): the mean
        absolute residual / scale of its least-squares psi through T_blk (+ ground), on a pixel subset."""
        _, sky = self.candidate_skies()
        K = sky.shape[0]
        half = BLOCK[1] // 2
        shifts = torch.stack([self.block_means(sky), self.block_means(torch.roll(sky, half, dims=-1))], 1)
        # azimuth index j = 2 a + h: a shift of (a BLOCK[1] + h half) columns
        rolled = torch.stack([torch.roll(shifts, a, dims=-1) for a in range(self.nbc)], 1)  # (K, A/2, 2, 3, nbr, nbc)
        A = 2 * self.nbc
        sub = slice(None, None, max(1, self.target.shape[1] // SEARCH_PIXELS))  # coarse ranking: a pixel subset
        tl = (rolled.reshape(K * A * 3, -1) @ self.t_blk[sub].T).reshape(K, A, 3, -1)
        rho_g = torch.full((K,), ground_albedo)
        tl = tl + self.ground(sky, rho_g)[:, None, :, sub]
        return self._psi_score(tl, self.target[:, sub], self.target_scale)[1]  # (K, A)

    def rotated_candidates(self, k_idx: list[int], j_idx: list[int]) -> torch.Tensor:
        """(R, 3, rows, W) the cached search skies of codes ``k_idx`` at azimuth indices ``j_idx``."""
        _, sky = self.candidate_skies()
        half = BLOCK[1] // 2
        return torch.stack([torch.roll(sky[k], int(j) * half, dims=-1) for k, j in zip(k_idx, j_idx)])

    @torch.no_grad()
    def full_scores(self, sky: torch.Tensor, ground_albedo: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Least-squares psi (R, 3) and score (R,) of skies (R, 3, rows, W) through the full transport."""
        return self._psi_score(self.transport(sky, torch.full((sky.shape[0],), ground_albedo)),
                               self.target, self.target_scale)

    def search_azimuth(self, j: int) -> float:
        """The azimuth (radians, in [-pi, pi)) of the search's azimuth index ``j``."""
        step = 2.0 * math.pi / self.width * (BLOCK[1] // 2)
        return float(((int(j) * step + math.pi) % (2 * math.pi)) - math.pi)

    @torch.no_grad()
    def refine_search(self, score: torch.Tensor, ground_albedo: float, refine: int = SEARCH_REFINE) -> list[dict]:
        """The best ``refine`` candidates of a (K, A) coarse score scored through the full
        transport (``search``), as dicts (k, j: code and azimuth index, code, azimuth, psi, score,
        coarse_score); best first."""
        codes, _ = self.candidate_skies()
        A = score.shape[1]
        best = torch.argsort(score.reshape(-1))[:refine]
        k_idx, j_idx = best // A, best % A
        psi2, score2 = self.full_scores(self.rotated_candidates(k_idx.tolist(), j_idx.tolist()), ground_albedo)
        out = [{"k": int(k), "j": int(j), "code": codes[int(k)], "azimuth": self.search_azimuth(j),
                "psi": psi2[i].numpy().astype(np.float64), "score": float(score2[i]), "coarse_score": float(score[k, j])}
               for i, (k, j) in enumerate(zip(k_idx.tolist(), j_idx.tolist()))]
        return sorted(out, key=lambda c: c["score"])

    def data_term(self, sky: torch.Tensor, psi: torch.Tensor, ground_albedo: torch.Tensor) -> torch.Tensor:
        """(B,) mean Charbonnier(psi ⊙ T l - s*) / mean(s*) of skies (B, 3, rows, W), psi (B, 3)
        and ground albedos (B,), plus the clipped pixels' term (``clipped_term``) on the same scale."""
        tl = self.transport(sky, ground_albedo)
        r = psi[:, :, None] * tl - self.target[None]
        data = torch.sqrt(r * r + self.cfg.charbonnier_eps**2).mean((1, 2)) / self.target_scale
        if self.clip is not None:
            data = data + self.clipped_term(sky, psi, ground_albedo) / (r.shape[1] * r.shape[2] * self.target_scale)
        return data


def pick_starts(candidates: list[dict], n: int) -> list[dict]:
    """The best candidate, then the best ones >= 45 deg in azimuth from all picked (or of
    another centroid and >= 15 deg away), up to ``n``."""
    picked: list[dict] = []
    for c in candidates:
        if len(picked) >= n:
            break
        ok = True
        for p in picked:
            d = abs((c["azimuth"] - p["azimuth"] + math.pi) % (2 * math.pi) - math.pi)
            if d < MIN_START_SEPARATION_RAD and not (c["k"] != p["k"] and d >= MIN_START_SEPARATION_RAD / 3):
                ok = False
                break
        if ok:
            picked.append(c)
    return picked


def estimate_latent_sky(obs: FaceObservation, model, cfg: EstimatorConfig | None = None) -> EstimateResult:
    """Estimate a face's lighting with a ``latent-sky`` model (module docstring)."""
    cfg = cfg or EstimatorConfig()
    t_start = time.perf_counter()
    torch.set_num_threads(max(1, cfg.threads))
    prob = LatentSkyProblem(obs, model, cfg)
    precompute_s = time.perf_counter() - t_start

    t_search = time.perf_counter()  # one (K A 3 x 256) . (256 x N) product: all threads
    rho_skin = np.asarray(cfg.fixed_albedo if cfg.fixed_albedo is not None else skin_albedo_mean(), dtype=np.float64)
    coarse = prob.coarse_scores(cfg.ground_albedo_init)
    candidates = prob.refine_search(coarse, cfg.ground_albedo_init)
    starts = pick_starts(candidates, max(1, cfg.sun_starts))
    search_s = time.perf_counter() - t_search
    torch.set_num_threads(1)  # small batched tensors: one intra-op thread (f2l.estimate.estimator)

    z0 = torch.tensor(np.stack([c["code"] for c in starts]), dtype=torch.float32)
    phi0 = torch.tensor([c["azimuth"] for c in starts], dtype=torch.float32)
    psi0 = np.stack([np.maximum(c["psi"], 1e-6 * max(c["psi"].max(), 1e-12)) for c in starts])
    logpsi0 = torch.tensor(np.log(psi0), dtype=torch.float32)
    # rho = psi / max(psi) * exp(-softplus(u)): start at the skin albedo's brightest channel
    sp = max(-math.log(float(np.clip(rho_skin.max(), 1e-3, 1 - 1e-3))), 1e-3)
    u0 = torch.full((len(starts),), math.log(math.expm1(sp)), dtype=torch.float32)
    g = float(np.clip(cfg.ground_albedo_init, 1e-3, 1 - 1e-3))
    xg0 = torch.full((len(starts),), math.log(g / (1 - g)), dtype=torch.float32)
    fixed = None if cfg.fixed_albedo is None else torch.as_tensor(rho_skin, dtype=torch.float32)

    def unpack(zs, phi, logpsi, u, xg):
        psi = torch.exp(logpsi)
        if fixed is None:
            log_exposure = logpsi.max(1).values + F.softplus(u)
            rho = torch.exp(logpsi - log_exposure[:, None])
        else:
            rho = fixed.expand(len(zs), 3)
            log_exposure = (logpsi - torch.log(fixed)).mean(1)
        return psi, rho, log_exposure, torch.sigmoid(xg)

    def objective(zs, phi, logpsi, u, xg):
        psi, rho, _, rho_g = unpack(zs, phi, logpsi, u, xg)
        data = prob.data_term(prob.shape_sky(zs, phi), psi, rho_g)
        total = data + cfg.light_prior_weight * model.code_prior_nll(zs)
        if fixed is None:
            total = total + cfg.albedo_prior_weight * albedo_prior_nll(rho)
        return total, data

    t_fit = time.perf_counter()
    variables, iterations, converged, total = fit_starts(objective, (z0, phi0, logpsi0, u0, xg0), cfg,
                                                         fixed is not None)
    fit_s = time.perf_counter() - t_fit
    zs, phi, logpsi, u, xg = variables
    with torch.no_grad():
        _, rho, log_exposure, rho_g = unpack(*variables)
    params = latent_params(model, float(log_exposure[0]), zs[0], phi[0])
    probe = _probe_with_ground(model, params, float(rho_g[0]))
    if not np.isfinite(probe).all():
        raise EstimationError("estimated probe is not finite")
    sun_direction = model.sun_direction(params)
    t_uncertainty = time.perf_counter()
    normals = np.asarray(obs.normals)[np.asarray(obs.mask, bool)]
    uncertainty = latent_sun_uncertainty(prob, coarse, sun_direction, normals)
    uncertainty_s = time.perf_counter() - t_uncertainty
    runtime = time.perf_counter() - t_start
    return EstimateResult(
        params=params, param_names=list(model.param_names), albedo=rho[0].double().numpy(),
        ground_albedo=float(rho_g[0]), loss=float(total[0]), iterations=iterations, converged=converged,
        runtime_s=runtime, probe=probe, sun_direction=sun_direction,
        timings={"precompute_s": precompute_s, "search_s": search_s, "fit_s": fit_s, "uncertainty_s": uncertainty_s,
                 "total_s": runtime, "starts": float(len(starts))},
        start_losses=[c["score"] for c in starts], num_pixels_used=int(prob.idx.size), sun_uncertainty=uncertainty,
    )


def candidate_sun_directions(prob: LatentSkyProblem, shape: tuple[int, int]) -> np.ndarray:
    """(K A, 3) the sun of each (code, azimuth) candidate of the coarse search (``shape`` = (K, A),
    row-major as :meth:`LatentSkyProblem.coarse_scores`): the brightest sky texel (Rec.709
    luminance) of the code's cached sky, its column turned with the candidate's azimuth roll."""
    key = ("suns", prob.model.cache_key, prob.grid.height, prob.grid.width)
    if key not in _SEARCH_CACHE:
        _, sky = prob.candidate_skies()
        lum = torch.einsum("c,kcrw->krw", torch.tensor([0.2126, 0.7152, 0.0722], dtype=sky.dtype), sky)
        flat = lum.reshape(lum.shape[0], -1).argmax(1).numpy()
        _SEARCH_CACHE[key] = (flat // prob.width, flat % prob.width)
    rows, cols = _SEARCH_CACHE[key]
    K, A = shape
    half = BLOCK[1] // 2
    col = (cols[:, None] + half * np.arange(A)[None, :]) % prob.width  # (K, A): torch.roll by j half-blocks
    texel = (np.repeat(rows[:, None], A, 1) * prob.grid.width + col).reshape(-1)
    return np.asarray(prob.grid.directions_flat, np.float64)[texel]


def latent_sun_uncertainty(prob: LatentSkyProblem, coarse: torch.Tensor, sun_direction, normals: np.ndarray):
    """The sun's cones of a latent-sky estimate (f2l.estimate.uncertainty): the posterior over the
    coarse search's candidates, each scored by its squared relative L1 residual (the search's
    score, squared to stand where a squared residual stands), calibrated by the latent-sky
    constants (``LATENT_CONE_COEFFICIENTS``; no overcast judgement: that feature is 0). None
    without a sun direction or a finite score."""
    from f2l.estimate import uncertainty as unc

    score = coarse.double().numpy()
    if sun_direction is None or not np.isfinite(score).any():
        return None
    dirs = candidate_sun_directions(prob, score.shape)
    return unc.sun_uncertainty(np.asarray(sun_direction, np.float64), dirs, (score * score).reshape(-1, 1), 1.0,
                               normals, False, cone_coefficients=unc.LATENT_CONE_COEFFICIENTS,
                               cone_quantiles=unc.LATENT_CONE_QUANTILES, mae_coefficients=unc.LATENT_MAE_COEFFICIENTS)


def fit_starts(objective, variables, cfg: EstimatorConfig, fixed_albedo: bool) -> tuple[tuple, int, bool, torch.Tensor]:
    """L-BFGS (``_lbfgs``) on every start (leading dimension of ``variables``) for
    ``sun_all_starts_iters`` iterations, then on the best alone for the rest of ``max_iter``:
    the optimised leaves, the iterations taken, whether the last run stopped before its budget and
    the final objective (1,). Raises EstimationError if that is not finite."""
    budget, iterations = max(1, cfg.max_iter), 0
    if len(variables[0]) > 1 and 0 < cfg.sun_all_starts_iters < budget:
        variables, its = _lbfgs(objective, variables, cfg, cfg.sun_all_starts_iters, fixed_albedo)
        iterations += its
        budget -= its
        with torch.no_grad():
            total, _ = objective(*variables)
        keep = int(np.nanargmin(total.numpy()))
        variables = tuple(v[keep : keep + 1].clone() for v in variables)
    variables, its = _lbfgs(objective, variables, cfg, budget, fixed_albedo)
    with torch.no_grad():
        total, _ = objective(*variables)
    if not torch.isfinite(total).all():
        raise EstimationError("optimisation diverged: objective is not finite")
    return variables, iterations + its, its < budget, total


def latent_params(model, log_exposure: float, code: torch.Tensor, azimuth: torch.Tensor) -> np.ndarray:
    """The model's parameter vector (float64) of an exposure, a code (D,) and an azimuth (wrapped to [-pi, pi))."""
    layout = model.latent_layout
    params = np.zeros(model.num_params, dtype=np.float64)
    params[layout.exposure] = log_exposure
    params[layout.code] = code.double().numpy()
    params[layout.azimuth] = float(((azimuth + math.pi) % (2 * math.pi)) - math.pi)
    return params


def _probe_with_ground(model, params: np.ndarray, ground_albedo: float) -> np.ndarray:
    """(H, W, 3) float32 probe of ``params`` with the Lambertian ground bounce below the horizon."""
    grid = model.grid
    probe = model.probe(params).astype(np.float64)
    rows = grid.sky_rows
    up = np.maximum(grid.directions[:rows, :, 1], 0.0) * grid.solid_angles[:rows]
    e_h = np.einsum("hwc,hw->c", probe[:rows], up)
    probe[rows:] = ground_albedo / math.pi * e_h
    return np.maximum(probe, 0.0).astype(np.float32)


def _lbfgs(objective, variables, cfg: EstimatorConfig, max_iter: int, fixed_albedo: bool):
    """:func:`f2l.estimate.lbfgs.minimise` with a change tolerance of ``cfg.tolerance`` x 1e-2 of
    the starting data term; a fixed albedo (leaf 3) is not trained."""
    with torch.no_grad():
        start = float(objective(*variables)[1].sum())
    return minimise(objective, variables, max_iter, cfg.tolerance * 1e-2 * start, tolerance_grad=1e-9,
                    frozen=(3,) if fixed_albedo else ())
