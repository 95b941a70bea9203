"""Procedural clouds for the autoencoder's sky corpus (numpy, deterministic from a generator).

Cloud field. Clouds live on a horizontal layer: a sky direction d (d_y > 0) meets it at plane
coordinates q = scale (d_x, d_z) / (d_y + 0.12) (the +0.12 keeps the horizon finite; clouds
crowd together towards the horizon, as perspective makes them). There an fBm value noise

    n(q) = sum_{o<6} 0.5^o v(2^o q + offset_o) / sum_o 0.5^o,   v: value noise in [0, 1]
           (random lattice values, quintic interpolation)

is thresholded to the wanted cover c: density rho = smoothstep(t, t + 0.1, n) with t the
solid-angle-weighted (1 - c) quantile of n over the sky, so a fraction c of the sky is cloud.
Towards the horizon (d_y < 0.1) the noise is blended to its mean (the layer is seen too obliquely
to resolve its texture on the grid). Optical depth tau = tau_max rho; transmittance T = e^-tau.

Cloud radiance, with E the sun's RGB irradiance (after the atmosphere), Y(.) luminance, gamma the
angle to the sun and HG the Henyey-Greenstein phase function (g = 0.75, normalised over 4 pi):

    L = T L_clear                                           clear sky seen through the cloud
      + (1 - T) (Y(E) / pi) a_d (0.35 + 0.65 e^{-tau/6}) c   sun-lit body, greyer when thick
      + (1 - T) sqrt(T) (Y(E) / pi) a_f 4 pi HG(cos gamma) c  forward scattering: bright, thin
                                                              edges around the sun (silver lining)
      + (1 - T) a_s mean(L_clear)                             skylight on the cloud

with c the cloud colour (white blended with the sun's chromaticity) and the sun's lobe multiplied
by T at its texels, so a cloud in front of the sun dims it partly (thin edge) or fully (thick
core). Overcast skies (:func:`overcast_radiance`) are the CIE overcast gradient (1 + 2 cos Z) / 3,
grey with a small tint, modulated by a low-contrast fBm and, for a thin deck, a soft glow
g e^{k (cos gamma - 1)} towards the hidden sun; they have no direct sun.
"""

from __future__ import annotations

import math

import numpy as np

HG_G = 0.75
HORIZON_OFFSET = 0.12
OCTAVES = 6
SOFTNESS = 0.1


class ValueNoise:
    """2-D value noise on an integer lattice of period 256, seeded (values in [0, 1])."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.perm = np.concatenate([rng.permutation(256)] * 2)
        self.values = rng.uniform(0.0, 1.0, 256)

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        xf, yf = np.floor(x), np.floor(y)
        xi, yi = xf.astype(np.int64) & 255, yf.astype(np.int64) & 255
        tx, ty = x - xf, y - yf
        fx = tx * tx * tx * (tx * (6 * tx - 15) + 10)  # quintic fade
        fy = ty * ty * ty * (ty * (6 * ty - 15) + 10)
        p, v = self.perm, self.values

        def corner(dx, dy):
            return v[p[p[(xi + dx) & 255] + ((yi + dy) & 255)]]

        top = corner(0, 0) + fx * (corner(1, 0) - corner(0, 0))
        bottom = corner(0, 1) + fx * (corner(1, 1) - corner(0, 1))
        return top + fy * (bottom - top)


def fbm(noise: ValueNoise, x: np.ndarray, y: np.ndarray, offsets: np.ndarray, octaves: int = OCTAVES) -> np.ndarray:
    """sum_o 0.5^o noise(2^o (x, y) + offsets[o]) / sum_o 0.5^o, in [0, 1]."""
    total = np.zeros_like(x)
    norm = 0.0
    for o in range(octaves):
        f, a = 2.0**o, 0.5**o
        total += a * noise(f * x + offsets[o, 0], f * y + offsets[o, 1])
        norm += a
    return total / norm


def henyey_greenstein(cos_gamma: np.ndarray, g: float = HG_G) -> np.ndarray:
    """HG phase function (1 - g^2) / (4 pi (1 + g^2 - 2 g cos)^1.5) (integrates to 1 over 4 pi)."""
    return (1.0 - g * g) / (4.0 * math.pi * (1.0 + g * g - 2.0 * g * cos_gamma) ** 1.5)


def cloud_noise(dirs: np.ndarray, rng: np.random.Generator, scale: float) -> np.ndarray:
    """fBm n in [0, 1] at sky directions (..., 3) on the cloud layer (module docstring)."""
    noise = ValueNoise(rng)
    offsets = rng.uniform(0.0, 256.0, (OCTAVES, 2))
    up = np.maximum(dirs[..., 1], 0.0)
    qx = scale * dirs[..., 0] / (up + HORIZON_OFFSET)
    qz = scale * dirs[..., 2] / (up + HORIZON_OFFSET)
    n = fbm(noise, qx, qz, offsets)
    fade = np.clip(up / 0.1, 0.0, 1.0)
    return fade * n + (1.0 - fade) * float(np.mean(n))


def weighted_quantile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    """The q-quantile of ``values`` under non-negative ``weights`` (same shape)."""
    v, w = values.reshape(-1), weights.reshape(-1)
    order = np.argsort(v)
    cum = np.cumsum(w[order])
    i = int(np.searchsorted(cum, q * cum[-1]))
    return float(v[order[min(i, v.size - 1)]])


def cloud_density(dirs: np.ndarray, solid_angles: np.ndarray, rng: np.random.Generator, cover: float,
                  scale: float) -> np.ndarray:
    """Density rho in [0, 1] over sky directions (H, W, 3), a fraction ``cover`` of the sky > 0."""
    n = cloud_noise(dirs, rng, scale)
    t = weighted_quantile(n, solid_angles, 1.0 - cover)
    x = np.clip((n - t) / SOFTNESS, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def cloud_colour(sun_rgb: np.ndarray, sun_tint: float) -> np.ndarray:
    """Unit-luminance cloud colour: white blended by ``sun_tint`` towards the sun's chromaticity."""
    luma = np.array([0.2126, 0.7152, 0.0722])
    sun = sun_rgb / max(float(sun_rgb @ luma), 1e-12)
    c = (1.0 - sun_tint) * np.ones(3) + sun_tint * sun
    return c / float(c @ luma)


def partly_cloudy(clear: np.ndarray, dirs: np.ndarray, solid_angles: np.ndarray, sun_dir: np.ndarray,
                  sun_rgb: np.ndarray, rng: np.random.Generator, cover: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """Clouds over a clear sky (module docstring).

    clear: (H, W, 3) clear-sky radiance without the sun; dirs (H, W, 3) and solid_angles (H, W)
    of the same sky texels; sun_rgb the sun's RGB irradiance. Returns (radiance (H, W, 3),
    transmittance T (H, W) for the sun's lobe, parameters drawn)."""
    scale = float(rng.uniform(0.5, 1.5))
    tau_max = float(rng.uniform(3.0, 15.0))
    a_d = float(rng.uniform(0.25, 0.6))
    a_f = float(rng.uniform(0.02, 0.08))
    a_s = float(rng.uniform(0.3, 0.8))
    tint = float(rng.uniform(0.2, 0.6))
    rho = cloud_density(dirs, solid_angles, rng, cover, scale)
    tau = tau_max * rho
    trans = np.exp(-tau)
    e_lum = float(sun_rgb @ np.array([0.2126, 0.7152, 0.0722]))
    colour = cloud_colour(sun_rgb, tint)
    cos_g = np.clip(dirs @ sun_dir, -1.0, 1.0)
    body = a_d * (0.35 + 0.65 * np.exp(-tau / 6.0))
    forward = a_f * 4.0 * math.pi * henyey_greenstein(cos_g) * np.sqrt(trans)
    sky_mean = (clear * solid_angles[..., None]).sum((0, 1)) / solid_angles.sum()
    lit = ((1.0 - trans) * (body + forward) * e_lum / math.pi)[..., None] * colour
    out = trans[..., None] * clear + lit + ((1.0 - trans) * a_s)[..., None] * sky_mean
    info = {"cloud_cover": float(cover), "cloud_scale": scale, "cloud_tau_max": tau_max}
    return out, trans, info


def overcast_radiance(dirs: np.ndarray, solid_angles: np.ndarray, sun_dir: np.ndarray,
                      rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """Overcast sky (H, W, 3), zenith radiance ~1 (module docstring); no direct sun."""
    cos_z = np.clip(dirs[..., 1], 0.0, 1.0)
    n = cloud_noise(dirs, rng, float(rng.uniform(0.5, 1.5)))
    contrast = float(rng.uniform(0.1, 0.5))
    glow_k = float(rng.uniform(2.0, 12.0))
    glow = float(rng.uniform(0.0, 1.5)) if rng.uniform() < 0.6 else 0.0
    cos_g = np.clip(dirs @ sun_dir, -1.0, 1.0)
    lum = (1.0 + 2.0 * cos_z) / 3.0 * (1.0 + contrast * (n - 0.5)) + glow * np.exp(glow_k * (cos_g - 1.0))
    tint = 1.0 + rng.uniform(-0.04, 0.04, 3)
    tint = tint / float(tint @ np.array([0.2126, 0.7152, 0.0722]))
    info = {"cloud_cover": 1.0, "overcast_contrast": contrast, "overcast_glow": glow}
    return np.maximum(lum, 0.0)[..., None] * tint, info
