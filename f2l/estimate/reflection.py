"""The skin's gloss as a reflection of the environment, for sun models (``EstimatorConfig.skin_reflection``).

Glossy skin reflects part of the light at its surface, untinted by the skin, in a lobe about the
mirror direction r = 2 (n·v) n − v (v towards the camera). The term added to a face pixel's
shading is

    s_refl = g_r · π ∫ K_p(r·ω) l(ω) dω,     K_p(c) = (p + 1) / (2π) · max(c, 0)^p,

K_p a normalised Phong lobe (∫ K_p dω = 1 over the hemisphere about r), so a uniform sky of
radiance L gives g_r π L: g_r is the share of an unoccluded Lambertian irradiance the skin
reflects this way. Where the constant gloss ``skin_gloss`` (ρ + g) reads the light about the
normal, this one reads it about the mirror direction: the face's sides, seen at grazing angles,
mirror the sky and the sun behind the head rather than the light they face.

Pieces: the sky through the block means of ``SkyTransport`` (the kernel summed exactly over each
block's texels), the sun exactly (its lobe taken as a point of irradiance w_sun), the ground
(radiance ρ_g E_h / π) through the kernel's integral over the lower hemisphere. Visibility is
left out: the mirror direction of a face pixel points away from the face. Needs the record's 3-D
points (camera frame, camera at the origin) for v; without them there is no term.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from f2l.lighting.grid import LatLongGrid


class SkinReflection:
    """Per-pixel kernels of the reflection term for the pixels of one face (module docstring).

    ``term`` takes the sky's block means on the hybrid transport's blocks (``block`` texels of
    ``grid``) and pools them ``pool`` × ``pool`` (solid-angle weighted) before the kernel product,
    on grids of 64 rows or more (blocks of 22.5° at most on 64 × 128): the p = 16 lobe is 34°
    wide at half its peak, so such blocks keep the smooth sky's share, and the sun, the term's
    sharp part, stays exact. On the eval-real faces the pooled term gives the same estimates
    within their noise (docs/experiments/accuracy_issue16.md) at a quarter of the product's cost. The kernels are summed exactly
    over each pooled block's texels (float32, on a grid twice as coarse where that keeps texels of
    5.6° or less).
    """

    def __init__(self, normals: np.ndarray, points: np.ndarray, grid: LatLongGrid, block: tuple[int, int],
                 exponent: float, dtype=torch.float64, pool: int = 2) -> None:
        n = np.asarray(normals, dtype=np.float64)
        v = -np.asarray(points, dtype=np.float64)
        v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
        n_dot_v = np.clip((n * v).sum(1), 0.0, 1.0)
        r = 2.0 * n_dot_v[:, None] * n - v
        r /= np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-12)
        self.exponent = float(exponent)
        self.norm = 0.5 * (self.exponent + 1.0)  # π (p + 1) / (2π)
        br, bc = block
        rows, width = grid.sky_rows, grid.width
        nbr, nbc = rows // br, width // bc
        self.num_blocks_in = nbr * nbc
        pool = pool if grid.height >= 64 else 1  # pooled blocks of 22.5 deg at most
        pr = pool if nbr % pool == 0 else 1
        pc = pool if nbc % pool == 0 else 1
        self._pool = (nbr // pr, pr, nbc // pc, pc)
        omega_in = np.asarray(grid.solid_angles_flat[: rows * width], np.float64).reshape(nbr, br, nbc, bc).sum((1, 3))
        omega_out = omega_in.reshape(self._pool).sum((1, 3))
        self._share = torch.as_tensor((omega_in / np.repeat(np.repeat(omega_out, pr, 0), pc, 1)).reshape(-1), dtype=dtype)
        kr, kc = br * pr, bc * pc  # the pooled blocks in texels of ``grid``
        if kr % 2 == 0 and kc % 2 == 0 and grid.height % 2 == 0 and grid.width % 2 == 0 and grid.height >= 64:
            grid, kr, kc = LatLongGrid(grid.height // 2, grid.width // 2), kr // 2, kc // 2
        kernel = r.astype(np.float32) @ np.asarray(grid.directions_flat, np.float32).T  # (N, L) x solid angle
        np.maximum(kernel, 0.0, out=kernel)
        _power_inplace(kernel, self.exponent)
        kernel *= (self.norm * np.asarray(grid.solid_angles_flat, np.float64)).astype(np.float32)[None]
        rows, width = grid.sky_rows, grid.width
        sky = kernel[:, : rows * width].reshape(len(n), rows // kr, kr, width // kc, kc)
        self.k_blocks = torch.as_tensor(sky.sum((2, 4), dtype=np.float64).reshape(len(n), -1), dtype=dtype)  # (N, nb)
        self.k_ground = torch.as_tensor(kernel[:, rows * width :].sum(1, dtype=np.float64), dtype=dtype)  # (N,)
        self.mirror = torch.as_tensor(r, dtype=dtype)

    def pooled(self, sky_block_means: torch.Tensor) -> torch.Tensor:
        """(B, nb_in, 3) block means -> (B, nb, 3) means over the pooled blocks (solid-angle weighted)."""
        B = sky_block_means.shape[0]
        m = (sky_block_means * self._share[None, :, None]).reshape(B, *self._pool, 3).sum((2, 4))
        return m.reshape(B, -1, 3)

    def term(self, sky_block_means: torch.Tensor, sun_direction: torch.Tensor, w_sun: torch.Tensor,
             ground_radiance: torch.Tensor) -> torch.Tensor:
        """π ∫ K_p(r·ω) l(ω) dω, (B, N, 3): sky block means without the sun on the transport's
        blocks (B, nb_in, 3), sun directions (B, 3) and RGB irradiances (B, 3), ground radiance (B, 3)."""
        m = self.pooled(sky_block_means)
        B, nb, C = m.shape  # one (N, nb) x (nb, B C) product, not B batched ones
        out = (self.k_blocks @ m.transpose(0, 1).reshape(nb, B * C)).reshape(-1, B, C).transpose(0, 1)
        cos = (sun_direction @ self.mirror.T).clamp_min(0.0)  # (B, N)
        out = out + (self.norm * _power(cos, self.exponent))[:, :, None] * w_sun[:, None, :]
        return out + self.k_ground[None, :, None] * ground_radiance[:, None, :]


def _power(a: torch.Tensor, exponent: float) -> torch.Tensor:
    """a ** exponent; by repeated squaring where the exponent is a power of two (its gradient
    is then products too, cheaper than pow's)."""
    e = int(exponent)
    if e == exponent and e >= 1 and e & (e - 1) == 0:
        while e > 1:
            a = a * a
            e //= 2
        return a
    return a**exponent


def _power_inplace(a: np.ndarray, exponent: float) -> None:
    """a **= exponent in place; by repeated squaring where the exponent is a power of two."""
    e = int(exponent)
    if e == exponent and e >= 1 and e & (e - 1) == 0:
        while e > 1:
            np.multiply(a, a, out=a)
            e //= 2
    else:
        np.power(a, exponent, out=a)


def sky_block_means_without_sun(hybrid, l_sky: torch.Tensor, sun: tuple,
                                block_means: torch.Tensor | None = None) -> torch.Tensor:
    """(B, nb, 3) block means of the sky radiance (B, Lu, 3) with the sun's lobe taken out;
    ``sun = (vals (B, K), flat (B, K), w_sun (B, 3))`` as ``CompactSun.radiance_parts`` gives it;
    ``block_means``: ``hybrid.block_means(l_sky)`` where the caller has it."""
    vals, flat, w_sun = sun
    m = hybrid.block_means(l_sky) if block_means is None else block_means
    block_of = _block_index(hybrid)[flat]  # (B, K)
    lobe = torch.zeros(m.shape[:2], dtype=m.dtype).scatter_add(1, block_of, vals * hybrid.d_omega[flat])
    return m - (lobe / hybrid.omega_b[None])[:, :, None] * w_sun[:, None, :]


def _block_index(hybrid) -> torch.Tensor:
    """``hybrid.block_of`` as a tensor, made once per transport."""
    cached = getattr(hybrid, "_block_of_tensor", None)
    if cached is None:
        cached = hybrid._block_of_tensor = torch.as_tensor(hybrid.block_of)
    return cached


def sun_direction_of(params: torch.Tensor, layout) -> torch.Tensor:
    """(B, 3) unit sun directions of compact-sun parameters (grid convention: +Y up, azimuth 0 = −Z)."""
    el = params[:, layout.elevation].clamp(0.0, 0.5 * math.pi)
    az = params[:, layout.azimuth]
    c = torch.cos(el)
    return torch.stack([c * torch.sin(az), torch.sin(el), -c * torch.cos(az)], 1)
