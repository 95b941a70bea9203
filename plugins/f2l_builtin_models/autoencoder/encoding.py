"""How HDR skies are represented for the autoencoder, and the sky-hemisphere geometry it uses.

Sky hemisphere: the upper half of an f2l lat-long probe (``docs/conventions.md``: row 0 the zenith,
+Y up, column centre u = 0.5 the camera's view -Z), area-resampled (energy preserving,
``f2l.lighting.resample``) to ``SKY_SHAPE`` = 32 x 128 (the upper rows of the default 64 x 128 grid).

Sun-centring: the sky is rotated about +Y so that its sun (:func:`sun_azimuth`: the
luminance-weighted centroid within 5 deg of the brightest sky texel) lies at azimuth 0, i.e. on
the edge between columns 63 and 64. A probe is then R(phi_sun) applied to the centred sky, with
R(phi) the column shift of :func:`rotate_columns`.

Encoding (per texel and channel, radiance l >= 0 in any linear unit):

    s = sum_sky Y(l) dOmega / 2 pi                (the sky's mean Rec.709 luminance: its exposure)
    e = (l / s)^(1/3)                             (POWER = 3)
    l = s * max(e, 0)^3                           (decoding)

Why: a sky spans ~5 decades within one probe (shadowed blue sky at ~0.1 of the mean, the sun's
texel at 1e3-1e4 x the mean on 32 x 128), and its absolute level depends on the camera. Dividing
by s removes the exposure, which becomes the exact latent coordinate z_0 = log s (model.py). The
cube root (CIE L*'s compression) then keeps e in about [0, 20] and resolves the sky's relative
differences almost as a log would (an L1 error of 0.01 at the mean sky is a 3% radiance error,
and the training noise sigma = 0.01 a 3% perturbation), while a sun texel (~750 x the mean sky
on 32 x 128) stays a large value, e ~ 9, that the training's squared-error term sees (train.py;
under a log encoding it is ~6.6 over a floor set by an arbitrary offset). e = 0 is black (no
floor, no offset), and the decoded radiance is never negative.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from f2l_builtin_models.autoencoder.model import SKY_SHAPE
from f2l.lighting.grid import LatLongGrid, rotate_y
from f2l.lighting.resample import column_overlap_matrix, resample, row_overlap_matrix

POWER = 3.0
REC709_LUMA = np.array([0.2126, 0.7152, 0.0722])
SUN_WINDOW_DEG = 5.0


class SkyFormatError(ValueError):
    """An image that is not a lat-long sky probe (the message names the file)."""


def sky_grid() -> LatLongGrid:
    """The full-sphere grid whose upper rows are the network's sky: 64 x 128."""
    return LatLongGrid(2 * SKY_SHAPE[0], SKY_SHAPE[1])


def sky_solid_angles() -> np.ndarray:
    """(32, 128) texel solid angles of the network's sky hemisphere (sum 2 pi), float64."""
    g = sky_grid()
    return np.array(g.solid_angles[: g.sky_rows])


def full_sphere(image: np.ndarray, name: str = "image") -> np.ndarray:
    """A lat-long probe (H, 2H, 3) full sphere or (H, 4H, 3) sky hemisphere -> full sphere
    (H', 2H', 3) float64 (a hemisphere gets a black lower half). Raises SkyFormatError naming
    ``name`` for other shapes and for NaN / infinite values; negatives are clipped to 0."""
    img = np.asarray(image)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] < 3 or img.shape[0] < 2:
        raise SkyFormatError(f"{name}: not an RGB image (shape {img.shape})")
    img = np.asarray(img[:, :, :3], dtype=np.float64)
    if not np.isfinite(img).all():
        raise SkyFormatError(f"{name}: holds NaN or infinite values")
    h, w = img.shape[:2]
    if w == 2 * h and h % 2 == 0:
        return np.maximum(img, 0.0)
    if w == 4 * h:
        return np.concatenate([np.maximum(img, 0.0), np.zeros_like(img)], axis=0)
    raise SkyFormatError(f"{name}: a {h}x{w} image is neither a lat-long full sphere (W = 2H, H even) "
                         "nor a sky hemisphere (W = 4H)")


def sun_azimuth(probe: np.ndarray) -> float:
    """Azimuth (radians, grid convention) of the sky's sun: the Y dOmega-weighted mean direction of
    the sky texels within 5 deg of the brightest one (any full-sphere lat-long (H, 2H, 3) probe)."""
    from f2l.metrics.lighting import sun_direction

    p = np.asarray(probe, dtype=np.float64)
    d = sun_direction(p, LatLongGrid(p.shape[0], p.shape[1]), window_deg=SUN_WINDOW_DEG)
    return float(math.atan2(d[0], -d[2]))


def centred_sky(probe: np.ndarray, azimuth: float | None = None) -> tuple[np.ndarray, float]:
    """(32, 128, 3) float64 sky hemisphere with the sun at azimuth 0, and the sun's azimuth.

    ``probe``: a full-sphere lat-long probe (:func:`full_sphere`). It is rotated at its own
    resolution (``rotate_y``, linear between columns) and then area-resampled to 64 x 128,
    whose upper 32 rows are kept. ``azimuth`` overrides the detected sun azimuth."""
    p = np.asarray(probe, dtype=np.float64)
    az = sun_azimuth(p) if azimuth is None else float(azimuth)
    rotated = rotate_y(p, az)
    g = sky_grid()
    small = rotated if rotated.shape[:2] == g.shape else resample(rotated, g.height, g.width)
    return np.maximum(small[: g.sky_rows], 0.0), az


def exposure(sky: np.ndarray) -> float:
    """s = sum Y(l) dOmega / 2 pi over a (32, 128, 3) sky: its mean luminance (> 0 required)."""
    return float(np.einsum("hwc,c,hw->", np.asarray(sky, np.float64), REC709_LUMA, sky_solid_angles()) / (2 * math.pi))


def encode(sky: np.ndarray, name: str = "sky") -> tuple[np.ndarray, float]:
    """(32, 128, 3) linear sky -> (encoded (3, 32, 128) float32, log s). Raises SkyFormatError for
    a sky without light."""
    s = exposure(sky)
    if not s > 0:
        raise SkyFormatError(f"{name}: the sky hemisphere is black")
    e = np.cbrt(np.maximum(np.asarray(sky, np.float64), 0.0) / s)
    return np.ascontiguousarray(e.transpose(2, 0, 1), dtype=np.float32), math.log(s)


def decode_numpy(e: np.ndarray, log_s: float) -> np.ndarray:
    """(3, 32, 128) encoded -> (32, 128, 3) linear radiance (float64)."""
    return math.exp(log_s) * (np.maximum(np.asarray(e, np.float64), 0.0) ** 3).transpose(1, 2, 0)


def decode_unit(e: torch.Tensor) -> torch.Tensor:
    """Encoded sky -> linear radiance of unit exposure: max(e, 0)^3 (any shape, e's dtype)."""
    c = e.clamp_min(0.0)
    return c * c * c


def decode_torch(e: torch.Tensor, log_s: torch.Tensor) -> torch.Tensor:
    """(B, 3, h, w) encoded, (B,) log exposure -> (B, 3, h, w) linear radiance (e's dtype)."""
    return torch.exp(log_s.to(e.dtype))[:, None, None, None] * decode_unit(e)


def rotate_columns(x: torch.Tensor, azimuth: torch.Tensor) -> torch.Tensor:
    """R(phi): (B, ..., W) sky(s) with the sun at azimuth 0 -> the sun at azimuth ``azimuth`` (B,).

    out(theta) = x(theta - phi): a circular shift of the columns by s = phi W / (2 pi), linear
    between the two neighbouring whole shifts (out[j] = (1 - f) x[j - k] + f x[j - k - 1],
    k = floor(s), f = s - k). A whole-column phi is exactly ``torch.roll(x, k, -1)``; the result
    is differentiable in x and (piecewise linearly) in phi; energy (column sums) is preserved.
    Equals ``f2l.lighting.grid.rotate_y(x, -phi)`` on (H, W, C) arrays."""
    w = x.shape[-1]
    shift = azimuth.to(x.dtype) * (w / (2.0 * math.pi))
    k = torch.floor(shift.detach())
    f = (shift - k).reshape(-1, *([1] * (x.dim() - 1)))
    cols = torch.arange(w, device=x.device)
    idx0 = torch.remainder(cols[None, :] - k.to(torch.int64)[:, None], w)  # (B, W)
    idx1 = torch.remainder(idx0 - 1, w)
    shape = (x.shape[0],) + (1,) * (x.dim() - 2) + (w,)
    g0 = torch.gather(x, -1, idx0.reshape(shape).expand(x.shape))
    g1 = torch.gather(x, -1, idx1.reshape(shape).expand(x.shape))
    return g0 + f * (g1 - g0)


def grid_resampler(grid: LatLongGrid) -> tuple[np.ndarray, np.ndarray] | None:
    """(rows (grid.sky_rows, 32), cols (grid.width, 128)) area-resampling matrices from the
    network's sky to ``grid``'s sky rows, or None when they coincide (64 x 128)."""
    g = sky_grid()
    if grid.height == g.height and grid.width == g.width:
        return None
    rows = np.array(row_overlap_matrix(grid.height, g.height)[: grid.sky_rows, : g.sky_rows])
    cols = np.array(column_overlap_matrix(grid.width, g.width))
    return rows, cols
