"""Sphere assembly: HDR views (linear float32 RGB) <-> lat-long probes in the DESIGN convention.

Cameras are :class:`~f2l.capture.cameras.ViewCamera` or :class:`~f2l.capture.cameras.MirrorBallCamera`
(or anything with their interface: ``width``, ``height``, ``rotation``, ``cam_direction_to_pixel``,
``pixel_to_cam_direction``, ``blend_weight``, ``radiance_gain``, ``with_rotation``); pixel
coordinates follow COLMAP (pixel (i, j) spans [j, j+1] x [i, i+1]).

- :func:`render_view`: each pixel averages s x s subpixel rays over the probe (piecewise constant
  per texel), times ``camera.radiance_gain``.
- :func:`assemble` splats each view: weighted 2^L x 2^L pixel boxes (about a quarter texel; views
  coarser than the grid are cut into s x s bilinear sub-pixels) carry their solid angle
  Omega = |dd/dx x dd/dy| x area x weight into the texels as boxes in the equal-area coordinates
  (theta, cos phi) with exact overlap fractions. Per view and texel L_v = sum(Omega I) / sum(Omega)
  (an area average; the view's energy is kept, so the sun keeps its energy at any resolution)
  and W_v = sum(Omega b) / texel solid angle, b = ``blend_weight`` (1 at the view centre, 0 at
  the edge of its valid region). Views blend as sum(W_v L_v) / sum(W_v). Pixels outside a camera's
  valid region (fisheye image circle, mirror-ball silhouette) or of weight 0 never count. Where a
  view's splats include a saturated pixel it gives only a lower bound, never averaged with
  measurements: a texel with lower bounds only keeps their maximum and is flagged ``saturated``.
  Directions no view sees are 0 and False in ``coverage`` (never invented).
- :func:`refine_rotations`: small world-frame rotations of all views but one minimising robust
  log-luminance differences at shared directions (scipy least_squares, coarse to fine).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from scipy.ndimage import gaussian_filter
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
    ``weight`` (h, w) in [0, 1] (usable fraction / confidence of the pixel, scaling its solid
    angle; 0 = never used) and an optional ``saturated`` (h, w) bool mask from the merge (the
    value there is only a lower bound). Tuples (image, camera[, weight[, saturated]]) also work."""

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
    """Result of :func:`assemble` on ``grid`` (row 0 = zenith, centre column = -Z)."""

    radiance: np.ndarray  # (H, W, 3) float32; 0 where not covered
    coverage: np.ndarray  # (H, W) bool: some view saw the texel
    saturated: np.ndarray  # (H, W) bool: only saturated pixels saw it; radiance is a lower bound
    weight_sum: np.ndarray  # (H, W) float32: sum of blend weights of the measurements
    view_stats: tuple[ViewStats, ...]
    grid: LatLongGrid


@dataclass(frozen=True, eq=False)
class RotationRefinement:
    """Result of :func:`refine_rotations`; costs are 0.5 sum(residual^2) on the finest blur level."""

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
    weight = weight * cam.valid_pixel_mask()  # pixels outside the lens's valid region never count
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
def _splat_plan(camera, grid: LatLongGrid, max_sub: int) -> tuple[int, int]:
    """(box level L, sub-splats per axis s) so that splats are about a quarter texel high: from the
    median angular pixel pitch p over the texels the view sees, 2^L = the largest power of two
    with p 2^L <= pi / (4 H), else L = 0 and s = ceil(p H 4 / pi) (at most ``max_sub``)."""
    px = camera.direction_to_pixel(grid.directions_flat)[0].reshape(*grid.shape, 2)
    d = grid.directions
    pitches = []
    for pa, pb, da, db in ((px[1:], px[:-1], d[1:], d[:-1]),
                           (px, np.roll(px, 1, axis=1), d, np.roll(d, 1, axis=1))):
        with np.errstate(invalid="ignore"):
            dist = np.linalg.norm(pa - pb, axis=-1)
        ok = np.isfinite(dist) & (dist > 0)
        pitches.append(np.arccos(np.clip(np.sum(da * db, axis=-1), -1.0, 1.0))[ok] / dist[ok])
    pitch, target = np.concatenate(pitches), math.pi / grid.height / 4.0
    p = float(np.median(pitch)) if pitch.size else target
    if p <= target:
        return min(int(math.log2(target / p)), int(math.log2(min(camera.width, camera.height)))), 1
    return 0, min(max_sub, math.ceil(p / target))


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
        pos = np.stack(np.broadcast_arrays(cols[:, None, None] + off[None, None, :],
                                           rows[:, None, None] + off[None, :, None]), axis=-1).reshape(-1, 2)
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
    """(L,) fraction of n x n sub-directions of each texel that project to a usable view pixel."""
    i = (np.arange(n) + 0.5) / n
    phi = grid.phi_edges_rad[:-1, None] + (np.pi / grid.height) * i[None, :]
    theta = grid.theta_edges_rad[:-1, None] + (2 * np.pi / grid.width) * i[None, :]
    ph, th = phi[:, None, :, None], theta[None, :, None, :]
    d = np.stack(np.broadcast_arrays(np.sin(ph) * np.sin(th), np.cos(ph), -np.sin(ph) * np.cos(th)), axis=-1)
    px, ok = v.camera.direction_to_pixel(d.reshape(-1, 3))
    cols = np.clip(np.nan_to_num(px[:, 0]).astype(np.int64), 0, v.camera.width - 1)
    rows = np.clip(np.nan_to_num(px[:, 1]).astype(np.int64), 0, v.camera.height - 1)
    ok &= v.weight[rows, cols] > 0
    return ok.reshape(grid.size, n * n).mean(axis=1)


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


def _splat_boxes(cam, pos: np.ndarray, area: np.ndarray, side_px: float):
    """For splats at pixel ``pos`` covering ``area`` (px^2 x weight): (mask of those that map to a
    valid direction, and for them: camera-frame direction, solid angle Omega = |dd/dx x dd/dy|
    area, and the box (theta_lo, theta_hi, t_lo, t_hi) in (theta, t = -cos phi) of area Omega whose
    extents are the RMS extents of the splat's Jacobian footprint, side ``side_px``)."""
    d, ok = cam.pixel_to_cam_direction(pos)
    jx, jy = _jacobian(cam, pos, d)
    rot = cam.rotation
    dw, jx, jy = d @ rot.T, jx @ rot.T, jy @ rot.T
    omega_px = np.nan_to_num(np.linalg.norm(np.cross(jx, jy), axis=1))
    ok &= omega_px > 0
    x, y, z = dw[ok].T
    jx, jy = jx[ok], jy[ok]
    rho2 = np.maximum(x * x + z * z, 1e-12)  # dtheta = (-z dx + x dz) / (x^2 + z^2), dt = -dy
    ext_th = side_px * np.hypot((-z * jx[:, 0] + x * jx[:, 2]) / rho2, (-z * jy[:, 0] + x * jy[:, 2]) / rho2)
    ext_t = side_px * np.hypot(jx[:, 1], jy[:, 1])
    scale = np.sqrt(omega_px[ok] * side_px**2 / np.maximum(ext_th * ext_t, 1e-300))  # box area = footprint area
    ext_th, ext_t = np.minimum(scale * ext_th, 2 * np.pi), np.minimum(scale * ext_t, 2.0)
    th, t = np.arctan2(x, -z), -y
    return ok, d[ok], omega_px[ok] * area[ok], (th - ext_th / 2, th + ext_th / 2, t - ext_t / 2, t + ext_t / 2)


def _accumulate(v: View, grid: LatLongGrid, level: int, sub: int):
    """Per-texel sums of one view: energy (L, 3) = sum(f Omega I), mass (L,) = sum(f Omega), blend
    (L,) = sum(f Omega b), saturated (L,) bool, and the fraction of each texel the view sees.

    A splat is an axis-aligned box in the equal-area coordinates (theta, cos phi), where texels are
    boxes too (see ``_splat_boxes``); f are its exact overlap fractions with the texels the view
    sees, renormalised to sum to 1, so the view's energy sum(Omega I) is kept exactly."""
    cam, size, H, W = v.camera, grid.size, grid.height, grid.width
    visible = _visible_texels(v, grid)
    seen = visible > 0
    energy, mass, blend, sat_w = np.zeros((size, 3)), np.zeros(size), np.zeros(size), np.zeros(size)
    pos, val, area, sat = _splats(v, level, sub)
    t_edges = -np.cos(grid.phi_edges_rad)  # increases with the row index
    c_edges, c_width = grid.theta_edges_rad, 2 * np.pi / W
    for c0 in range(0, len(pos), _CHUNK_SAMPLES // 8):
        sl = slice(c0, c0 + _CHUNK_SAMPLES // 8)
        ok, d, omega, (th_lo, th_hi, t_lo, t_hi) = _splat_boxes(cam, pos[sl], area[sl], 2.0**level / sub)
        p, value, st = pos[sl][ok], val[sl][ok], sat[sl][ok]
        bw = cam.blend_weight(d, p)
        r_start = np.clip(np.searchsorted(t_edges, t_lo, side="right") - 1, 0, H - 1)
        n_rows = int(np.max(np.searchsorted(t_edges, t_hi) - r_start, initial=0)) + 1
        rows, f_r = _overlaps(t_lo, t_hi, t_edges, r_start, min(n_rows, H), periodic=False)
        c_start = np.floor((th_lo - c_edges[0]) / c_width).astype(np.int64)
        spans = np.minimum(2 ** np.ceil(np.log2(np.ceil((th_hi - th_lo) / c_width) + 1)), W + 1).astype(np.int64)
        for span in np.unique(spans):  # splats grouped by the number of columns they may touch
            g = np.flatnonzero(spans == span)
            cols, f_c = _overlaps(th_lo[g], th_hi[g], c_edges, c_start[g], int(span), periodic=True)
            idx = (rows[g][:, :, None] * W + cols[:, None, :]).reshape(len(g), -1)
            f = (f_r[g][:, :, None] * f_c[:, None, :]).reshape(len(g), -1) * seen[idx]
            tot = f.sum(1)
            g, idx, f = g[tot > 0], idx[tot > 0], f[tot > 0] / tot[tot > 0, None]
            wgt = f * omega[g, None]
            ii = idx.ravel()
            for ch in range(3):
                energy[:, ch] += np.bincount(ii, (wgt * value[g, ch, None]).ravel(), size)
            mass += np.bincount(ii, wgt.ravel(), size)
            blend += np.bincount(ii, (wgt * bw[g, None]).ravel(), size)
            sat_w += np.bincount(ii, (wgt * st[g, None]).ravel(), size)
    return energy, mass, blend, sat_w > 0, visible


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
        level, sub = _splat_plan(v.camera, grid, int(max_subsamples))
        plans.append((level, sub))
        energy, mass, blend, sat, visible = _accumulate(v, grid, level, sub)
        covered = (visible > 0) & (mass > 0) & (blend > 0)
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
    y, a = 1.0 - 2.0 * i / n, math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([np.sqrt(1.0 - y * y) * np.sin(a), y, -np.sqrt(1.0 - y * y) * np.cos(a)], axis=1)


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
                     blur_sigmas_px: Sequence[float] = (8.0, 3.0), max_correction_deg: float = 10.0,
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
