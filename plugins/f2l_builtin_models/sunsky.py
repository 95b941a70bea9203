"""Sun+Sky lighting model (Calian et al. 2018, §3.3.2): a Preetham sky plus a vMF sun.

    l(omega) = f(omega; omega_sun, t) * w_sky  +  C exp(kappa (omega_sun . omega - 1)) * w_sun,
    C = kappa / (2 pi (1 - e^{-2 kappa})),

with RGB weights w_sky, w_sun (products are per channel). Parameters, in order:

    w_sky_r, w_sky_g, w_sky_b    sky scale, radiance units (the sky's mean luminance radiance)
    w_sun_r, w_sun_g, w_sun_b    sun RGB irradiance at normal incidence (the lobe integrates to 1)
    sun_elevation_rad            [0, pi/2]: the sun is above the horizon (0 = on it, pi/2 = zenith)
    sun_azimuth_rad              [-pi, pi]: grid azimuth (0 = -Z, the camera's view; +pi/2 = +X);
                                 radiance is 2 pi-periodic in it, so any real value works
    turbidity                    [1.7, 35] (Preetham's t)
    kappa                        [8, 8192] (vMF concentration, 1/rad^2; sigma ~ 1/sqrt(kappa))

Conventions: f2l grid (``docs/conventions.md``: +Y up, row 0 the zenith, radiance (B, L, 3)
row-major over the whole grid). The domain is "sky": rows below the horizon are returned as 0
(the estimator replaces them by the ground bounce), and so is the part of the sun below it.

Sky f: Preetham et al. 1999 (appendix A.2, see ``preetham.py``): Perez ratios for Y, x, y at
texel centres, xyY -> XYZ -> linear Rec.709 RGB (colour-science's ITU-R BT.709 matrix, read
once, lazily), negative RGB clipped to 0, then scaled so that
sum_{upper texels} lum(f) dOmega = 2 pi, lum = Rec.709 luminance (the Y row of RGB -> XYZ):
the sky's mean luminance over the hemisphere is 1, independent of t and the sun's position,
so w_sky is the sky's mean radiance. Preetham's absolute zenith luminance Y_z cancels out.

Sun: each texel holds the lobe's mean over the texel (``f2l.lighting.sun_lobe``; integrated, never point
sampled), so its energy is right to ~3e-4 on 64 x 128 even for kappa = 8192 and the sun moves
smoothly between texel centres; only the lobe's window (below e^-40 of its peak outside) is
evaluated and scattered into the sky.

Numerics: inside ``radiance`` the parameters are clamped to their bounds (w >= 0, elevation to
[0, pi/2], t to [1.7, 35], kappa to [8, 8192]) so no input gives NaN (a clamped parameter has a
zero gradient beyond its bound). The sun-to-texel angle is gamma = acos(clamp(c, -1 + 1e-12,
1 - 1e-12)), c = omega . omega_sun: finite gradients when the sun sits exactly on a texel centre
(gamma = 0) or at the zenith, at the cost of gamma >= 1.4e-6 rad (negligible in e^{D gamma}).
The Perez term clamps cos(theta) >= 1e-3 (finite at and below the horizon) and y >= 1e-3 before
dividing by it. Everything is computed in float64 and returned in the parameters' dtype/device.

Timing (2-core Xeon VM, torch 2.13, 64 x 128 grid, batch 8, float64, kappa = 8192 or 1024):
radiance ~5 ms forward (median of runs 4.7-8 ms), ~14-17 ms forward + backward of a weighted
sum; the sky is ~2 ms of the forward, the lobe ~2 ms (per-op overhead of small tensors). The
machine has slow spells (up to ~15x). Measure with ``timeit`` on ``model.radiance`` of
``torch.as_tensor(model.initial_points()[:8])``; ``f2l dev bench`` times whole estimates.

References
----------
- Calian, Lalonde, Gotardo, Simon, Matthews, Mitchell. "From Faces to Outdoor Light Probes."
  Computer Graphics Forum (Eurographics) 37(2), 2018 (§3.3.2: the Sun+Sky model).
- Preetham, Shirley, Smits. "A Practical Analytic Model for Daylight." Proceedings of
  SIGGRAPH 99, pp. 91-100, 1999 (appendix A.2: the sky, in ``preetham.py``).
"""

from __future__ import annotations

import functools
import math
import os
from pathlib import Path

import numpy as np
import torch

from f2l.lighting.grid import LatLongGrid
from f2l.models.base import LightingModel
from f2l.models.capabilities import CompactSun, SunLayout
from f2l_builtin_models import preetham, sunsky_prior

ELEVATION_RANGE = (0.0, math.pi / 2.0)
AZIMUTH_RANGE = (-math.pi, math.pi)
TURBIDITY_RANGE = (1.7, 35.0)
KAPPA_RANGE = (8.0, 8192.0)
GAMMA_EPS = 1e-12  # gamma = acos(clamp(cos, -1 + eps, 1 - eps)): >= 1.4e-6 rad, finite gradient
DEFAULT_PRIOR_PATH = Path(__file__).parent / "data" / "sunsky_prior.json"
_SCORED_INDEX = [sunsky_prior.FEATURE_NAMES.index(name) for name in sunsky_prior.SCORED_FEATURES]
MAX_PRIOR_COMPONENTS = 4  # x 4 azimuths = 16 starts
SKY_INTEGRAL = 2.0 * math.pi  # sum of the normalised sky's luminance x dOmega over the hemisphere


# CIE XYZ -> linear Rec.709 RGB: colour-science's RGB_COLOURSPACES["ITU-R BT.709"].matrix_XYZ_to_RGB,
# bit for bit (tests/test_sunsky.py checks it against the library); held as a constant because
# importing colour-science costs about a second of every estimating process.
XYZ_TO_REC709 = (
    (3.240969941904522, -1.537383177570094, -0.49861076029300344),
    (-0.9692436362808798, 1.8759675015077206, 0.04155505740717563),
    (0.05563007969699364, -0.20397695888897655, 1.0569715142428786),
)


@functools.cache
def xyz_to_rgb_matrix() -> np.ndarray:
    """(3, 3) CIE XYZ -> linear Rec.709 RGB (:data:`XYZ_TO_REC709`)."""
    return np.array(XYZ_TO_REC709, dtype=np.float64)


@functools.cache
def rgb_luminance_weights() -> np.ndarray:
    """(3,) Rec.709 luminance weights: the Y row of the inverse of :func:`xyz_to_rgb_matrix`."""
    return np.linalg.inv(xyz_to_rgb_matrix())[1]


def rgb_from_xy1_matrix() -> np.ndarray:
    """(3, 3) N with RGB = (Y / y) N [x, y, 1]^T: xyY -> XYZ (X = x Y/y, Z = (1-x-y) Y/y) folded
    into M = :func:`xyz_to_rgb_matrix`: N = [M_0 - M_2, M_1 - M_2, M_2] (columns)."""
    m = xyz_to_rgb_matrix()
    return np.stack([m[:, 0] - m[:, 2], m[:, 1] - m[:, 2], m[:, 2]], 1)


class SunSky(CompactSun, LightingModel):
    """Preetham sky + integrated vMF sun, 10 parameters (see the module docstring).

    Capability ``compact-sun`` (``f2l.models.capabilities``): the model supplies the unit-weight
    Preetham sky (:meth:`sky`) and the layout; radiance, the sun lobe and the estimator's fast
    paths (exact-core transport, global sun search) come with the capability."""

    name = "sunsky"
    version = "1"
    description = "Sun+Sky: Preetham sky (turbidity) + vMF sun (kappa), RGB weights, 10 parameters"
    domain = "sky"

    def __init__(self, grid: LatLongGrid) -> None:
        super().__init__(grid)
        n = grid.sky_rows * grid.width
        self._dirs = np.array(grid.directions_flat[:n])  # (Lu, 3) texel centres of the sky rows
        self._sa = np.array(grid.solid_angles_flat[:n])
        self._cache: dict = {}

    @property
    def param_names(self) -> list[str]:
        return [
            "w_sky_r", "w_sky_g", "w_sky_b", "w_sun_r", "w_sun_g", "w_sun_b",
            "sun_elevation_rad", "sun_azimuth_rad", "turbidity", "kappa",
        ]  # fmt: skip

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        inf = np.inf
        ranges = (ELEVATION_RANGE, AZIMUTH_RANGE, TURBIDITY_RANGE, KAPPA_RANGE)
        lo = np.array([0.0] * 6 + [r[0] for r in ranges])
        hi = np.array([inf] * 6 + [r[1] for r in ranges])
        return lo, hi

    # -- prior (sunsky_prior.py; the GMM ships as data/sunsky_prior.json) ---------------------
    prior_feature_names = sunsky_prior.FEATURE_NAMES
    intensity_params = (0, 1, 2, 3, 4, 5)  # radiance is linear in w_sky, w_sun (fit-probe: log scale)

    @property
    def prior(self):
        """The GMM prior (:class:`f2l.estimate.model_prior.GmmPrior`) or None: $F2L_SUNSKY_PRIOR,
        else the shipped ``data/sunsky_prior.json`` (rebuilt by ``make prior``), each component
        widened by ``sunsky_prior.FEATURE_MIN_STD`` (the synthetic corpus is narrower than real
        skies: its overcast mode has a spread of 0.01 in every feature)."""
        if "prior" not in self._cache:
            from f2l.estimate.model_prior import load_prior

            path = Path(os.environ.get("F2L_SUNSKY_PRIOR", DEFAULT_PRIOR_PATH))
            prior = load_prior(path) if path.exists() else None
            self._cache["prior"] = None if prior is None else prior.widened(sunsky_prior.FEATURE_MIN_STD)
        return self._cache["prior"]

    @property
    def scored_prior(self):
        """The prior the estimator scores: :attr:`prior` marginalised over the sun's elevation
        (``sunsky_prior.SCORED_FEATURES``), or None without a prior."""
        if "scored_prior" not in self._cache:
            prior = self.prior
            self._cache["scored_prior"] = None if prior is None else prior.marginal(list(sunsky_prior.SCORED_FEATURES))
        return self._cache["scored_prior"]

    def prior_features(self, params: np.ndarray) -> np.ndarray:
        return sunsky_prior.features_numpy(params)

    def prior_nll(self, params: torch.Tensor) -> torch.Tensor:
        """GMM negative log-likelihood of the prior features but the sun's elevation (the GMM
        marginalised over it: :attr:`scored_prior`); 0 without a prior."""
        prior = self.scored_prior
        if prior is None:
            return super().prior_nll(params)
        return prior.nll_torch(sunsky_prior.features_torch(params)[:, _SCORED_INDEX])

    def probe_starts(self, probe_flat: np.ndarray) -> np.ndarray:
        """Starts for ``fit-probe``: the sun at the probe's brightest sky texel."""
        return sunsky_prior.probe_starts(self.grid, probe_flat)

    # -- sun search (f2l.estimate.sun_search): which parameters are the sun's and the weights ----
    sun_layout = SunLayout(sky_rgb=(0, 1, 2), sun_rgb=(3, 4, 5), elevation=6, azimuth=7, kappa=9)
    SEARCH_TURBIDITIES = (2.2, 4.5)  # the GMM's sunny and overcast modes (data/sunsky_prior.json)

    def search_shapes(self) -> np.ndarray:
        """(S, 10) sky shapes scored by the sun search: unit grey w_sky, no sun, each turbidity
        of ``SEARCH_TURBIDITIES`` (the search sets the sun's angles and both weights)."""
        return np.array([[1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.5, 0.0, t, 1024.0]
                         for t in self.SEARCH_TURBIDITIES])

    def initial_points(self) -> np.ndarray:
        """GMM starts: the ``MAX_PRIOR_COMPONENTS`` heaviest component means at 4 azimuths
        (sunsky_prior.params_from_features); without a prior, the placeholder starts below."""
        prior = self.prior
        if prior is None:
            return self._placeholder_starts()
        order = np.argsort(-prior.weights)[:MAX_PRIOR_COMPONENTS]
        return sunsky_prior.params_from_features(prior.means[order])

    def _placeholder_starts(self) -> np.ndarray:
        """(8, 10) deterministic starts: 4 azimuths (+-pi/4, +-3pi/4) x 2 elevations (22.5, 67.5 deg).

        t = 3, kappa = 1024, grey w_sky = 1 and w_sun = 10 (the estimator rescales intensities to
        the observation). Used only when no GMM prior is available.
        """
        starts = []
        for elevation in (math.pi / 8.0, 3.0 * math.pi / 8.0):
            for azimuth in (-0.75 * math.pi, -0.25 * math.pi, 0.25 * math.pi, 0.75 * math.pi):
                starts.append([1.0, 1.0, 1.0, 10.0, 10.0, 10.0, elevation, azimuth, 3.0, 1024.0])
        return np.array(starts, dtype=np.float64)

    # -- evaluation ----------------------------------------------------------------------------
    def _consts(self, device) -> tuple[torch.Tensor, ...]:
        key = str(device)
        if key not in self._cache:
            f64 = dict(dtype=torch.float64, device=device)
            self._cache[key] = (
                torch.as_tensor(self._dirs, **f64),
                torch.as_tensor(self._sa, **f64),
                torch.as_tensor(rgb_from_xy1_matrix(), **f64),
                torch.as_tensor(rgb_luminance_weights(), **f64),
            )
        return self._cache[key]

    @staticmethod
    def clamp_params(params: torch.Tensor) -> dict[str, torch.Tensor]:
        """Split (B, 10) parameters into named tensors clamped to the bounds (azimuth as is)."""
        p = params
        return dict(
            w_sky=p[:, 0:3].clamp_min(0.0),
            w_sun=p[:, 3:6].clamp_min(0.0),
            elevation=p[:, 6].clamp(*ELEVATION_RANGE),
            azimuth=p[:, 7],
            turbidity=p[:, 8].clamp(*TURBIDITY_RANGE),
            kappa=p[:, 9].clamp(*KAPPA_RANGE),
        )

    def sky(self, params: torch.Tensor) -> torch.Tensor:
        """(B, Lu, 3) normalised Preetham sky on the upper rows (float64), w_sky not applied: a
        transposed view of the channel-first computation (copying it costs more than it saves)."""
        p = self.clamp_params(params.to(torch.float64))
        rgb, scale = self._sky(p, *self._consts(params.device))
        return (rgb * scale[:, None, None]).transpose(1, 2)

    def _sky(self, p, dirs, sa, rgb_from_xy1, luma) -> tuple[torch.Tensor, torch.Tensor]:
        """Unnormalised sky RGB (B, 3, Lu) and its normaliser (B,) (channel-first: contiguous
        broadcasting is several times faster on CPU).

        Preetham's q = q_z F_q(theta, gamma) / F_q(0, theta_s) for q in (Y, x, y), with the
        theta factor (1 + A e^{B / cos theta}) evaluated once per row, not per texel, then
        RGB = M XYZ = (Y / y) N [x, y, 1] (N folds xyY -> XYZ into colour-science's matrix M).
        """
        el, az = p["elevation"], p["azimuth"]
        B, rows, W = el.shape[0], self.grid.sky_rows, self.grid.width
        sun = torch.stack([torch.cos(el) * torch.sin(az), torch.sin(el), -torch.cos(el) * torch.cos(az)], -1)
        cos_gamma = sun @ dirs.T  # (B, Lu)
        gamma = torch.acos(cos_gamma.clamp(-1.0 + GAMMA_EPS, 1.0 - GAMMA_EPS))
        sun_zenith = 0.5 * math.pi - el
        coeffs = preetham.perez_coefficients(p["turbidity"])  # (B, 3, 5), rows Y, x, y
        f0 = preetham.perez(torch.ones_like(el)[:, None], sun_zenith[:, None], torch.cos(sun_zenith)[:, None], coeffs)
        xz, yz = preetham.zenith_chromaticity(p["turbidity"], sun_zenith)
        zenith = torch.stack([torch.ones_like(xz), xz, yz], -1) / f0  # (B, 3)
        row_f = preetham.perez_theta_factor(dirs[::W, 1], coeffs[:, :, None, :]) * zenith[:, :, None]  # (B, 3, rows)
        # q = row_f (1 + C e^{D gamma} + E cos^2 gamma), fused
        c, d, e = (coeffs[:, :, None, None, i] for i in (2, 3, 4))
        row_f = row_f[..., None]  # (B, 3, rows, 1)
        g = gamma.reshape(B, 1, rows, W)
        q = torch.addcmul(row_f, row_f * e, (cos_gamma * cos_gamma).reshape(B, 1, rows, W))
        q = q.addcmul_(row_f * c, (d * g).exp_()).reshape(B, 3, rows * W)
        # q's channels are read whole (unbind, and N padded with a zero column for Y): slicing
        # them would make autograd zero-fill and add a q-sized gradient per slice
        q_big_y, _, q_y = q.unbind(1)
        ratio = q_big_y / q_y.clamp_min(1e-3)  # Y / y (y floored: the division stays finite)
        n_yxy = torch.nn.functional.pad(rgb_from_xy1[:, :2], (1, 0))  # (3, 3): 0, N_x, N_y
        xy1 = torch.baddbmm(rgb_from_xy1[:, 2:3].expand(B, 3, 1), n_yxy.expand(B, 3, 3), q)
        rgb = (xy1 * ratio[:, None, :]).relu_()  # (B, 3, Lu); out-of-gamut negatives clipped
        integral = (luma @ rgb) @ sa  # (B,)
        return rgb, SKY_INTEGRAL / integral.clamp_min(1e-300)
