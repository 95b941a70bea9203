"""Global search for the sun before the non-linear fit (the multi-start centroids of sun models).

For a fixed sun direction and sky shape, a compact-sun model (``f2l.models.capabilities.CompactSun``) is linear in its RGB weights:

    s_c = psi_sky,c a_c + psi_sun,c b,   a_c = T f_c + g (rho_g/pi) E_h(f_c),
                                         b   = T[:, w] / dOmega_w + g (rho_g/pi) sin(elevation),

(psi = albedo x weight per channel c, f the unit-weight sky, b a point sun of unit irradiance at
texel w, g the ground row sums). So every candidate (sun texel on a ~5.6 deg lattice x sky shape)
is scored by a per-channel two-variable non-negative least squares, all from small Gram matrices:
with Z = [T_blk | g], the sky term is Z u_c (u_c = block means of f_c and the ground term), and

    |a|^2 = u^T (Z^T Z) u,  a.b = u^T (Z^T C_w + (Z^T Z) e_g s_w),  a.y = u^T Z^T y, ...

where C = the exact columns of the candidate texels (C_w = T[:, w] / dOmega_w). The data are
pixel-weighted by 1 / (mean shading + its median) so that dark, shadowed pixels -- where the sun's
direction shows -- count as much as bright ones. The search visits ~650 directions x sky shapes
in a few tens of milliseconds and returns the best, mutually distant, candidates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from f2l.lighting.grid import LatLongGrid

LATTICE_STEP = 2  # candidate suns on every 2nd texel row; columns thinned to keep ~equal spacing
MAX_SEARCH_PIXELS = 1024


@dataclass
class SunCandidate:
    """One scored candidate: sun texel and direction, sky shape index, per-channel psi, residual."""

    texel: int
    elevation_rad: float
    azimuth_rad: float
    shape: int
    psi_sky: np.ndarray  # (3,)
    psi_sun: np.ndarray  # (3,)
    residual: float


def candidate_texels(grid: LatLongGrid, elevation_range_rad: tuple[float, float] | None = None) -> np.ndarray:
    """Flat indices of sky texels on a lattice of about ``LATTICE_STEP`` texels spacing.

    Rows LATTICE_STEP/2, LATTICE_STEP/2 + LATTICE_STEP, ...; per row max(4, W sin(phi) / step)
    evenly spaced columns (so the spacing in angle is about the same near the zenith).
    ``elevation_range_rad`` keeps only rows whose centre elevation lies inside it (with at least
    the row nearest to its middle, so a narrow range still has candidates).
    """
    rows = np.arange(LATTICE_STEP // 2, grid.sky_rows, LATTICE_STEP)
    if elevation_range_rad is not None:
        lo, hi = elevation_range_rad
        elevation = 0.5 * math.pi - grid.phi_rad[rows]
        keep = (elevation >= lo) & (elevation <= hi)
        if not keep.any():
            keep = np.abs(elevation - 0.5 * (lo + hi)) == np.abs(elevation - 0.5 * (lo + hi)).min()
        rows = rows[keep]
    out = []
    for r in rows:
        n = int(max(4, round(grid.width * math.sin(grid.phi_rad[r]) / LATTICE_STEP)))
        cols = np.round((np.arange(n) + 0.5) * grid.width / n - 0.5).astype(np.int64) % grid.width
        out.append(r * grid.width + np.unique(cols))
    return np.concatenate(out)


def _nnls2(h11, h12, h22, b1, b2):
    """Vectorised min_{x >= 0} x^T H x - 2 x^T b for 2 x 2 H: returns (x1, x2, value)."""
    det = h11 * h22 - h12 * h12
    safe = np.where(np.abs(det) > 1e-300, det, 1.0)
    x1 = (h22 * b1 - h12 * b2) / safe
    x2 = (h11 * b2 - h12 * b1) / safe
    ok = (det > 1e-14 * h11 * h22) & (x1 >= 0) & (x2 >= 0)
    opts = [
        (np.where(ok, x1, 0.0), np.where(ok, x2, 0.0), ok),
        (np.maximum(b1, 0) / np.maximum(h11, 1e-300), np.zeros_like(b1), np.ones_like(ok)),
        (np.zeros_like(b2), np.maximum(b2, 0) / np.maximum(h22, 1e-300), np.ones_like(ok)),
    ]
    best = None
    for a, b, valid in opts:
        val = h11 * a * a + 2 * h12 * a * b + h22 * b * b - 2 * (a * b1 + b * b2)
        val = np.where(valid, val, np.inf)
        if best is None:
            best = (a, b, val)
        else:
            better = val < best[2]
            best = tuple(np.where(better, new, old) for new, old in zip((a, b, val), best))
    return best


@dataclass
class SearchScores:
    """Every candidate's score (module docstring): the candidate ``texels`` (k,), per texel x sky
    shape the best non-negative per-channel psi_sky and psi_sun (k, S, 3) and their weighted
    squared residual ``total`` (k, S); the same skies without a sun (``sky_psi``, ``sky_total``);
    ``yy`` the weighted squared norm of the observation (the residual of predicting zero)."""

    texels: np.ndarray
    psi_sky: np.ndarray
    psi_sun: np.ndarray
    total: np.ndarray
    sky_psi: np.ndarray
    sky_total: np.ndarray
    yy: float


def _weighted_rows(t_blk, g, y):
    """The search's pixel rows (at most MAX_SEARCH_PIXELS, evenly strided) and their weights
    1 / (mean shading + its median): dark, shadowed pixels count as much as bright ones."""
    stride = max(1, int(math.ceil(len(y) / MAX_SEARCH_PIXELS)))
    rows = slice(None, None, stride)
    yy = y[rows]
    wts = 1.0 / (yy.mean(1) + np.median(yy.mean(1)) + 1e-12)
    Z = np.concatenate([t_blk[rows], g[rows, None]], axis=1)  # (n', nb + 1)
    return rows, wts, Z * wts[:, None], yy * wts[:, None]


def _sky_coefficients(sky_blocks: np.ndarray, e_blocks: np.ndarray, rg: float) -> np.ndarray:
    """u[..., c, :] = [block means of the unit sky f_c, (rho_g / pi) E_h(f_c)]: the coefficients
    of Z = [T_blk | g] that give its shading; ``sky_blocks`` (..., nb, 3)."""
    sky_t = np.swapaxes(sky_blocks, -1, -2)  # (..., 3, nb)
    return np.concatenate([sky_t, rg * (sky_t @ e_blocks)[..., None]], axis=-1)


def score(t_blk: np.ndarray, g: np.ndarray, columns, y: np.ndarray, grid: LatLongGrid,
          texels: np.ndarray, sky_blocks: np.ndarray, e_blocks: np.ndarray, ground_albedo: float) -> SearchScores:
    """Score every candidate texel x sky shape (module docstring).

    t_blk (N, nb) block transport, g (N,) ground row sums, ``columns(texels) -> (N, k)`` exact T
    columns, y (N, 3) observed shading, ``texels`` (k,) candidate sun texels, sky_blocks
    (k, S, nb, 3) unit-weight sky block means for each candidate and shape, e_blocks (nb,)
    horizontal-irradiance weights of the block means (E_h = e_blocks . m).
    """
    rows, wts, Zw, yw = _weighted_rows(t_blk, g, y)
    C = columns(texels, rows=rows) / grid.solid_angles_flat[texels][None, :]  # point sun, unit irradiance
    Cw = C * wts[:, None]
    G_zz, G_zc, c_sq = Zw.T @ Zw, Zw.T @ Cw, (Cw * Cw).sum(0)
    zy, cy = Zw.T @ yw, Cw.T @ yw  # (nb + 1, 3), (k, 3)
    rg = ground_albedo / math.pi
    sin_el = grid.directions_flat[texels, 1]
    s = rg * sin_el  # ground bounce of the unit sun
    u = _sky_coefficients(sky_blocks, e_blocks, rg)  # (k, S, 3, nb + 1)
    h11 = np.einsum("ksci,ksci->ksc", u, u @ G_zz)
    cross = G_zc.T + s[:, None] * G_zz[-1][None, :]  # (k, nb + 1): Z^T b per candidate
    h12 = np.einsum("ksci,ki->ksc", u, cross)
    h22 = np.broadcast_to((c_sq + 2 * s * G_zc[-1] + s * s * G_zz[-1, -1])[:, None, None], h11.shape)
    b1 = np.einsum("ksci,ic->ksc", u, zy)
    b2 = np.broadcast_to((cy + s[:, None] * zy[-1][None, :])[:, None, :], h11.shape)
    x1, x2, val = _nnls2(h11, h12, h22, b1, b2)
    yy_sum = float((yw * yw).sum())
    total = val.sum(-1) + yy_sum  # (k, S) weighted squared residual
    sky_x = np.maximum(b1, 0.0) / np.maximum(h11, 1e-300)  # the same skies without a sun
    sky_total = (-sky_x * np.maximum(b1, 0.0)).sum(-1) + yy_sum
    return SearchScores(np.asarray(texels), x1, x2, total, sky_x, sky_total, yy_sum)


def pick(scores: SearchScores, grid: LatLongGrid, keep: int = 256) -> list[SunCandidate]:
    """The best ``keep`` candidates sorted by residual, then the best sun-less candidate."""
    S = scores.total.shape[1]
    order = np.argsort(scores.total, axis=None)[:keep]
    out = [_candidate(grid, scores.texels, flat, S, scores.psi_sky, scores.psi_sun, scores.total) for flat in order]
    best_sky = int(np.argmin(scores.sky_total))
    out.append(_candidate(grid, scores.texels, best_sky, S, scores.sky_psi, np.zeros_like(scores.psi_sun),
                          scores.sky_total))
    return out


def search(t_blk: np.ndarray, g: np.ndarray, columns, y: np.ndarray, grid: LatLongGrid,
           texels: np.ndarray, sky_blocks: np.ndarray, e_blocks: np.ndarray, ground_albedo: float,
           keep: int = 256) -> list[SunCandidate]:
    """Score every candidate texel x sky shape (:func:`score`); returns the best ``keep`` sorted
    by residual, then the best sun-less candidate (:func:`pick`)."""
    return pick(score(t_blk, g, columns, y, grid, texels, sky_blocks, e_blocks, ground_albedo), grid, keep)


def combine(scores: list[SearchScores], weights: np.ndarray) -> SearchScores:
    """One light for several faces: each candidate scored by the weighted sum of the faces'
    relative residuals (total / yy), with the faces' psi averaged with the same weights. Each
    face keeps its own psi per candidate here (a relaxation of one shared light: its scale is the
    face's albedo and exposure); the joint fit then ties them (f2l.estimate.joint)."""
    w = np.asarray(weights, np.float64)
    w = w / w.sum()
    total = sum(wi * s.total / max(s.yy, 1e-300) for wi, s in zip(w, scores))
    sky_total = sum(wi * s.sky_total / max(s.yy, 1e-300) for wi, s in zip(w, scores))
    mean = lambda name: sum(wi * getattr(s, name) for wi, s in zip(w, scores))  # noqa: E731
    return SearchScores(scores[0].texels, mean("psi_sky"), mean("psi_sun"), total, mean("sky_psi"), sky_total, 1.0)


def relative_residual(t_blk: np.ndarray, g: np.ndarray, columns, y: np.ndarray, grid: LatLongGrid, sun_texel: int,
                      sky_block_means: np.ndarray, e_blocks: np.ndarray, ground_albedo: float,
                      w_sky: np.ndarray, w_sun: np.ndarray) -> float:
    """How well one given light explains a face, in the search's metric: the weighted squared
    residual of the shading of w_sky ⊙ f + w_sun ⊙ (a point sun at ``sun_texel``), with one free
    non-negative scale per channel (the face's albedo and exposure), over the observation's
    weighted squared norm. ``sky_block_means`` (nb, 3) the unit sky f's block means."""
    rows, wts, Zw, yw = _weighted_rows(t_blk, g, y)
    c = columns(np.asarray([sun_texel]), rows=rows)[:, 0] / grid.solid_angles_flat[sun_texel]
    rg = ground_albedo / math.pi
    b = (c + rg * grid.directions_flat[sun_texel, 1] * g[rows]) * wts  # the unit sun's weighted shading
    u = _sky_coefficients(sky_block_means, e_blocks, rg)  # (3, nb + 1)
    pred = (Zw @ u.T) * np.asarray(w_sky)[None, :] + b[:, None] * np.asarray(w_sun)[None, :]  # (n', 3)
    pp, py = (pred * pred).sum(0), (pred * yw).sum(0)
    k = np.maximum(py, 0.0) / np.maximum(pp, 1e-300)
    resid = yw - k[None, :] * pred
    return float((resid * resid).sum() / max(float((yw * yw).sum()), 1e-300))


def sun_seen(t_blk: np.ndarray, g: np.ndarray, columns, y: np.ndarray, grid: LatLongGrid, sun_texel: int,
             sky_block_means: np.ndarray, e_blocks: np.ndarray, ground_albedo: float,
             w_sky: np.ndarray, w_sun: np.ndarray) -> tuple[float, float]:
    """How much of a given light's sun a face shows, in the search's metric: (seen, share).

    The face's shading is fitted as a_c (sky part) + b_c (sun part) of the light w_sky ⊙ f + w_sun ⊙
    (a point sun at ``sun_texel``), with a free non-negative scale for each part and channel
    (``_nnls2``); ``seen`` is the luminance-weighted mean of b_c / a_c (1: the face is lit as the
    light says, 0: it shows the sky's light and none of the sun's, as a face in an occluder's
    shadow). ``share`` is the sun part's share of the light's predicted shading (luminance): where
    it is small the face cannot tell. ``sky_block_means`` (nb, 3) the unit sky f's block means."""
    rows, wts, Zw, yw = _weighted_rows(t_blk, g, y)
    c = columns(np.asarray([sun_texel]), rows=rows)[:, 0] / grid.solid_angles_flat[sun_texel]
    rg = ground_albedo / math.pi
    b = (c + rg * grid.directions_flat[sun_texel, 1] * g[rows]) * wts
    u = _sky_coefficients(sky_block_means, e_blocks, rg)  # (3, nb + 1)
    sky = (Zw @ u.T) * np.asarray(w_sky)[None, :]  # (n', 3)
    sun = b[:, None] * np.asarray(w_sun)[None, :]
    lum = np.array([0.2126, 0.7152, 0.0722])
    share = float((sun.sum(0) @ lum) / max(float((sky + sun).sum(0) @ lum), 1e-300))
    x1, x2, _ = _nnls2((sky * sky).sum(0), (sky * sun).sum(0), (sun * sun).sum(0), (sky * yw).sum(0),
                       (sun * yw).sum(0))
    ratio = np.where(x1 > 1e-300, x2 / np.maximum(x1, 1e-300), np.where(x2 > 0, np.inf, 1.0))
    return float(np.clip(ratio, 0.0, 10.0) @ lum), share


def _candidate(grid, texels, flat, S, x1, x2, total) -> SunCandidate:
    i, j = divmod(int(flat), S)
    d = grid.directions_flat[texels[i]]
    return SunCandidate(
        texel=int(texels[i]), elevation_rad=math.asin(float(np.clip(d[1], -1, 1))),
        azimuth_rad=math.atan2(float(d[0]), float(-d[2])), shape=j,
        psi_sky=x1[i, j], psi_sun=x2[i, j], residual=float(total[i, j]))


def distinct(candidates: list[SunCandidate], count: int, min_separation_deg: float = 25.0) -> list[SunCandidate]:
    """The best ``count`` candidates whose suns are pairwise at least ``min_separation_deg`` apart."""
    from f2l.lighting.grid import direction_from_angles

    picked, dirs = [], []
    cos_min = math.cos(math.radians(min_separation_deg))
    for c in candidates:
        d = direction_from_angles(c.elevation_rad, c.azimuth_rad)
        if all(float(d @ e) < cos_min for e in dirs):
            picked.append(c)
            dirs.append(d)
            if len(picked) == count:
                break
    return picked
