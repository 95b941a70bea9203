"""Sphere assembly: HDR views (linear float32 RGB) <-> lat-long probes in the DESIGN convention.

A camera is any mapping with the interface of :class:`~f2l.capture.cameras.ViewCamera` /
:class:`~f2l.capture.cameras.MirrorBallCamera`: ``width``, ``height``, ``rotation``
(world_from_camera), ``cam_direction_to_pixel``, ``pixel_to_cam_direction``, ``blend_weight``,
``pixel_angle_rad``, ``radiance_gain`` (image = gain * radiance) and ``with_rotation``.
Pixel coordinates follow COLMAP (pixel (i, j) spans [j, j+1] x [i, i+1]).

- :func:`render_view` averages s x s subpixel rays per pixel over the probe (piecewise constant
  per texel), so a sun of a few texels keeps its energy.
- :func:`assemble` splats every view into the grid: the view is reduced to weighted 2^L x 2^L
  pixel boxes (about half a texel across; views coarser than the grid are split into s x s
  bilinear sub-pixels instead), each carrying its solid angle Omega = |dd/dx x dd/dy| x pixel
  area x weight to the texel containing its direction. Per view and texel L_v = sum(Omega I) /
  sum(Omega) -- the exact area average, so the sun keeps its energy at any view resolution -- and
  W_v = sum(Omega b) / texel solid angle, b = ``blend_weight`` (1 at the view centre, 0 at the
  edge of its valid region). Views are blended as sum(W_v L_v) / sum(W_v). Pixels outside a
  camera's valid region (fisheye image circle, mirror-ball silhouette) or of weight 0 never count.
  A view whose splats in a texel include a saturated pixel only gives a lower bound there: lower
  bounds are never averaged with measurements; a texel with lower bounds only keeps their
  maximum and is flagged ``saturated``. Directions no view sees are 0 and False in ``coverage``.
- :func:`refine_rotations` fixes one view and solves for small world-frame rotations of the
  others minimising robust log-luminance differences at shared directions (scipy least_squares,
  coarse-to-fine Gaussian blur).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from scipy.ndimage import gaussian_filter, uniform_filter1d
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from f2l.capture.cameras import MirrorBallCamera, ViewCamera, mirror_ball_view
from f2l.lighting.grid import LatLongGrid

__all__ = [
    "View", "ViewStats", "AssembledProbe", "RotationRefinement", "render_view", "assemble",
    "refine_rotations", "mirror_ball_view", "ViewCamera", "MirrorBallCamera",
]  # fmt: skip

_LUMA = np.array([0.2126, 0.7152, 0.0722])
_CHUNK_SAMPLES = 1 << 19


@dataclass(frozen=True, eq=False)
class View:
    """One HDR view: ``image`` (h, w, 3) linear radiance, its ``camera``, an optional per-pixel
    ``weight`` (h, w) in [0, 1] (0 = unusable, e.g. outside the image circle) and an optional
    ``saturated`` (h, w) bool mask (the merged value is only a lower bound there)."""

    image: np.ndarray
    camera: Any
    weight: np.ndarray | None = None
    saturated: np.ndarray | None = None
    name: str = ""


@dataclass(frozen=True)
class ViewStats:
    """Per-view diagnostics of an assembly (solid angles in steradians)."""

    name: str
    covered_texels: int
    covered_solid_angle_sr: float
    saturated_texels: int
    weight_share: float  # solid-angle-weighted share of this view in the blend weights
    median_ratio_to_blend: float  # median Y(view) / Y(blend) where another view also measured; NaN if none
    pyramid_level: int  # splats are 2^level x 2^level pixel boxes
    subsamples: int  # or s x s sub-pixel splats per pixel (views coarser than the grid)


@dataclass(frozen=True, eq=False)
class AssembledProbe:
    radiance: np.ndarray  # (H, W, 3) float32; 0 where not covered
    coverage: np.ndarray  # (H, W) bool: some view saw the texel
    saturated: np.ndarray  # (H, W) bool: only saturated pixels saw it; radiance is a lower bound
    weight_sum: np.ndarray  # (H, W) float32: sum of blend weights of the measurements
    view_stats: tuple[ViewStats, ...]
    grid: LatLongGrid


@dataclass(frozen=True, eq=False)
class RotationRefinement:
    views: tuple[View, ...]  # the input views with refined cameras
    correction_rotvec_rad: np.ndarray  # (n, 3): refined world_from_camera = exp([r]x) @ original
    initial_cost: float
    final_cost: float
    n_directions: int  # sample directions seen by at least two views
    success: bool


# -- sampling helpers -----------------------------------------------------------------------
def _bilinear(image: np.ndarray, weight: np.ndarray, saturated: np.ndarray | None, px: np.ndarray):
    """Weighted bilinear lookup at COLMAP pixel coords px (N, 2) (finite). Returns value (N, C)
    = sum(b w I) / sum(b w), wsum (N,) = sum(b w), sat (N,) = any contributing tap saturated."""
    h, w = weight.shape
    fx, fy = px[:, 0] - 0.5, px[:, 1] - 0.5
    x0, y0 = np.floor(fx), np.floor(fy)
    tx, ty = fx - x0, fy - y0
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    flat = image.reshape(h * w, -1)
    wflat, sflat = weight.reshape(-1), None if saturated is None else saturated.reshape(-1)
    acc = np.zeros((len(px), flat.shape[1]))
    wsum = np.zeros(len(px))
    sat = np.zeros(len(px), dtype=bool)
    for dy, by in ((0, 1.0 - ty), (1, ty)):
        yi = np.clip(y0 + dy, 0, h - 1)
        for dx, bx in ((0, 1.0 - tx), (1, tx)):
            idx = yi * w + np.clip(x0 + dx, 0, w - 1)
            b = by * bx * wflat[idx]
            acc += b[:, None] * flat[idx]
            wsum += b
            if sflat is not None:
                sat |= (b > 0) & sflat[idx]
    with np.errstate(invalid="ignore", divide="ignore"):
        value = np.where(wsum[:, None] > 0, acc / wsum[:, None], 0.0)
    return value, wsum, sat


def _lens_mask(camera) -> np.ndarray:
    """(h, w) bool: pixels whose centre maps to a valid direction (e.g. inside a fisheye's image
    circle or a mirror ball's silhouette); other pixels never contribute to an assembly."""
    h, w = camera.height, camera.width
    mask = np.zeros((h, w), dtype=bool)
    step = max(1, _CHUNK_SAMPLES // w)
    x = np.arange(w) + 0.5
    for r0 in range(0, h, step):
        y = np.arange(r0, min(h, r0 + step)) + 0.5
        px = np.stack(np.broadcast_arrays(x[None, :], y[:, None]), axis=-1).reshape(-1, 2)
        mask[r0 : r0 + len(y)] = camera.pixel_to_cam_direction(px)[1].reshape(len(y), w)
    return mask


def _as_view(item, index: int) -> View:
    v = item if isinstance(item, View) else View(*item)
    name = v.name or f"#{index}"
    label = f"view {index} ({name!r})"
    img = np.asarray(v.image)
    cam = v.camera
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"{label}: image must be (h, w, 3), got shape {img.shape}")
    if img.shape[:2] != (cam.height, cam.width):
        raise ValueError(f"{label}: image is {img.shape[1]}x{img.shape[0]} but its camera is {cam.width}x{cam.height}")
    img = np.ascontiguousarray(img, dtype=np.float32)
    if not np.all(np.isfinite(img)):
        raise ValueError(f"{label}: image has NaN or infinite values")
    weight = np.ones(img.shape[:2], np.float32) if v.weight is None else np.asarray(v.weight, np.float32)
    if weight.shape != img.shape[:2] or not np.all(np.isfinite(weight)) or weight.min() < 0:
        raise ValueError(f"{label}: weight must be a finite, non-negative (h, w) array matching the image")
    weight = weight * _lens_mask(cam)
    sat = None if v.saturated is None else np.asarray(v.saturated, dtype=bool)
    if sat is not None and sat.shape != img.shape[:2]:
        raise ValueError(f"{label}: saturated mask shape {sat.shape} does not match the image {img.shape[:2]}")
    return View(img, cam, weight, sat, name)


# -- rendering -------------------------------------------------------------------------------
def render_view(probe_latlong: np.ndarray, camera, supersample: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Sample an HDR lat-long probe (H, W, 3) into ``camera``'s image.

    Each pixel averages ``supersample`` x ``supersample`` stratified subpixel rays over the probe
    (piecewise constant per texel) and is multiplied by ``camera.radiance_gain``. Returns
    (image (h, w, 3) float32, valid (h, w) bool): a pixel averages its valid rays and is valid when
    at least half of them are (pixels with none are 0).
    """
    probe = np.asarray(probe_latlong)
    if probe.ndim != 3 or probe.shape[2] != 3:
        raise ValueError(f"probe must be (H, W, 3), got shape {probe.shape}")
    if not np.all(np.isfinite(probe)):
        raise ValueError("probe has NaN or infinite values")
    grid = LatLongGrid(probe.shape[0], probe.shape[1])
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    h, w = camera.height, camera.width
    off = (np.arange(s) + 0.5) / s
    image = np.zeros((h, w, 3), np.float32)
    count = np.zeros((h, w), np.int64)
    step = max(1, _CHUNK_SAMPLES // (w * s * s))
    for r0 in range(0, h, step):
        r1 = min(h, r0 + step)
        ys = np.arange(r0, r1)[:, None, None, None] + off[None, None, :, None]
        xs = np.arange(w)[None, :, None, None] + off[None, None, None, :]
        px = np.stack(np.broadcast_arrays(xs, ys), axis=-1).reshape(-1, 2)
        d, valid = camera.pixel_to_direction(px)
        vals = np.zeros((len(px), 3))
        row, col = grid.direction_to_texel(d[valid])
        vals[valid] = probe[row, col]
        vals = vals.reshape(r1 - r0, w, s * s, 3)
        n_valid = valid.reshape(r1 - r0, w, s * s).sum(-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(n_valid[..., None] > 0, vals.sum(2) / n_valid[..., None], 0.0)
        image[r0:r1] = mean * camera.radiance_gain
        count[r0:r1] = n_valid
    return image, count * 2 >= s * s


# -- assembly --------------------------------------------------------------------------------
def _splat_plan(camera, grid: LatLongGrid, max_sub: int) -> tuple[int, int, float]:
    """(pyramid level L, sub-splats per axis s, splat spacing in rad) so that splats are about
    half a texel high: from the median angular pixel pitch p over the texels the view sees,
    2^L = largest power of two with p 2^L <= pi / (2 H), else L = 0 and s = ceil(p / that)."""
    px = camera.direction_to_pixel(grid.directions_flat)[0].reshape(*grid.shape, 2)
    d = grid.directions
    pitches = []
    for pa, pb, da, db in ((px[1:], px[:-1], d[1:], d[:-1]),
                           (px, np.roll(px, 1, axis=1), d, np.roll(d, 1, axis=1))):
        with np.errstate(invalid="ignore"):
            dist = np.linalg.norm(pa - pb, axis=-1)
        ok = np.isfinite(dist) & (dist > 0)
        pitches.append(np.arccos(np.clip(np.sum(da * db, axis=-1), -1.0, 1.0))[ok] / dist[ok])
    pitch = np.concatenate(pitches)
    target = math.pi / grid.height / 2.0
    if pitch.size == 0:
        return 0, 1, target
    p = float(np.median(pitch))
    if p <= target:
        level = min(int(math.floor(math.log2(target / p))), int(math.log2(min(camera.width, camera.height))))
        return level, 1, p * 2.0**level
    sub = min(max_sub, math.ceil(p / target))
    return 0, sub, p / sub


def _jacobian(camera, pos: np.ndarray, d0: np.ndarray, eps: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame dd/dx, dd/dy (N, 3) per pixel at ``pos`` (central differences, one-sided next
    to the edge of the valid region; NaN where undefined)."""
    jac = []
    for axis in (0, 1):
        off = np.zeros(2)
        off[axis] = eps
        dp, okp = camera.pixel_to_cam_direction(pos + off)
        dm, okm = camera.pixel_to_cam_direction(pos - off)
        j = np.where(okp[:, None], dp - d0, d0 - dm) / eps
        jac.append(np.where((okp & okm)[:, None], (dp - dm) / (2 * eps), j))
    return jac[0], jac[1]


def _splats(v: View, level: int, sub: int):
    """Splat positions (N, 2), values (N, 3), pixel areas x weight (N,), saturated (N,): the
    weighted 2^L x 2^L box means at their weighted centroids (sub = 1), or s x s bilinear
    sub-pixel samples of the view (level 0)."""
    img, wt = v.image.astype(np.float64), v.weight.astype(np.float64)
    h, w = wt.shape
    if sub > 1:
        off = (np.arange(sub) + 0.5) / sub
        rows, cols = np.nonzero(wt > 0)
        pos = np.stack([(cols[:, None, None] + off[None, None, :]), (rows[:, None, None] + off[None, :, None])],
                       axis=-1).reshape(-1, 2)
        val, _, sat = _bilinear(img, wt, v.saturated, pos)
        return pos, val, np.repeat(wt[rows, cols] / sub**2, sub * sub), sat
    b = 2**level
    pad = ((0, -h % b), (0, -w % b))
    blocks = lambda a: np.pad(a, pad + ((0, 0),) * (a.ndim - 2)).reshape(
        (h - 1) // b + 1, b, (w - 1) // b + 1, b, *a.shape[2:]).sum(axis=(1, 3))
    mass = blocks(wt)
    keep = mass > 0
    yc, xc = np.mgrid[0:h, 0:w] + 0.5
    m = mass[keep]
    pos = np.stack([blocks(wt * xc)[keep] / m, blocks(wt * yc)[keep] / m], axis=1)
    val = blocks(img * wt[..., None])[keep] / m[:, None]
    sat = np.zeros(len(m), bool) if v.saturated is None else blocks((v.saturated & (wt > 0)).astype(np.int64))[keep] > 0
    return pos, val, m, sat


def _visible_texels(v: View, grid: LatLongGrid, n: int = 3) -> np.ndarray:
    """(L,) bool: some of n x n sub-directions of the texel project to a usable pixel of the view."""
    i = (np.arange(n) + 0.5) / n
    phi = grid.phi_edges_rad[:-1, None] + (np.pi / grid.height) * i[None, :]
    theta = grid.theta_edges_rad[:-1, None] + (2 * np.pi / grid.width) * i[None, :]
    ph, th = phi[:, None, :, None], theta[None, :, None, :]
    d = np.stack(np.broadcast_arrays(np.sin(ph) * np.sin(th), np.cos(ph), -np.sin(ph) * np.cos(th)), axis=-1)
    px, ok = v.camera.direction_to_pixel(d.reshape(-1, 3))
    cols = np.clip(np.nan_to_num(px[:, 0]).astype(np.int64), 0, v.camera.width - 1)
    rows = np.clip(np.nan_to_num(px[:, 1]).astype(np.int64), 0, v.camera.height - 1)
    ok &= v.weight[rows, cols] > 0
    return ok.reshape(grid.size, n * n).any(axis=1)


def _overlaps(lo: np.ndarray, hi: np.ndarray, edges: np.ndarray, start: np.ndarray, span: int, periodic: bool):
    """Cell indices (N, span) and 1-D overlap lengths of intervals [lo, hi] with cells
    [edges[c], edges[c+1]] for c = start .. start + span - 1 (wrapped if periodic)."""
    n_cells = len(edges) - 1
    c = start[:, None] + np.arange(span)[None, :]
    if periodic:
        width = edges[-1] - edges[0]
        turns, cc = np.divmod(c, n_cells)
        e0 = edges[cc] + turns * width
        e1 = edges[cc + 1] + turns * width
    else:
        cc = np.clip(c, 0, n_cells - 1)
        e0, e1 = edges[cc], edges[cc + 1]
        e1 = np.where(c == cc, e1, e0)  # cells past the last edge have zero length
    return cc, np.clip(np.minimum(hi[:, None], e1) - np.maximum(lo[:, None], e0), 0.0, None)


def _accumulate(v: View, grid: LatLongGrid, level: int, sub: int):
    """Per-texel sums of one view: energy (L, 3) = sum(f Omega I), mass (L,) = sum(f Omega), blend
    (L,) = sum(f Omega b), saturated (L,) bool, and its visible-texel mask.

    A splat (solid angle Omega = |dd/dx x dd/dy| x pixel area x weight) is an axis-aligned box in
    the equal-area coordinates (theta, mu = cos phi), where texels are boxes too: its extents are
    the RMS extents of its Jacobian footprint scaled to area Omega, and f are its exact overlap
    fractions with the texels the view sees (renormalised to 1), so energy is kept exactly."""
    cam, size, H, W = v.camera, grid.size, grid.height, grid.width
    visible = _visible_texels(v, grid)
    energy, mass, blend, sat_n = np.zeros((size, 3)), np.zeros(size), np.zeros(size), np.zeros(size)
    pos, val, area, sat = _splats(v, level, sub)
    side_px = 2.0**level / sub
    t_edges = -np.cos(grid.phi_edges_rad)  # t = -mu increases with the row index
    c_edges = grid.theta_edges_rad
    for c0 in range(0, len(pos), _CHUNK_SAMPLES // 8):
        sl = slice(c0, c0 + _CHUNK_SAMPLES // 8)
        p, value, ar, st = pos[sl], val[sl], area[sl], sat[sl]
        d, ok = cam.pixel_to_cam_direction(p)
        jx, jy = _jacobian(cam, p, d)
        rot = cam.rotation
        dw, jx, jy = d @ rot.T, jx @ rot.T, jy @ rot.T
        omega = np.nan_to_num(np.linalg.norm(np.cross(jx, jy), axis=1)) * ar
        ok &= omega > 0
        dw, jx, jy, omega, p, value, st = dw[ok], jx[ok], jy[ok], omega[ok], p[ok], value[ok], st[ok]
        x, y, z = dw.T
        rho2 = np.maximum(x * x + z * z, 1e-12)
        th_x, th_y = (-z * jx[:, 0] + x * jx[:, 2]) / rho2, (-z * jy[:, 0] + x * jy[:, 2]) / rho2
        ext_th = side_px * np.hypot(th_x, th_y)
        ext_t = side_px * np.hypot(jx[:, 1], jy[:, 1])
        k = np.sqrt(omega / ar[ok] * side_px**2 / np.maximum(ext_th * ext_t, 1e-300))
        ext_th, ext_t = np.minimum(k * ext_th, 2 * np.pi), np.minimum(k * ext_t, 2.0)
        th_c, t_c = np.arctan2(x, -z), -y
        t_lo, t_hi = t_c - ext_t / 2, t_c + ext_t / 2
        r_start = np.clip(np.searchsorted(t_edges, t_lo, side="right") - 1, 0, H - 1)
        th_lo, th_hi = th_c - ext_th / 2, th_c + ext_th / 2
        c_start = np.floor((th_lo - c_edges[0]) / (2 * np.pi / W)).astype(np.int64)
        n_rows = int(np.max(np.searchsorted(t_edges, t_hi, side="left") - r_start, initial=1)) + 1
        rows, f_r = _overlaps(t_lo, t_hi, t_edges, r_start, min(n_rows, H), periodic=False)
        c_span = np.ceil(ext_th / (2 * np.pi / W)).astype(np.int64) + 1
        for span in np.unique(np.minimum(2 ** np.ceil(np.log2(c_span)).astype(np.int64), W + 1)):
            g = np.flatnonzero(np.minimum(2 ** np.ceil(np.log2(c_span)).astype(np.int64), W + 1) == span)
            cols, f_c = _overlaps(th_lo[g], th_hi[g], c_edges, c_start[g], int(span), periodic=True)
            idx = (rows[g][:, :, None] * W + cols[:, None, :]).reshape(len(g), -1)
            f = (f_r[g][:, :, None] * f_c[:, None, :]).reshape(len(g), -1) * visible[idx]
            tot = f.sum(1)
            keep = tot > 0
            wgt = (f[keep] / tot[keep, None]) * omega[g][keep, None]
            ii = idx[keep].ravel()
            for ch in range(3):
                energy[:, ch] += np.bincount(ii, (wgt * value[g][keep, ch, None]).ravel(), size)
            mass += np.bincount(ii, wgt.ravel(), size)
            b = cam.blend_weight(d[ok][g][keep], p[g][keep])
            blend += np.bincount(ii, (wgt * b[:, None]).ravel(), size)
            sat_n += np.bincount(ii, (wgt * st[g][keep, None]).ravel(), size)
    return energy, mass, blend, sat_n > 0, visible


def assemble(views: Sequence, grid_height: int = 64, grid_width: int = 128, max_subsamples: int = 8) -> AssembledProbe:
    """Blend HDR ``views`` (:class:`View` or tuples (image, camera[, weight[, saturated]])) into a
    (grid_height, grid_width) lat-long probe; see the module docstring for the rules.
    ``max_subsamples`` caps the sub-pixel splats per axis for views coarser than the grid.
    Raises ValueError naming the view for NaN/inf or mismatched inputs."""
    vs = [_as_view(v, i) for i, v in enumerate(views)]
    if not vs:
        raise ValueError("assemble needs at least one view")
    grid = LatLongGrid(grid_height, grid_width)
    size, nv = grid.size, len(vs)
    texel_sr = grid.solid_angles_flat
    num, den = np.zeros((size, 3)), np.zeros(size)
    lower = np.full((size, 3), -np.inf)
    view_y = np.full((nv, size), np.nan)  # luminance of each view's measurement per texel
    view_w = np.zeros((nv, size))
    view_sat = np.zeros((nv, size), dtype=bool)
    plans = []
    for k, v in enumerate(vs):
        level, sub, _ = _splat_plan(v.camera, grid, int(max_subsamples))
        plans.append((level, sub))
        energy, mass, blend, sat, visible = _accumulate(v, grid, level, sub)
        covered = visible & (mass > 0) & (blend > 0)
        lv = energy[covered] / mass[covered, None] / v.camera.radiance_gain
        wv = blend[covered] / texel_sr[covered]
        st = sat[covered]
        idx = np.flatnonzero(covered)
        num[idx[~st]] += wv[~st, None] * lv[~st]
        den[idx[~st]] += wv[~st]
        lower[idx[st]] = np.maximum(lower[idx[st]], lv[st])
        view_y[k, idx[~st]] = lv[~st] @ _LUMA
        view_w[k, idx] = wv
        view_sat[k, idx] = st
    measured = den > 0
    saturated = ~measured & np.isfinite(lower).all(1)
    radiance = np.zeros((size, 3))
    radiance[measured] = num[measured] / den[measured, None]
    radiance[saturated] = lower[saturated]
    stats = _view_stats(vs, grid, plans, radiance @ _LUMA, measured, view_y, view_w, view_sat)
    shape = grid.shape
    return AssembledProbe(
        radiance=radiance.reshape(*shape, 3).astype(np.float32),
        coverage=(measured | saturated).reshape(shape),
        saturated=saturated.reshape(shape),
        weight_sum=den.reshape(shape).astype(np.float32),
        view_stats=stats, grid=grid,
    )


def _view_stats(vs, grid, plans, blend_y, measured, view_y, view_w, view_sat) -> tuple[ViewStats, ...]:
    sa = grid.solid_angles_flat
    total_w = float(np.sum(view_w * sa)) or 1.0
    n_meas = np.isfinite(view_y).sum(0)
    out = []
    for k, v in enumerate(vs):
        cov = view_w[k] > 0
        shared = np.isfinite(view_y[k]) & (n_meas >= 2) & measured & (blend_y > 0)
        ratio = float(np.median(view_y[k][shared] / blend_y[shared])) if shared.any() else float("nan")
        out.append(ViewStats(
            name=v.name, covered_texels=int(cov.sum()), covered_solid_angle_sr=float(sa[cov].sum()),
            saturated_texels=int(view_sat[k].sum()), weight_share=float(np.sum(view_w[k] * sa) / total_w),
            median_ratio_to_blend=ratio, pyramid_level=plans[k][0], subsamples=plans[k][1],
        ))
    return tuple(out)


# -- rotation refinement -----------------------------------------------------------------------
def _fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    y = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - y * y)
    a = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.sin(a), y, -r * np.cos(a)], axis=1)


def _log_luminance(v: View, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Blurred log luminance (normalised convolution over usable, unsaturated pixels) and its mask."""
    y = v.image.astype(np.float64) @ _LUMA
    m = (v.weight > 0) & (y > 0)
    if v.saturated is not None:
        m &= ~v.saturated
    floor = 1e-3 * float(np.median(y[m])) if m.any() else 1e-12
    g = np.log(np.maximum(y, floor)) * m
    if sigma_px > 0:
        mb = gaussian_filter(m.astype(np.float64), sigma_px)
        with np.errstate(invalid="ignore", divide="ignore"):
            g = np.where(mb > 1e-3, gaussian_filter(g, sigma_px) / mb, 0.0)
        m = mb > 0.5
    return g[..., None], m.astype(np.float64)


def refine_rotations(views: Sequence, *, fixed_index: int = 0, n_directions: int = 8000,
                     blur_sigmas_px: Sequence[float] = (4.0, 1.0), max_correction_deg: float = 10.0,
                     loss_scale: float = 0.1) -> RotationRefinement:
    """Refine the orientation of overlapping views (view ``fixed_index`` is held fixed).

    Unknowns: a world-frame rotation vector r_v per other view (world_from_camera becomes
    exp([r_v]x) R_v, |r_v| components bounded by ``max_correction_deg``). Residuals at
    ``n_directions`` Fibonacci-sphere directions, for every pair of views i < j:
    sqrt(w_i w_j) (g_i - g_j), g the Gaussian-blurred log luminance (saturated and masked pixels
    excluded), w the blend weights; soft-L1 loss with scale ``loss_scale`` (log units), solved
    coarse to fine over ``blur_sigmas_px`` with scipy least_squares (TRF).
    """
    vs = [_as_view(v, i) for i, v in enumerate(views)]
    nv = len(vs)
    if nv < 2 or not 0 <= fixed_index < nv:
        raise ValueError(f"refine_rotations needs >= 2 views and a valid fixed_index, got {nv}, {fixed_index}")
    free = [k for k in range(nv) if k != fixed_index]
    dirs = _fibonacci_sphere(int(n_directions))
    seen = np.zeros(len(dirs), dtype=int)
    for v in vs:
        seen += v.camera.direction_to_pixel(dirs)[1]
    dirs = dirs[seen >= 2]
    if len(dirs) == 0:
        raise ValueError("refine_rotations: the views do not overlap")
    pairs = [(i, j) for i in range(nv) for j in range(i + 1, nv)]
    base = [v.camera.rotation for v in vs]

    def rotations(x: np.ndarray) -> list[np.ndarray]:
        rots = list(base)
        for m, k in enumerate(free):
            rots[k] = Rotation.from_rotvec(x[3 * m : 3 * m + 3]).as_matrix() @ base[k]
        return rots

    def residuals(x: np.ndarray, images) -> np.ndarray:
        gs, ws = [], []
        for v, rot, (g_img, m_img) in zip(vs, rotations(x), images):
            d_cam = dirs @ rot
            px, valid = v.camera.cam_direction_to_pixel(d_cam)
            px = np.where(valid[:, None], px, 0.0)
            g, wsum, _ = _bilinear(g_img, m_img, None, px)
            gs.append(g[:, 0])
            ws.append(np.where(valid, wsum * v.camera.blend_weight(d_cam, px), 0.0))
        return np.concatenate([np.sqrt(ws[i] * ws[j]) * (gs[i] - gs[j]) for i, j in pairs])

    bound = math.radians(max_correction_deg)
    x = np.zeros(3 * len(free))
    final, success = float("nan"), True
    for sigma in blur_sigmas_px:
        images = [_log_luminance(v, float(sigma)) for v in vs]
        res = least_squares(residuals, x, args=(images,), method="trf", loss="soft_l1", f_scale=loss_scale,
                            bounds=(-bound, bound), diff_step=1e-3, x_scale=1e-2, xtol=1e-10, ftol=1e-12)
        x, final, success = res.x, float(0.5 * np.sum(res.fun**2)), success and bool(res.success)
    initial = float(0.5 * np.sum(residuals(np.zeros_like(x), images) ** 2))  # on the finest level
    rotvec = np.zeros((nv, 3))
    for m, k in enumerate(free):
        rotvec[k] = x[3 * m : 3 * m + 3]
    rots = rotations(x)
    out = tuple(dataclasses.replace(v, camera=v.camera.with_rotation(rots[k])) for k, v in enumerate(vs))
    return RotationRefinement(views=out, correction_rotvec_rad=rotvec, initial_cost=initial,
                              final_cost=final, n_directions=len(dirs), success=success)
