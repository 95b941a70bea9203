"""The skin's specular highlight of the sun, for sun models (``EstimatorConfig.sun_specular``).

Skin reflects a few percent of light at its surface, uncoloured by the skin (the dichromatic
model), in a lobe about the mirror direction. For a compact sun of RGB irradiance ``w_sun`` (at
normal incidence) in direction ``s``, a pixel with normal ``n``, view direction ``v`` (towards
the camera) and sun visibility ``V`` adds the microfacet radiance (Cook–Torrance with a GGX
distribution, shadowing-masking G ≈ 1, the Fresnel factor folded into ``k_s``):

    spec = k_s · V · [n·s > 0] · D(n·h) / (4 max(n·v, 0.2)) · w_sun,    h = (s + v) / |s + v|,
    D(c) = α² / (π (c² (α² − 1) + 1)²),   α = roughness²,

so the shading model of a face pixel becomes ``s = ρ ⊙ (T l) + spec`` (paper §3.2 plus the
specular term the paper leaves to future work). ``k_s`` (F0 of skin ≈ 0.028 for an index of 1.4)
is chosen per face at every evaluation of the objective as the best of a few levels in
[0, ``sun_specular_max``] for the data term (``f2l.estimate.problem.SPECULAR_LEVELS``), so a
face without a highlight keeps k_s = 0; the roughness is fixed. The sky's own highlight is
left out: it is broad and dim next to the sun's. ``V`` is the pixel's visibility bit of the sky
texel holding the sun (no gradient flows through it; through ``D`` and ``n·s`` it does).

The view direction comes from the record's 3-D points (camera frame, the camera at the origin);
without points there is no specular term.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from f2l.lighting.grid import LatLongGrid

NV_FLOOR = 0.2  # 1 / (4 n·v) grows without bound at grazing views; the mask rarely keeps those


class SunSpecular:
    """Per-pixel pieces of the sun's highlight for the pixels ``idx`` of an observation."""

    def __init__(self, normals: np.ndarray, points: np.ndarray, visibility_bits: np.ndarray,
                 grid: LatLongGrid, roughness: float, dtype=torch.float64) -> None:
        n = np.asarray(normals, dtype=np.float64)
        v = -np.asarray(points, dtype=np.float64)
        v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
        self.grid = grid
        self.normals = torch.as_tensor(n, dtype=dtype)
        self.view = torch.as_tensor(v, dtype=dtype)
        self.n_dot_v = torch.as_tensor(np.maximum((n * v).sum(1), NV_FLOOR), dtype=dtype)
        sky_texels = grid.sky_rows * grid.width
        bits = np.unpackbits(np.asarray(visibility_bits, np.uint8), axis=1, count=sky_texels, bitorder="little")
        self.visible = torch.from_numpy(np.ascontiguousarray(bits.T.astype(bool)))  # (Lu, N)
        self.alpha2 = float(roughness) ** 4

    @staticmethod
    def sun_direction(elevation: torch.Tensor, azimuth: torch.Tensor) -> torch.Tensor:
        """(B, 3) unit directions (grid convention, ``f2l.lighting.grid.direction_from_angles``)."""
        c = torch.cos(elevation)
        return torch.stack([c * torch.sin(azimuth), torch.sin(elevation), -c * torch.cos(azimuth)], dim=1)

    def shading(self, direction: torch.Tensor) -> torch.Tensor:
        """(B, N): V [n·s > 0] D(n·h) / (4 max(n·v, 0.2)) for sun directions (B, 3)."""
        d = direction.detach().cpu().numpy()
        row, col = self.grid.direction_to_texel(d)
        row = np.minimum(row, self.grid.sky_rows - 1)
        vis = self.visible[torch.from_numpy(row * self.grid.width + col)].to(direction.dtype)  # (B, N)
        h = direction[:, None, :] + self.view[None]
        h = h / h.norm(dim=2, keepdim=True).clamp_min(1e-12)
        n_dot_h = (h * self.normals[None]).sum(2).clamp(0.0, 1.0)
        n_dot_s = (direction @ self.normals.T)
        a2 = self.alpha2
        dist = a2 / (math.pi * (n_dot_h * n_dot_h * (a2 - 1.0) + 1.0) ** 2)
        return vis * (n_dot_s > 0).to(direction.dtype) * dist / (4.0 * self.n_dot_v[None])
