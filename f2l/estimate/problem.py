"""One face's inverse-lighting problem (paper §3.2): its precomputed pieces, forward model,
objective and starting points, shared by every lighting model (``f2l.estimate.estimator`` runs it).

Shading of face pixel p:  s_p = rho ⊙ (T l)_p,  T[p, w] = V(p, w) max(0, <n_p, w>) dOmega_w / pi;
for sun models s_p = (rho + g) ⊙ (T l)_p, the skin's gloss g an achromatic albedo (``skin_gloss``),
plus optionally the sun's highlight (``sun_specular``, f2l.estimate.specular) and the skin's
reflection of the environment (``skin_reflection``, f2l.estimate.reflection).
For ``domain == "sky"`` models the lower hemisphere is a Lambertian ground of unknown grey albedo
rho_g lit by the sky: l_gnd = rho_g / pi * E_h,  E_h = sum_{w in sky} max(0, w_y) l(w) dOmega_w, so
T l = T_sky l_sky + g (rho_g / pi) E_h with g = T_gnd 1 (row sums over the ground texels).

Objective (minimised over the model parameters theta, albedo rho in [0,1]^3, rho_g in [0,1]):
    mean_{p,c} Charbonnier(s - s*) / mean(s*)        (Charbonnier(r) = sqrt(r^2 + eps^2), eps = 1e-6)
  + w_l psi_l(theta)  (the model's prior NLL)  + w_rho psi_rho(rho)  (skin-albedo GMM NLL)
  + w_neg * mean_w dOmega relu(-l)^2 / mean(l)^2    (l >= 0, for models that can go negative)
Sun models add the clipped pixels as censored observations (``clipped_bounds``). T is held as
T @ B for linear models (``linear_basis``), in hybrid form for sun models (block-averaged sky,
exact sun core: f2l.estimate.sky_transport) and as a rank-k factor for the others.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from f2l.estimate.config import EstimatorConfig
from f2l.estimate.observation import FaceObservation, clipped_pixels, usable_pixels
from f2l.estimate.skin import albedo_prior_nll
from f2l.models.base import LightingModel
from f2l.models.capabilities import CompactSun, LinearRadiance, SunAngles
from f2l.transport import Transport

SPECULAR_LEVELS = (0.0, 1 / 16, 1 / 8, 1 / 4, 1 / 2, 1.0)  # x sun_specular_max: the k_s tried per evaluation


class FaceProblem:
    """One face's precomputed pieces (pixels, transport, targets) and its objective (module docstring)."""

    def __init__(self, obs: FaceObservation, model: LightingModel, cfg: EstimatorConfig, dtype=torch.float64):
        self.grid = obs.grid
        self.model = model
        self.cfg = cfg
        self.dtype = dtype
        t0 = time.perf_counter()
        idx = usable_pixels(obs, cfg.highlight_mad)
        if cfg.max_pixels and idx.size > cfg.max_pixels:
            idx = np.sort(np.random.default_rng(cfg.seed).choice(idx, cfg.max_pixels, replace=False))
        if isinstance(model, CompactSun) and cfg.sun_max_pixels and idx.size > cfg.sun_max_pixels:
            idx = idx[np.round(np.linspace(0, idx.size - 1, cfg.sun_max_pixels)).astype(np.int64)]
        self.idx = idx
        transport = Transport(obs.visibility_bits[idx], np.asarray(obs.normals, np.float64)[idx], self.grid)
        self.target = torch.as_tensor(np.asarray(obs.observed_rgb, np.float64)[idx], dtype=dtype)
        self.target_scale = float(self.target.mean().clamp_min(1e-12))
        grid = self.grid
        self.sky = model.domain == "sky"
        L = grid.size
        self.L_sky = grid.sky_rows * grid.width
        self.d_omega = torch.as_tensor(np.array(grid.solid_angles_flat), dtype=dtype)
        upward = np.maximum(grid.directions_flat[: self.L_sky, 1], 0.0) * grid.solid_angles_flat[: self.L_sky]
        self.e_sky = torch.as_tensor(upward, dtype=dtype)  # E_h = e_sky . l_sky
        sky_cols = np.zeros(L, dtype=bool)
        sky_cols[: self.L_sky] = True
        if self.sky and isinstance(model, CompactSun):  # ground rows summed from their bits
            ground_rows = grid.height - grid.sky_rows
            g = transport.block_sums(ground_rows, (ground_rows, 4), first_row=grid.sky_rows).sum(1)
            self.g = torch.as_tensor(g, dtype=dtype)
        elif self.sky:
            self.g = torch.as_tensor(transport.row_sums(~sky_cols), dtype=dtype)  # T_gnd 1
        basis = model.linear_basis() if isinstance(model, LinearRadiance) else None
        self.linear = basis is not None
        self.hybrid = None
        self.albedo_prior_weight = cfg.albedo_prior_weight
        self.gloss = float(cfg.skin_gloss) if self.sky and isinstance(model, CompactSun) else 0.0
        if isinstance(model, CompactSun) and cfg.sun_albedo_prior_weight is not None:
            self.albedo_prior_weight = cfg.sun_albedo_prior_weight
        self.clip_hybrid = None
        self.spec = self.clip_spec = self.refl = self.clip_refl = None
        if self.linear:
            basis = np.asarray(basis, dtype=np.float64)
            if self.sky:
                basis = np.where(sky_cols[:, None], basis, 0.0)
                self.eB = torch.as_tensor(upward @ basis[: self.L_sky], dtype=dtype)  # (K,)
            self.basis = torch.as_tensor(np.array(basis), dtype=dtype)
            # l >= 0 is checked on a 4x coarser set of directions (SH radiance is smooth there)
            step = max(1, min(grid.height, grid.width) // 16)
            rows = np.arange(step // 2, grid.height, step)
            cols = np.arange(step // 2, grid.width, step)
            sel = (rows[:, None] * grid.width + cols[None, :]).reshape(-1)
            self.neg_basis = torch.as_tensor(basis[sel], dtype=dtype)
            self.neg_weights = torch.as_tensor(grid.solid_angles_flat[sel] / grid.solid_angles_flat[sel].sum(), dtype=dtype)
            self.TB = torch.as_tensor(transport.project(basis), dtype=dtype)  # (N, K)
        elif self.sky and isinstance(model, CompactSun):
            from f2l.estimate.sky_transport import SkyTransport

            self.hybrid = SkyTransport(transport, grid, core_texels=cfg.sun_core_texels)
            self.transport = transport
            self._init_clipped(obs, cfg, dtype)
            self._init_specular(obs, cfg, dtype)
            self._init_reflection(obs, cfg, dtype)
        else:
            dense = torch.as_tensor(transport.dense(np.float32))
            if self.sky:
                dense = dense[:, : self.L_sky]
            k = min(cfg.lowrank_k, min(dense.shape) - 1)
            gen_state = torch.random.get_rng_state()
            torch.manual_seed(cfg.seed)
            U, S, V = torch.svd_lowrank(dense, q=k, niter=3)
            torch.random.set_rng_state(gen_state)
            del dense
            self.U = (U * S).to(dtype)
            self.Vt = V.T.contiguous().to(dtype)
        self.precompute_s = time.perf_counter() - t0

    def apparent(self, albedo):
        """The skin's apparent albedo, rho + g: its diffuse albedo plus the achromatic gloss
        (``EstimatorConfig.skin_gloss``; sun models only, else g = 0 and ``albedo`` itself)."""
        return albedo + self.gloss if self.gloss else albedo

    def _init_clipped(self, obs: FaceObservation, cfg: EstimatorConfig, dtype) -> None:
        """Clipped face pixels, channel by channel (``EstimatorConfig.clipped_bounds``, sun models).

        A pixel the fit left out because a channel clipped (outside the mask, brightest channel at
        least ``clipped_level``) still carries information: its clipped channels say the true value
        is at least what was recorded (a censored observation: Charbonnier(max(0, observed −
        predicted))), and its other channels are ordinary observations. Skin clips in red first,
        so the green and blue of the pixels facing the sun — the ones that place it — come back."""
        self.clip_hybrid = None
        cidx = clipped_pixels(obs, cfg.clipped_level, cfg.sun_max_pixels) if cfg.clipped_bounds else []
        if len(cidx) == 0:
            return
        rgb = np.asarray(obs.observed_rgb, np.float64)
        from f2l.estimate.sky_transport import SkyTransport

        grid = self.grid
        ct = Transport(obs.visibility_bits[cidx], np.asarray(obs.normals, np.float64)[cidx], grid)
        self.clip_hybrid = SkyTransport(ct, grid, core_texels=cfg.sun_core_texels)
        ground_rows = grid.height - grid.sky_rows
        self.clip_g = torch.as_tensor(ct.block_sums(ground_rows, (ground_rows, 4), first_row=grid.sky_rows).sum(1),
                                      dtype=dtype)
        self._clipped_idx = np.asarray(cidx)
        self.clip_target = torch.as_tensor(rgb[cidx], dtype=dtype)
        self.clip_bound = self.clip_target >= cfg.clipped_level

    def _init_specular(self, obs: FaceObservation, cfg: EstimatorConfig, dtype) -> None:
        """The sun's highlight on the fitted and the clipped pixels (``EstimatorConfig.sun_specular``)."""
        self.spec = self.clip_spec = None
        if not cfg.sun_specular or obs.points is None:
            return
        from f2l.estimate.specular import SunSpecular

        def pieces(pixels):
            return SunSpecular(np.asarray(obs.normals)[pixels], np.asarray(obs.points)[pixels],
                               np.asarray(obs.visibility_bits)[pixels], self.grid, cfg.sun_specular_roughness, dtype)

        self.spec = pieces(self.idx)
        if self.clip_hybrid is not None:
            self.clip_spec = pieces(self._clipped_idx)

    def _init_reflection(self, obs: FaceObservation, cfg: EstimatorConfig, dtype) -> None:
        """The skin's reflection of the environment on the fitted and the clipped pixels
        (``EstimatorConfig.skin_reflection``, f2l.estimate.reflection)."""
        self.refl = self.clip_refl = None
        if not cfg.skin_reflection or obs.points is None:
            return
        from f2l.estimate.reflection import SkinReflection

        # one kernel over the fitted and the clipped pixels together (their term is split after the
        # product): one set-up and one term per evaluation instead of two
        pixels = self.idx if self.clip_hybrid is None else np.concatenate([self.idx, self._clipped_idx])
        self.refl = SkinReflection(np.asarray(obs.normals)[pixels], np.asarray(obs.points)[pixels], self.grid,
                                   self.hybrid.block, cfg.skin_reflection_exponent, dtype)
        self.clip_refl = self.clip_hybrid is not None  # the clipped pixels' rows follow the fitted ones

    def reflection_terms(self, params, ground_albedo) -> tuple[torch.Tensor, torch.Tensor | None]:
        """g_r π ∫ K(r·ω) l dω on the fitted pixels (B, N, 3) and on the clipped ones (or None),
        for the light of the last :meth:`light_transport` call."""
        from f2l.estimate.reflection import sky_block_means_without_sun, sun_direction_of

        l_sky, sun, e_h, m_sky = self._sky_parts
        m = sky_block_means_without_sun(self.hybrid, l_sky, sun, m_sky)
        d = sun_direction_of(params, self.model.sun_layout)
        ground = ground_albedo[:, None] / np.pi * e_h
        term = self.cfg.skin_reflection * self.refl.term(m, d, sun[2], ground)
        n = len(self.idx)
        return (term[:, :n], term[:, n:]) if self.clip_refl else (term, None)

    def specular_term(self, spec, params, k_s) -> torch.Tensor:
        """(B, N, 3) k_s V D / (4 n·v) w_sun of the pixels of ``spec`` (f2l.estimate.specular)."""
        layout = self.model.sun_layout
        elevation = params[:, layout.elevation].clamp(0.0, 0.5 * np.pi)
        direction = spec.sun_direction(elevation, params[:, layout.azimuth])
        w_sun = params[:, list(layout.sun_rgb)].clamp_min(0.0)
        return k_s[:, None, None] * spec.shading(direction)[:, :, None] * w_sun[:, None, :]

    def clipped_term(self, parts, albedo, ground_albedo, spec=None) -> torch.Tensor:
        """Σ over clipped pixels and channels of the censored / ordinary Charbonnier terms, (B,);
        ``parts`` = (sky radiance, sun, E_h[, the sky's block means]) as :meth:`light_transport`
        keeps them; ``spec`` (B, N_clipped, 3) is the sun's highlight on those pixels (``sun_specular``)."""
        l_sky, sun, e_h = parts[:3]
        m_sky = parts[3] if len(parts) > 3 else None  # the sky's block means, where computed already
        self.clip_hybrid.core_texels = self.hybrid.core_texels
        tl = self.clip_hybrid.apply(l_sky, sun, m_sky)
        tl = tl + self.clip_g[None, :, None] * (ground_albedo[:, None, None] / np.pi) * e_h[:, None, :]
        resid = self.apparent(albedo)[:, None, :] * tl - self.clip_target[None]
        if spec is not None:
            resid = resid + spec
        resid = torch.where(self.clip_bound[None], torch.clamp(resid, max=0.0), resid)
        eps = self.cfg.charbonnier_eps
        return torch.sqrt(resid * resid + eps**2).sum((1, 2))

    # -- forward model -----------------------------------------------------------------------------
    def light_transport(self, params: torch.Tensor, ground_albedo: torch.Tensor | None, parts=None):
        """Returns (T l (B, N, 3), radiance (B, L, 3) or None when not needed). ``parts``: the
        model's ``light_parts(params)`` when already computed (faces sharing one light)."""
        if self.linear:
            coeffs = params.reshape(params.shape[0], -1, 3)
            tl = torch.einsum("nk,bkc->bnc", self.TB, coeffs)
            if self.sky:
                e_h = torch.einsum("k,bkc->bc", self.eB, coeffs)
                tl = tl + self.g[None, :, None] * (ground_albedo[:, None, None] / np.pi) * e_h[:, None, :]
            return tl, None
        if self.hybrid is not None:
            # l = w_sky ⊙ sky + w_sun ⊙ lobe on the sky rows: the transport reads its block means
            # and E_h, each the sum of the sky's (read once) and the sparse lobe's
            sky, w_sky, sun = self.model.light_parts(params) if parts is None else parts
            vals, flat, w_sun = sun
            m_unit, e_unit = self.hybrid.sky_summary(sky, self.e_sky)
            lobe_m = self.hybrid.lobe_block_means(vals, flat)
            m_sky = m_unit * w_sky[:, None, :] + lobe_m[:, :, None] * w_sun[:, None, :]  # shared below
            e_h = e_unit * w_sky + (self.e_sky[flat] * vals).sum(1)[:, None] * w_sun
            tl = self.hybrid.apply(None, sun, m_sky)
            tl = tl + self.g[None, :, None] * (ground_albedo[:, None, None] / np.pi) * e_h[:, None, :]
            self._sky_parts = (None, sun, e_h, m_sky)
            return tl, None
        rad = self.model.radiance(params)
        if self.sky:
            l_sky = rad[:, : self.L_sky]
            tl = torch.einsum("nk,bkc->bnc", self.U, torch.einsum("kl,blc->bkc", self.Vt, l_sky))
            e_h = torch.einsum("l,blc->bc", self.e_sky, l_sky)
            tl = tl + self.g[None, :, None] * (ground_albedo[:, None, None] / np.pi) * e_h[:, None, :]
        else:
            tl = torch.einsum("nk,bkc->bnc", self.U, torch.einsum("kl,blc->bkc", self.Vt, rad))
        return tl, rad

    def radiance(self, params: torch.Tensor) -> torch.Tensor:
        if self.linear:
            return torch.einsum("lk,bkc->blc", self.basis, params.reshape(params.shape[0], -1, 3))
        return self.model.radiance(params)

    def data_term(self, params, albedo, ground_albedo, parts=None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Per-start data term (B,): mean Charbonnier(s - s*) / mean(s*), plus the clipped pixels'
        censored terms; and the radiance (B, L, 3) where the forward model computed it.
        ``parts``: as :meth:`light_transport`'s."""
        cfg = self.cfg
        tl, rad = self.light_transport(params, ground_albedo, parts)
        pred = self.apparent(albedo)[:, None, :] * tl
        clip_extra = None
        if self.refl is not None:  # the skin's reflection of the environment (skin_reflection)
            refl, clip_extra = self.reflection_terms(params, ground_albedo)
            pred = pred + refl
        k_s = None
        if self.spec is not None:  # the highlight's k_s: the best of a few levels for the data term
            unit = self.specular_term(self.spec, params, torch.ones(len(params), dtype=params.dtype))
            with torch.no_grad():
                levels = torch.as_tensor(SPECULAR_LEVELS, dtype=params.dtype) * cfg.sun_specular_max
                r = pred[None] + levels[:, None, None, None] * unit[None] - self.target[None, None]
                cost = torch.sqrt(r * r + cfg.charbonnier_eps**2).mean((2, 3))  # (levels, B)
                k_s = levels[cost.argmin(0)]
            pred = pred + k_s[:, None, None] * unit
            self.last_ks = k_s.detach()
        resid = pred - self.target[None]
        data = torch.sqrt(resid * resid + cfg.charbonnier_eps**2).mean((1, 2)) / self.target_scale
        if self.clip_hybrid is not None:
            n = resid.shape[1] * resid.shape[2]
            clip_spec = None if k_s is None or self.clip_spec is None else self.specular_term(self.clip_spec, params, k_s)
            if clip_extra is not None:
                clip_spec = clip_extra if clip_spec is None else clip_spec + clip_extra
            data = data + self.clipped_term(self._sky_parts, albedo, ground_albedo, clip_spec) / (n * self.target_scale)
        return data, rad

    def light_prior(self, params) -> torch.Tensor:
        """w_l psi_l(theta), the model's prior NLL (B,)."""
        return self.cfg.light_prior_weight * self.model.prior_nll(params)

    def sun_elevation_term(self, params) -> torch.Tensor | None:
        """The capture's sun-elevation prior (``sun_elevation_prior``), (B,) or None."""
        cfg = self.cfg
        if cfg.sun_elevation_prior is None or not isinstance(self.model, SunAngles):
            return None
        el0, sigma = cfg.sun_elevation_prior
        z = (params[:, self.model.sun_angles.elevation] - el0) / sigma
        return cfg.sun_prior_weight * 0.5 * z * z

    def albedo_term(self, albedo) -> torch.Tensor | None:
        """w_rho psi_rho(rho), the skin-albedo prior (B,), or None for a fixed albedo."""
        return None if self.cfg.fixed_albedo is not None else self.albedo_prior_weight * albedo_prior_nll(albedo)

    def negativity_term(self, params, rad) -> torch.Tensor | None:
        """w_neg mean dOmega relu(-l)^2 / mean(l)^2 (B,) for models whose radiance can go
        negative (not ``sky`` models), or None."""
        cfg = self.cfg
        if not (cfg.negativity_weight > 0 and not self.sky):
            return None
        if self.linear:
            rad = torch.einsum("lk,bkc->blc", self.neg_basis, params.reshape(params.shape[0], -1, 3))
            w = self.neg_weights
        else:
            w = self.d_omega / self.d_omega.sum()
        mean_l = (rad.clamp_min(0) * w[None, :, None]).sum((1, 2)) / 3
        neg = (torch.relu(-rad) ** 2 * w[None, :, None]).sum((1, 2)) / 3
        return cfg.negativity_weight * neg / (mean_l.detach() ** 2 + 1e-12)

    def objective(self, params, albedo, ground_albedo):
        """Per-start objective (B,) and its data term (B,)."""
        data, rad = self.data_term(params, albedo, ground_albedo)
        total = data + self.light_prior(params)
        for term in (self.sun_elevation_term(params), self.albedo_term(albedo), self.negativity_term(params, rad)):
            if term is not None:
                total = total + term
        return total, data

    # -- initial points ----------------------------------------------------------------------------------
    def search_setup(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What the global sun search scores (sun_search.py), for a ``compact-sun`` model: the
        candidate sun texels (k,), the model's sky shapes (S, P), the unit-weight sky of each
        candidate and shape as block means (k, S, nb, 3) and the block means' E_h weights (nb,).
        The same for every face of one grid, model and config."""
        from f2l.estimate import sun_search
        from f2l.lighting.grid import LatLongGrid as Grid

        cfg, model, grid, layout = self.cfg, self.model, self.grid, self.model.sun_layout
        el_range = None
        if cfg.sun_elevation_prior is not None:
            el0, sigma = cfg.sun_elevation_prior
            half = max(3.0 * sigma, np.radians(4.0))
            el_range = (el0 - half, el0 + half)
        texels = sun_search.candidate_texels(grid, el_range)
        d = grid.directions_flat[texels]
        el, az = np.arcsin(np.clip(d[:, 1], -1, 1)), np.arctan2(d[:, 0], -d[:, 2])
        shapes = model.search_shapes()
        params = np.repeat(shapes[None], len(texels), axis=0)  # (k, S, P)
        params[:, :, layout.elevation] = el[:, None]
        params[:, :, layout.azimuth] = az[:, None]
        br, bc = self.hybrid.block
        coarse = type(model)(Grid(grid.height // br, grid.width // bc))
        with torch.no_grad():  # the unit-weight sky of each shape (compact-sun's ``sky``)
            sky = coarse.sky(torch.as_tensor(params.reshape(-1, params.shape[-1]))).to(torch.float64).numpy()
        k, S = params.shape[:2]
        sky_blocks = sky.reshape(k, S, -1, 3)
        e_blocks = np.bincount(self.hybrid.block_of, weights=self.e_sky.numpy(), minlength=sky_blocks.shape[2])
        return texels, shapes, sky_blocks, e_blocks

    def search_scores(self, setup, ground_albedo: float):
        """This face's scores of every candidate of ``setup`` (:meth:`search_setup`;
        ``sun_search.score``)."""
        from f2l.estimate import sun_search

        texels, _, sky_blocks, e_blocks = setup
        return sun_search.score(self.hybrid.t_blk.numpy(), self.g.numpy(), self.transport.columns,
                                self.target.numpy(), self.grid, texels, sky_blocks, e_blocks, ground_albedo)

    def starts_from(self, found, shapes: np.ndarray, albedo: np.ndarray) -> np.ndarray:
        """(S, P) starts from the search's candidates ``found`` (best first, the sun-less one
        last): the best ``sun_starts - 1`` distinct suns and the sun-less sky, weights psi / the
        albedo's apparent value."""
        from f2l.estimate import sun_search

        cfg, layout = self.cfg, self.model.sun_layout
        starts = []
        sunny = sun_search.distinct(found[:-1], max(1, cfg.sun_starts - 1))
        for c in sunny + found[-1:]:
            p = shapes[c.shape].copy()
            lum = max(float(c.psi_sky.mean()), float(c.psi_sun.mean()) * 1e-3, 1e-12)
            p[list(layout.sky_rgb)] = np.maximum(c.psi_sky / self.apparent(albedo), 1e-3 * lum)
            p[list(layout.sun_rgb)] = np.maximum(c.psi_sun / self.apparent(albedo), 1e-4 * lum)
            p[layout.elevation] = np.clip(c.elevation_rad, 0.01, 0.5 * np.pi - 0.01)
            p[layout.azimuth] = c.azimuth_rad
            if layout.kappa is not None:
                p[layout.kappa] = cfg.sun_kappa_init
            starts.append(p)
        return np.stack(starts)

    def sun_search_starts(self, albedo: np.ndarray, ground_albedo: float) -> np.ndarray:
        """(S, P) starts from the global sun search (sun_search.py) for a ``compact-sun`` model."""
        from f2l.estimate import sun_search

        setup = self.search_setup()
        found = sun_search.pick(self.search_scores(setup, ground_albedo), self.grid)
        self.search_candidates = found
        return self.starts_from(found, setup[1], albedo)

    def least_squares_start(self, albedo: np.ndarray, ground_albedo: float) -> np.ndarray:
        """theta minimising ||rho ⊙ (T B theta) - s*||^2 (small ridge), for a linear model."""
        A = self.TB.numpy()
        if self.sky:
            A = A + self.g.numpy()[:, None] * (ground_albedo / np.pi) * self.eB.numpy()[None, :]
        ridge = 1e-8 * np.trace(A.T @ A) / A.shape[1]
        lhs = A.T @ A + ridge * np.eye(A.shape[1])
        rhs = A.T @ (self.target.numpy() / self.apparent(albedo)[None, :])
        return np.linalg.solve(lhs, rhs).reshape(-1)
