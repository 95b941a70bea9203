"""Skin's glossy highlight of a whole probe: GGX microfacet reflection with Smith shadowing and
Schlick Fresnel (Cook–Torrance; Walter et al. 2007), shared by the synthetic faces
(:func:`f2l.synth.render.render_face`) and the ideal photos of :mod:`f2l.evaluation.highlight`.

A face pixel with unit normal ``n``, view direction ``v`` (towards the camera at the origin of the
camera frame) and visibility ``V`` on the probe's grid reflects, on top of its diffuse shading::

    spec = Σ_ω V(ω) [n·ω > 0] D(n·h) G1(n·ω) G1(n·v) F(v·h) / (4 n·v) · l(ω) dΩ_ω,
    h = (ω + v) / |ω + v|,
    D(c) = α² / (π (c² (α² − 1) + 1)²),  α = roughness²,
    G1(c) = 2c / (c + sqrt(α² + (1 − α²) c²)),  F(c) = F0 + (1 − F0)(1 − c)⁵,

per channel, uncoloured by the skin (the dichromatic model), over every texel of the sphere (sky,
sun and ground), each texel sampled at its centre. Roughness and F0 follow the principled BSDF's
conventions (F0 = 0.08 × specular, α = roughness²) and the ranges of the path-traced faces
(:mod:`f2l.render.dataset`: roughness 0.3–0.7, specular 0.35–0.6, so F0 0.028–0.048).

The sun of a probe is a few texels of huge radiance; its highlight is the kernel at those texels'
centres times their energy, so it is finite (the kernel is bounded: D ≤ 1/(π α²), and the
G1(n·v)/(4 n·v) factor stays finite as n·v → 0) and sits up to half a texel from the exact sun's
(docs/experiments/synth_gloss.md measures the difference against a point sun).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from f2l.lighting.grid import LatLongGrid

__all__ = ["SkinGloss", "glossy_highlight", "sample_skin_gloss", "ROUGHNESS_RANGE", "SPECULAR_RANGE",
           "F0_PER_SPECULAR"]

NV_FLOOR = 1e-3  # n·v of a pixel seen exactly edge-on (records keep n·v > 0.1)
# The path tracer's skin (f2l.render.dataset draws these; synth sits below render, so they are repeated here).
ROUGHNESS_RANGE = (0.3, 0.7)
SPECULAR_RANGE = (0.35, 0.6)
F0_PER_SPECULAR = 0.08  # the principled BSDF's F0 = 0.08 × specular


@dataclass(frozen=True)
class SkinGloss:
    """A skin's gloss: principled roughness (α = roughness²) and normal-incidence Fresnel F0."""

    roughness: float
    f0: float

    def to_meta(self) -> dict:
        return {"roughness": float(self.roughness), "f0": float(self.f0)}


def sample_skin_gloss(rng: np.random.Generator) -> SkinGloss:
    """Roughness ~ U(ROUGHNESS_RANGE), F0 = F0_PER_SPECULAR × U(SPECULAR_RANGE): two draws from ``rng``."""
    roughness = float(rng.uniform(*ROUGHNESS_RANGE))
    f0 = F0_PER_SPECULAR * float(rng.uniform(*SPECULAR_RANGE))
    return SkinGloss(roughness, f0)


def _smith_g1(cos: np.ndarray, alpha2: float) -> np.ndarray:
    c = np.clip(cos, 1e-4, 1.0)
    return 2.0 * c / (c + np.sqrt(alpha2 + (1.0 - alpha2) * c * c))


def _similar_normals_order(n: np.ndarray) -> np.ndarray:
    """Pixel order that groups similar normals (16 azimuth sectors about +Z, then by n_y), so a
    chunk's lit hemispheres overlap and fewer texels need the kernel."""
    sector = np.floor((np.arctan2(n[:, 0], n[:, 2]) + math.pi) / (2.0 * math.pi) * 16.0)
    return np.lexsort((n[:, 1], sector))


def glossy_highlight(normals: np.ndarray, points: np.ndarray, visibility_bits: np.ndarray, grid: LatLongGrid,
                     probe: np.ndarray, roughness: float, f0: float, chunk: int = 128,
                     dtype=np.float64) -> np.ndarray:
    """(N, 3) float64 highlight radiance of the module docstring for (N, 3) unit normals and
    camera-frame points, packed visibility bits (N, ceil(L / 8), little bit order) and an (H, W, 3)
    probe on ``grid``. The half vector enters only through n·h = (n·ω + n·v) / |ω + v| and
    v·h = (v·ω + 1) / |ω + v|, |ω + v|² = 2 + 2 v·ω; pixels are taken in chunks of similar normals
    and each chunk sums only the texels that some pixel of it sees (the others add exactly 0).
    ``dtype``: the kernel's arithmetic (float32 is 2-3x faster, relative error ~1e-5)."""
    n = np.asarray(normals, np.float64)
    v = -np.asarray(points, np.float64)
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    p = np.asarray(probe, np.float64)
    if p.shape != grid.shape + (3,):
        raise ValueError(f"probe {p.shape} is not on the {grid.height}x{grid.width} grid")
    if not 0.0 < roughness <= 1.0 or not 0.0 <= f0 <= 1.0:
        raise ValueError(f"roughness {roughness} must lie in (0, 1] and F0 {f0} in [0, 1]")
    dt = np.dtype(dtype).type
    dirs_t = np.ascontiguousarray(np.asarray(grid.directions_flat, np.float64).T, dtype=dt)
    light = (p.reshape(-1, 3) * np.asarray(grid.solid_angles_flat, np.float64)[:, None]).astype(dt)  # l dΩ
    alpha2 = dt(float(roughness) ** 4)
    f0 = dt(f0)
    n_dot_v_raw = (n * v).sum(1)
    n_dot_v = np.clip(n_dot_v_raw, NV_FLOOR, 1.0)
    bits = np.asarray(visibility_bits, np.uint8)
    order = _similar_normals_order(n)
    out = np.zeros((n.shape[0], 3))
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):  # small products: OpenBLAS's spinning threads cost more
        _accumulate(out, n, v, n_dot_v_raw, n_dot_v, bits, order, dirs_t, light, alpha2, f0, grid.size, chunk, dt)
    return out


def _accumulate(out, n, v, n_dot_v_raw, n_dot_v, bits, order, dirs_t, light, alpha2, f0, size, chunk, dt):
    one = dt(1.0)
    for i in range(0, n.shape[0], chunk):
        rows = order[i:i + chunk]
        nv = n_dot_v[rows, None].astype(dt)
        n_dot_l = n[rows].astype(dt) @ dirs_t
        lit = np.unpackbits(bits[rows], axis=1, count=size, bitorder="little").view(bool)
        lit &= n_dot_l > 0.0
        cols = np.flatnonzero(lit.any(0))
        lit, n_dot_l = np.take(lit, cols, axis=1), np.take(n_dot_l, cols, axis=1)  # C order (x[:, cols] is F)
        # t = |ω + v|² = 2 + 2 v·ω; below 1e-12 only within 1e-6 rad of ω = −v (no texel centre in practice)
        t = v[rows].astype(dt) @ dirs_t[:, cols]
        v_dot_h = t + one  # (v·ω + 1), divided by |ω + v| below
        t *= 2.0
        t += 2.0
        np.maximum(t, dt(1e-12), out=t)
        np.sqrt(t, out=t)
        np.divide(one, t, out=t)  # t = 1 / |ω + v|
        v_dot_h *= t
        np.clip(v_dot_h, 0.0, 1.0, out=v_dot_h)
        n_dot_h = n_dot_l + n_dot_v_raw[rows, None].astype(dt)
        n_dot_h *= t
        np.clip(n_dot_h, 0.0, 1.0, out=n_dot_h)
        # D = α² / (π (c² (α² − 1) + 1)²), c = n·h
        kernel = np.square(n_dot_h, out=n_dot_h)
        kernel *= alpha2 - one
        kernel += one
        np.square(kernel, out=kernel)
        np.divide(alpha2 / dt(math.pi), kernel, out=kernel)
        # Schlick: F0 + (1 − F0)(1 − v·h)⁵
        w = np.subtract(one, v_dot_h, out=v_dot_h)
        np.maximum(w, dt(1e-6), out=w)  # (1e-6)⁵ = 1e-30 stays a normal float32 (denormals are slow); F0 ≫ 1e-30
        w5 = np.square(w)
        np.square(w5, out=w5)
        w5 *= w
        w5 *= one - f0
        w5 += f0
        kernel *= w5
        kernel *= _smith_g1(n_dot_l, alpha2)
        kernel *= _smith_g1(nv, alpha2) / (dt(4.0) * nv)
        kernel *= lit
        out[rows] = kernel @ light[cols]
