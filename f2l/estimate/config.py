"""The estimator's settings and result (shared by every estimation path in ``f2l.estimate``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class EstimatorConfig:
    charbonnier_eps: float = 1e-6
    light_prior_weight: float = 1e-3
    albedo_prior_weight: float = 1e-3
    # compact-sun models: the skin-albedo prior's weight (None: albedo_prior_weight). The skin prior
    # (ColorChecker skin) decides the light's colour, which a face cannot tell from the skin's; at
    # 1e-3 it overrules the sky prior's colours and the light comes out too blue on `make eval-real`
    # (median R/G 0.82 of the truth's). Chosen on its tuning part from 1e-3, 3e-4, 1e-4, 3e-5
    # (MAE (s) 0.222, 0.211, 0.204, 0.215); reporting part MAE (s) 0.224 -> 0.211, R/G 0.82 -> 0.93.
    # docs/experiments/accuracy_issue16.md "What each change bought". The latent-sky model keeps 1e-3 (its MAE (s) rose at 1e-4).
    sun_albedo_prior_weight: float | None = 1e-4
    negativity_weight: float = 1.0
    max_iter: int = 18
    tolerance: float = 1e-4
    max_pixels: int | None = None  # subsample usable pixels (deterministic) for speed
    lowrank_k: int = 96
    threads: int = 2
    seed: int = 0
    fixed_albedo: tuple[float, float, float] | None = None
    ground_albedo_init: float = 0.2
    albedo_starts: int = 2  # least-squares starts at this many albedo-GMM component means
    # IRLS iterations for linear models, before and after the albedo split: caps; each round stops
    # once its estimated distance to the fixed point is below `irls_tolerance` (relative, see
    # linear.solve_psi). On the 12 demo faces 20 of 24 SH fits stop by that rule (40-154
    # iterations), the rest at the caps; (40, 12) stopped 5e-6 to 3.5e-2 (of max|theta|) short of
    # the fixed point, the former (18, 6) further still. §5.1 metrics move by <= 0.3% between them.
    irls_iters: tuple[int, int] = (150, 50)
    irls_tolerance: float = 1e-6
    # the first `irls_warm_iters` of the first round run on every `irls_warm_stride`-th pixel:
    # that half-size problem's optimum is a start that 4 full iterations polish (psi within
    # 2.8e-3 of the optimum, as close as 20 full iterations, in 11/20 of the time)
    irls_warm_iters: int = 14
    irls_warm_stride: int = 2
    # IRLS weights 1 / (2 max(C(r), floor * scale)): the Charbonnier term (eps = 1e-6) is |r|-like,
    # and with a tiny floor the pixels that fit almost exactly get weights so large that float32
    # rounding moves the solution (0.5% across CPU code paths, issue 18) and IRLS crawls. See
    # linear.solve_psi for the choice of floor.
    irls_floor: float = 1e-3
    # sun models (capability compact-sun): hybrid sky transport and the global sun search
    sun_starts: int = 3  # search candidates refined by L-BFGS: distinct suns (>= 25 deg apart) + no sun
    sun_core_texels: int = 48  # lobe texels with exact visibility (sky_transport.py)
    sun_kappa_init: float = 6000.0
    sun_max_pixels: int | None = 2048  # evenly spaced usable pixels for sun models
    sun_all_starts_iters: int = 4  # L-BFGS iterations on every start, then the best one alone
    # after those, a solution whose sun share (_sun_share) is below this is overcast: the rest of
    # the fit skips the exact sun core (f2l dev bench shows the time saved and the error cost); 0 = never
    sun_core_min_share: float = 0.02
    # sun models (compact-sun): the sun's elevation profile. After the fit, copies of it with the
    # sun's elevation pinned at each of these (deg) are refined for sun_profile_iters L-BFGS
    # iterations; the estimate's sun direction is the posterior mean over the fit and its copies,
    # its probe their posterior mixture, weights exp(-sun_profile_temperature x relative excess
    # objective) (f2l.estimate.sun_profile); () = off. The free fit stalls in elevation (18
    # iterations; fits pinned 10 deg apart found a lower objective for 94 of the 128 faces of
    # `make eval-real`), and where the face cannot tell the elevation apart the posterior mean
    # hedges. Tuning part (fitted mesh): mean Sun-ang 12.3 -> 11.7 deg, MAE (s) 0.204 -> 0.195;
    # reporting part 18.6 -> 14.8, 0.211 -> 0.202; +30% time. docs/experiments/accuracy_issue16.md "What each change bought".
    sun_elevation_profile_deg: tuple[float, ...] = (10.0, 25.0, 40.0, 55.0, 70.0, 85.0)
    sun_profile_iters: int = 8
    sun_profile_temperature: float = 100.0
    # (elevation_rad, sigma_rad) from the photo's time and place (f2l.io.capture), or None; the
    # runner fills it per record when sun_prior_from_capture (CLI: --no-sun-prior turns it off)
    sun_elevation_prior: tuple[float, float] | None = None
    sun_prior_weight: float = 1e-3
    sun_prior_from_capture: bool = True
    sun_prior_sigma_rad: float = 0.05  # ~3 deg: the camera's tilt and the face fit's up vector
    # leave out pixels that look like specular highlights (usable_pixels / highlight_pixels); None
    # keeps them. At 1.0 it helped the tuning half of `make eval-real` (latent-sky mean Sun-ang
    # 21.4 -> 14.1 deg, compact-sun 15.3 -> 13.5) but not the reporting half (compact-sun 20.7 -> 22.6): off by default
    highlight_mad: float | None = None
    # sun models (capabilities compact-sun and latent-sky): clipped face pixels read channel
    # by channel, clipped channels as lower bounds (clipped_pixels). On the tuning half of `make
    # eval-real` the compact-sun model's mean Sun-ang 15.4 -> 13.0 deg, the latent-sky model's 21.2 ->
    # 19.8; on the reporting half the former's median 12.9 -> 11.1 (mean unchanged), the latter's mean
    # 22.3 -> 21.4; +18-20% time in
    # `f2l dev bench`. docs/experiments/accuracy_issue16.md "What each change bought".
    clipped_bounds: bool = True
    clipped_level: float = 0.95  # a channel at or above this (linear, 1 = white) counts as clipped
    # sun models (compact-sun): the skin's specular highlight of the sun in the forward model
    # (f2l.estimate.specular; GGX roughness fixed, k_s the best of a few levels up to
    # sun_specular_max for the data term at every evaluation); needs the record's 3-D points. Off:
    # on `make eval-real` (128 cases) the data pick k_s > 0 on 67% of the faces on the true mesh
    # and 28% on the fitted one; on the true mesh the compact-sun model's mean Sun-ang 9.5 -> 9.1 deg
    # (tuning part), MAE (s) -3%, on the fitted mesh no change. docs/experiments/accuracy_issue16.md "What each change bought".
    sun_specular: bool = False
    sun_specular_roughness: float = 0.5
    sun_specular_max: float = 0.15
    # sun models (compact-sun): the skin's gloss, an achromatic albedo g added to its diffuse one
    # in the forward model, s = (rho + g) ⊙ (T l). Skin reflects a few percent of the light at its
    # surface untinted by the skin, so a photo's skin is less red and bluer than its albedo
    # (docs/results/eval_real.md, the colour bullet under its first table), and a Lambertian reading gives that shift to the light
    # (make eval-real: R/G 0.92, B/G 1.09 of the truth's). The data term cannot tell g from rho; the
    # priors (on rho and on the light) split them. Tuning part (fitted mesh), g = 0 / 0.03 / 0.06 /
    # 0.1 / 0.15: MAE (s) 0.182 / 0.174 / 0.162 / 0.154 / 0.151, mean Sun-ang 10.3 / 10.8 / 11.1 /
    # 11.2 / 11.3 deg; the demo's Lambertian faces bound it (MAE (s) 0.048 / 0.032 / 0.051 / -, at
    # 0.06 RMSE (s) +14%, at 0.05 every metric within 10%). 0.05: tuning part 10.2 deg / 0.163,
    # reporting part 14.2 -> 14.4 deg, MAE (s) 0.197 -> 0.174. On Lambertian faces (f2l's own
    # renders) it is a colour bias, largest on dark skin: 40 of them MAE (s) 0.048 -> 0.072; there
    # use 0 (`f2l estimate --skin-gloss 0`). docs/experiments/accuracy_issue16.md "What each change bought".
    skin_gloss: float = 0.05
    # sun models (compact-sun): the skin's reflection of the environment about the mirror
    # direction, g_r pi ∫ K_p(r·w) l(w) dw with a normalised Phong lobe of exponent p
    # (f2l.estimate.reflection); needs the record's 3-D points; 0 = off. Chosen on the tuning
    # part of `make eval-real` from p = 4, 8, 16, 32 and g_r = 0.01, 0.015, 0.02: p = 16, g_r =
    # 0.01 gives mean Sun-ang 10.2 -> 9.1 deg, MAE (s) 0.163 -> 0.151 (reporting part 14.4 -> 14.8,
    # 0.174 -> 0.164). Off by default (`f2l estimate --skin-reflection 0.01`): on Lambertian faces
    # (f2l's own renders) it is a bias (`make demo`: Sun+Sky MAE (s) 0.043 -> 0.096), and it costs
    # +15% time a face against issue 16's time bound. docs/experiments/accuracy_issue16.md "The skin's reflection of the environment".
    skin_reflection: float = 0.0
    skin_reflection_exponent: float = 16.0


@dataclass
class EstimateResult:
    params: np.ndarray
    param_names: list[str]
    albedo: np.ndarray
    ground_albedo: float | None
    loss: float
    iterations: int
    converged: bool
    runtime_s: float
    probe: np.ndarray  # (H, W, 3) float32, ground included, >= 0
    sun_direction: np.ndarray | None
    timings: dict = field(default_factory=dict)
    start_losses: list = field(default_factory=list)
    num_pixels_used: int = 0
    specular_ks: float | None = None  # the sun highlight's k_s (EstimatorConfig.sun_specular), else None
