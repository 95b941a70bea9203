"""An example f2l plugin that uses the estimator's fast paths: a sun plus a gradient sky.

    l(omega) = w_sky ⊙ f(omega; h)  +  w_sun ⊙ vMF(omega; sun, kappa = 2048)

f is a grey sky that changes linearly with the sine of the elevation, from ``h`` times the
zenith's radiance at the horizon to the zenith, normalised so that its mean over the upper
hemisphere is 1 (so ``w_sky`` is the sky's mean radiance):

    f(e) = (h + (1 - h) sin e) / ((1 + h) / 2),   0 <= e <= pi/2,  h in [0.05, 20]

(the integral of sin e over the hemisphere, with dOmega = cos e de dphi, is pi, so the mean of
h + (1 - h) sin e is (1 + h) / 2). It is written only against ``docs/plugins.md``: the class
declares the ``compact-sun`` capability (``f2l.models.capabilities.CompactSun``) with its
``sun_layout`` and supplies the unit-weight sky (``sky``); radiance, the integrated sun lobe,
the exact-core transport and the global sun search come with the capability.

Parameters (9): w_sky_r/g/b (mean sky radiance), w_sun_r/g/b (sun irradiance at normal
incidence), sun_elevation_rad, sun_azimuth_rad (f2l's grid convention: 0 = the camera's view,
-Z; +pi/2 = +X), horizon_ratio h. ``domain = "sky"``: f2l adds the ground bounce.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from f2l.models.base import LightingModel
from f2l.models.capabilities import CompactSun, SunLayout

HORIZON_RATIO_RANGE = (0.05, 20.0)


class GradientSun(CompactSun, LightingModel):
    name = "gradient_sun"
    version = "1"
    description = "Example plugin (compact-sun): vMF sun (kappa 2048) + horizon-to-zenith gradient sky, 9 parameters"
    domain = "sky"
    sun_layout = SunLayout(sky_rgb=(0, 1, 2), sun_rgb=(3, 4, 5), elevation=6, azimuth=7)  # kappa fixed:
    sun_kappa = 2048.0
    intensity_params = (0, 1, 2, 3, 4, 5)

    @property
    def param_names(self) -> list[str]:
        return ["w_sky_r", "w_sky_g", "w_sky_b", "w_sun_r", "w_sun_g", "w_sun_b",
                "sun_elevation_rad", "sun_azimuth_rad", "horizon_ratio"]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.array([0.0] * 6 + [0.0, -math.pi, HORIZON_RATIO_RANGE[0]])
        hi = np.array([np.inf] * 6 + [0.5 * math.pi, math.pi, HORIZON_RATIO_RANGE[1]])
        return lo, hi

    def initial_points(self) -> np.ndarray:
        """Two sky shapes (brighter at the zenith, brighter at the horizon) x 4 sun azimuths.
        With compact-sun the estimator starts from its sun search instead; these give the
        search its sky shapes (``search_shapes``) and serve ``fit-probe``."""
        starts = []
        for ratio in (0.5, 2.0):
            for azimuth in (-0.75 * math.pi, -0.25 * math.pi, 0.25 * math.pi, 0.75 * math.pi):
                starts.append([1.0, 1.0, 1.0, 10.0, 10.0, 10.0, math.pi / 4, azimuth, ratio])
        return np.array(starts, dtype=np.float64)

    def sky(self, params: torch.Tensor) -> torch.Tensor:
        """(B, 9) -> (B, sky_rows * W, 3): the unit-weight gradient sky (float64)."""
        grid = self.grid
        n = grid.sky_rows * grid.width
        sin_e = torch.as_tensor(np.maximum(grid.directions_flat[:n, 1], 0.0), dtype=torch.float64)
        h = params[:, 8].to(torch.float64).clamp(*HORIZON_RATIO_RANGE)[:, None]
        f = (h + (1.0 - h) * sin_e[None, :]) / (0.5 * (1.0 + h))
        return f[:, :, None].expand(-1, -1, 3)
