"""An example third-party f2l lighting model: one directional light plus a uniform sky.

Copy this package to start a plugin. It registers in its own ``pyproject.toml``:

    [project.entry-points."f2l.lighting_models"]
    directional = "f2l_example_directional:DirectionalAmbient"

Parameters (8): sun elevation and azimuth (radians, f2l's grid convention: azimuth 0 = the
camera's viewing direction -Z, +pi/2 = +X), sun RGB power (irradiance at normal incidence,
W-like units), ambient sky RGB radiance. The sun is a narrow von Mises-Fisher lobe with
kappa = 300 whose texel values are renormalised so its solid-angle-weighted sum equals the sun
power exactly on any grid. ``domain = "sky"``: f2l adds the ground bounce below the horizon.
"""

from __future__ import annotations

import numpy as np
import torch

from f2l.models.base import LightingModel

KAPPA = 300.0


class DirectionalAmbient(LightingModel):
    name = "directional"
    version = "1"
    description = "Example plugin: one directional (vMF) light + uniform sky"
    domain = "sky"

    @property
    def param_names(self) -> list[str]:
        return ["sun_elevation_rad", "sun_azimuth_rad", "sun_R", "sun_G", "sun_B", "sky_R", "sky_G", "sky_B"]

    def bounds(self):
        lo = np.array([0.0, -np.pi, 0, 0, 0, 0, 0, 0], dtype=np.float64)
        hi = np.array([np.pi / 2, np.pi, np.inf, np.inf, np.inf, np.inf, np.inf, np.inf])
        return lo, hi

    def initial_points(self) -> np.ndarray:
        pts = []
        for elevation in (0.3, 0.9):
            for azimuth in (-2.4, -0.8, 0.8, 2.4):
                pts.append([elevation, azimuth, 3.0, 3.0, 3.0, 0.3, 0.3, 0.3])
        return np.asarray(pts, dtype=np.float64)

    def _sun_dirs(self, params: torch.Tensor) -> torch.Tensor:
        elevation, azimuth = params[:, 0], params[:, 1]
        polar = torch.pi / 2 - elevation
        return torch.stack(
            [torch.sin(polar) * torch.sin(azimuth), torch.cos(polar), -torch.sin(polar) * torch.cos(azimuth)], -1
        )

    def radiance(self, params: torch.Tensor) -> torch.Tensor:
        dirs = torch.as_tensor(np.array(self.grid.directions_flat), dtype=params.dtype)
        d_omega = torch.as_tensor(np.array(self.grid.solid_angles_flat), dtype=params.dtype)
        sun = self._sun_dirs(params)  # (B, 3)
        lobe = torch.exp(KAPPA * (dirs @ sun.T - 1.0)).T  # (B, L)
        lobe = lobe / (lobe * d_omega).sum(-1, keepdim=True)  # unit energy on this grid
        return lobe[..., None] * params[:, None, 2:5] + params[:, None, 5:8]

    def sun_direction(self, params: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return self._sun_dirs(torch.as_tensor(np.asarray(params, dtype=np.float64))[None])[0].numpy()
