"""The skin's glossy highlight of a whole probe, for ideal photos (``f2l eval geometry``).

A face pixel with unit normal ``n``, view direction ``v`` (towards the camera at the origin of the
record's camera frame) and visibility ``V`` on the probe's grid reflects, on top of its diffuse
shading, the microfacet radiance (Cook–Torrance, GGX distribution, Smith shadowing-masking, Schlick
Fresnel; Walter et al. 2007)::

    spec = Σ_ω V(ω) [n·ω > 0] D(n·h) G1(n·ω) G1(n·v) F(v·h) / (4 n·v) · l(ω) dΩ_ω,   h = (ω + v) / |ω + v|,
    D(c) = α² / (π (c² (α² − 1) + 1)²),  α = roughness²,
    G1(c) = 2c / (c + sqrt(α² + (1 − α²) c²)),  F(c) = F0 + (1 − F0)(1 − c)⁵,

per channel, uncoloured by the skin (the dichromatic model), over every texel of the sphere (the
ground reflects too). Roughness and F0 follow the principled BSDF's conventions (F0 = 0.08 ×
specular, α = roughness²). It is an evaluation tool, not part of the estimator: it adds to an
ideal photo what the renderer's glossy skin adds to a photo, so that its share of the error can be
measured on its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from f2l.lighting.grid import LatLongGrid

__all__ = ["Gloss", "glossy_highlight"]

NV_FLOOR = 1e-3  # n·v of a pixel seen exactly edge-on (the mask keeps n·v > 0.1)


@dataclass(frozen=True)
class Gloss:
    """A skin's gloss: principled roughness and F0, and its diffuse RGB albedo (which sets the
    photo's exposure relative to the uncoloured highlight)."""

    roughness: float
    f0: float
    albedo_rgb: tuple[float, float, float]


def _smith_g1(cos: np.ndarray, alpha2: float) -> np.ndarray:
    c = np.clip(cos, 1e-4, 1.0)
    return 2.0 * c / (c + np.sqrt(alpha2 + (1.0 - alpha2) * c * c))


def glossy_highlight(normals: np.ndarray, points: np.ndarray, visibility_bits: np.ndarray, grid: LatLongGrid,
                     probe: np.ndarray, roughness: float, f0: float, chunk: int = 256) -> np.ndarray:
    """(N, 3) highlight radiance of the module docstring for (N, 3) normals and camera-frame points,
    packed visibility bits (N, ceil(L / 8), little bit order) and an (H, W, 3) probe on ``grid``."""
    n = np.asarray(normals, np.float64)
    v = -np.asarray(points, np.float64)
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    p = np.asarray(probe, np.float64)
    if p.shape != grid.shape + (3,):
        raise ValueError(f"probe {p.shape} is not on the {grid.height}x{grid.width} grid")
    if not 0.0 < roughness <= 1.0 or not 0.0 <= f0 <= 1.0:
        raise ValueError(f"roughness {roughness} must lie in (0, 1] and F0 {f0} in [0, 1]")
    dirs = np.asarray(grid.directions_flat, np.float64)
    light = p.reshape(-1, 3) * np.asarray(grid.solid_angles_flat, np.float64)[:, None]  # l dΩ
    alpha2 = float(roughness) ** 4
    n_dot_v = np.clip((n * v).sum(1), NV_FLOOR, 1.0)
    out = np.zeros((n.shape[0], 3))
    for i in range(0, n.shape[0], chunk):
        nn, vv, nv = n[i:i + chunk], v[i:i + chunk], n_dot_v[i:i + chunk, None]
        visible = np.unpackbits(np.asarray(visibility_bits[i:i + chunk], np.uint8), axis=1, count=grid.size,
                                bitorder="little").astype(bool)
        n_dot_l = nn @ dirs.T
        h = dirs[None] + vv[:, None]
        h /= np.maximum(np.linalg.norm(h, axis=2, keepdims=True), 1e-12)
        n_dot_h = np.clip(np.einsum("cd,ctd->ct", nn, h), 0.0, 1.0)
        v_dot_h = np.clip(np.einsum("cd,ctd->ct", vv, h), 0.0, 1.0)
        dist = alpha2 / (math.pi * (n_dot_h * n_dot_h * (alpha2 - 1.0) + 1.0) ** 2)
        fresnel = f0 + (1.0 - f0) * (1.0 - v_dot_h) ** 5
        shadowing = _smith_g1(n_dot_l, alpha2) * _smith_g1(nv, alpha2)
        kernel = np.where(visible & (n_dot_l > 0.0), dist * shadowing * fresnel / (4.0 * nv), 0.0)
        out[i:i + chunk] = kernel @ light
    return out
