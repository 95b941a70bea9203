"""A compact-sun probe with its sun spread over the sun direction's posterior
(``EstimatorConfig.sun_spread``; docs/experiments/sun_spread.md).

Why. The probe that minimises the expected error under the posterior over the sun's direction is
the posterior mean of the probe: the sun lobe convolved with that posterior. A sharp sun (kappa ~
6000, 0.6 deg) a few degrees off the truth is counted twice by the Full-dω probe error; a sun spread
over its own uncertainty is not.

How. The posterior is taken as a von Mises-Fisher distribution around the estimate's sun whose 68%
radius is ``sun_spread`` x the face's calibrated 68% cone r (f2l.estimate.uncertainty):

    P(angle <= r) = (1 - e^{-kappa_post (1 - cos r)}) / (1 - e^{-2 kappa_post}) = 0.68

(:func:`kappa_for_radius`; ~ -ln(0.32) / (1 - cos r) for narrow cones). A vMF convolved with a vMF
is close to a vMF whose mean cosine A(kappa) = coth(kappa) - 1/kappa is the product of theirs (the
first Legendre coefficient of a convolution on the sphere is the product of the two; exact for the
mean cosine, and 1/kappa ~ 1/kappa_sun + 1/kappa_post for narrow lobes: :func:`convolved_kappa`).
Each sun of the probe (its profile mixture's components too) is rewritten as that lobe
(``f2l.lighting.sun_lobe``) with

- its centre (the sun's direction) unchanged, and the estimate's parameters unchanged;
- its energy over the whole sphere exactly the sharp lobe's there (the sum of texel means x solid
  angles, so the lobe quadrature's ~3e-4 error cancels too);
- its part below the horizon dropped (``HORIZON = "drop"``): the probe's lower rows are the ground
  model's, and the posterior's mass below the horizon stands for the outcomes with no direct sun.
  A sun near the horizon with a wide cone thus loses up to half its energy. The alternative,
  "renormalise" (the part above the horizon scaled to the sharp lobe's energy there: the
  posterior truncated to the upper hemisphere), lifts a near-horizon sun's whole energy into the
  sky, where it lights the ground plane of the relit scene; on the tuning part of ``eval real``
  it gave the same Full-dω and a worse MAE (s) (docs/experiments/sun_spread.md).

A 68% radius above ~111 deg (a uniform sphere already holds 68% there) gets the widest lobe,
``KAPPA_MIN``. Overcast fits (no sun core) and models without a compact sun are not spread.

Conventions: the grid's (+Y up, azimuth 0 = -Z); radii in radians, kappa in 1/rad^2.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.optimize import brentq

from f2l.lighting.sun_lobe import sun_lobe, sun_lobe_sparse
from f2l.models.capabilities import KAPPA_RANGE

__all__ = ["LEVEL", "KAPPA_MIN", "KAPPA_MAX", "HORIZONS", "HORIZON", "mean_cosine", "kappa_for_radius", "convolved_kappa",
           "spread_lobe", "spread_sky_radiance"]

LEVEL = 0.68  # the cone's credibility: sun_cone68_deg
KAPPA_MIN = 1e-6  # the widest spread lobe (uniform over the sphere to 1e-6)
KAPPA_MAX = 1e12  # narrower posteriors than this (cone -> 0) leave the sun's own lobe
HORIZONS = ("renormalise", "drop")  # what becomes of a spread lobe's part below the horizon
HORIZON = "drop"  # chosen on the tuning part of eval-real (docs/experiments/sun_spread.md)


def mean_cosine(kappa: float) -> float:
    """A(kappa) = coth(kappa) - 1/kappa, the mean cosine of a vMF's angle to its centre.

    >>> [round(mean_cosine(k), 6) for k in (1e-9, 1.0, 8192.0)]
    [0.0, 0.313035, 0.999878]
    """
    if kappa < 1e-4:
        return kappa / 3.0  # series: kappa / 3 - kappa^3 / 45
    return 1.0 / math.tanh(kappa) - 1.0 / kappa


def _kappa_of_mean_cosine(target: float) -> float:
    """The vMF concentration whose mean cosine is ``target`` in (0, 1)."""
    if target <= mean_cosine(KAPPA_MIN):
        return KAPPA_MIN
    if target >= mean_cosine(KAPPA_MAX):
        return KAPPA_MAX
    log_k = brentq(lambda s: mean_cosine(math.exp(s)) - target, math.log(KAPPA_MIN), math.log(KAPPA_MAX),
                   xtol=1e-13, rtol=1e-14, maxiter=400)
    return math.exp(log_k)


def kappa_for_radius(radius_rad: float, level: float = LEVEL) -> float:
    """The vMF concentration whose cone of ``radius_rad`` around its centre holds ``level`` of its
    mass: (1 - e^{-kappa (1 - cos r)}) / (1 - e^{-2 kappa}) = level. KAPPA_MAX for r -> 0,
    KAPPA_MIN where a uniform sphere already holds ``level`` ((1 - cos r) / 2 >= level).

    >>> r = math.radians(10.0)
    >>> round(kappa_for_radius(r) * (1 - math.cos(r)) / -math.log(0.32), 6)  # narrow: the Gaussian limit
    1.0
    >>> kappa_for_radius(math.radians(120.0)) == KAPPA_MIN
    True
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    c = 2.0 * math.sin(0.5 * radius_rad) ** 2  # 1 - cos r, without cancellation
    if c <= 0.0:
        return KAPPA_MAX

    def held(log_k: float) -> float:
        k = math.exp(log_k)
        return -math.expm1(-k * c) / -math.expm1(-2.0 * k) - level

    lo, hi = math.log(KAPPA_MIN), math.log(KAPPA_MAX)
    if held(lo) >= 0.0:
        return KAPPA_MIN
    if held(hi) <= 0.0:
        return KAPPA_MAX
    return math.exp(brentq(held, lo, hi, xtol=1e-13, rtol=1e-14, maxiter=400))


def convolved_kappa(kappa_a: float, kappa_b: float) -> float:
    """The concentration of a vMF(kappa_a) convolved with a vMF(kappa_b), as the vMF of the same
    mean cosine: A(kappa) = A(kappa_a) A(kappa_b). Never above either.

    >>> round(convolved_kappa(6000.0, 100.0) * (1 / 6000 + 1 / 100), 3)  # narrow lobes: 1/kappa adds
    1.0
    """
    if kappa_b >= KAPPA_MAX:
        return float(kappa_a)
    if kappa_a >= KAPPA_MAX:
        return float(kappa_b)
    return min(_kappa_of_mean_cosine(mean_cosine(kappa_a) * mean_cosine(kappa_b)), kappa_a, kappa_b)


def spread_lobe(grid, zenith_rad: torch.Tensor, azimuth_rad: torch.Tensor, kappa_sun: torch.Tensor,
                radius68_rad: float, horizon: str | None = None) -> tuple[torch.Tensor, np.ndarray]:
    """Unit-energy vMF suns (B,) (``f2l.lighting.sun_lobe`` arguments, float64) spread over a vMF
    posterior of 68% radius ``radius68_rad``: (B, rows * W) texel means and the spread lobes'
    concentrations (B,). ``horizon`` (default ``HORIZON``): "drop" gives all H rows, each lobe
    with the sharp lobe's energy over the sphere (its part below the horizon is the caller's to
    drop); "renormalise" the sky rows, each lobe with the sharp lobe's energy there."""
    horizon = HORIZON if horizon is None else horizon
    if horizon not in HORIZONS:
        raise ValueError(f"horizon must be one of {HORIZONS}, got {horizon!r}")
    rows = grid.sky_rows if horizon == "renormalise" else grid.height
    solid = torch.tensor(grid.solid_angles_flat[: rows * grid.width], dtype=torch.float64)
    vals, flat = sun_lobe_sparse(grid, zenith_rad, azimuth_rad, kappa_sun, rows)
    energy = (vals * solid[flat]).sum(1)  # (B,) the sharp lobe's energy on those rows
    kappa_post = kappa_for_radius(float(radius68_rad))
    kappa = np.array([convolved_kappa(float(k), kappa_post) for k in kappa_sun.numpy()])
    lobe = sun_lobe(grid, zenith_rad, azimuth_rad, torch.as_tensor(kappa, dtype=torch.float64), rows)
    held = (lobe * solid).sum(1)  # > 0: the lobe's centre is on the rows
    return lobe * torch.where(held > 0, energy / held.clamp_min(1e-300), torch.zeros_like(held))[:, None], kappa


def spread_sky_radiance(model, params: torch.Tensor, radius68_rad: float,
                        horizon: str | None = None) -> tuple[torch.Tensor, np.ndarray]:
    """A compact-sun model's radiance on the sky rows, (B, sky_rows * W, 3) float64, with each
    row of ``params`` (B, P)'s sun spread over a vMF posterior of 68% radius ``radius68_rad``
    (:func:`spread_lobe`; the part below the horizon dropped or renormalised, ``horizon``), and
    the spread lobes' concentrations (B,). The sky part is the model's own (w_sky ⊙ sky(params));
    only the sun lobe is replaced."""
    grid, lay = model.grid, model.sun_layout
    with torch.no_grad():
        sky, w_sky, (_, _, w_sun) = model.light_parts(params)
        p = params.to(torch.float64)
        kappa_sun = (p[:, lay.kappa] if lay.kappa is not None else torch.full((len(p),), float(model.sun_kappa),
                                                                                dtype=torch.float64))
        zenith = 0.5 * math.pi - p[:, lay.elevation].clamp(0.0, 0.5 * math.pi)
        lobe, kappa = spread_lobe(grid, zenith, p[:, lay.azimuth], kappa_sun.clamp(*KAPPA_RANGE), radius68_rad, horizon)
        upper = sky * w_sky[:, None, :] + lobe[:, : grid.sky_rows * grid.width, None] * w_sun[:, None, :]
    return upper, kappa
