"""A von Mises-Fisher sun lobe integrated over each lat-long texel (torch, differentiable).

    lobe(omega) = C exp(kappa (omega_sun . omega - 1)),   C = kappa / (2 pi (1 - e^{-2 kappa})),

integrates to 1 over the sphere. Point sampling it at texel centres is wrong once the lobe is
narrower than a texel (kappa = 8192: sigma = 1/sqrt(kappa) = 0.63 deg against 2.8 deg texels;
see the shared performance notes), so :func:`sun_lobe` returns each texel's *mean* radiance
(its integral over the texel divided by the texel's solid angle).

Method (grid convention of ``f2l.lighting.grid``: phi polar angle from +Y, theta azimuth). With
the sun at (phi_s, theta_s) and Delta = theta - theta_s, the exponent splits exactly:

    kappa (cos alpha - 1) = kappa (cos(phi - phi_s) - 1) + a(phi) (cos Delta - 1),
    a(phi) = kappa sin(phi) sin(phi_s) >= 0.

- phi: composite 3-node Gauss-Legendre on sin(phi) dphi, S sub-rows per row with
  S = ceil(dphi sqrt(kappa) / 2) (sub-rows at most 2 sigma tall). Exact at the poles, where the
  lobe is radial in phi.
- theta: per column, exp(a (cos Delta - 1)) ~ exp(a (cos Delta_m - 1)) exp(-a (Delta^2 -
  Delta_m^2) / 2) (Delta_m the column centre's wrapped offset), and the Gaussian factor is
  integrated in closed form (erfcx, see :func:`column_factor`). Exact as a -> 0 (sun at a pole)
  and as a -> inf (lobe much narrower than a column).
- Window: only texels within alpha_tail of the sun (kappa (1 - cos alpha_tail) = 40, i.e. below
  e^-40 of the peak) are integrated; the rest are 0. The window's rows and columns are discrete
  choices made from detached values, so everything is differentiable in (phi_s, theta_s, kappa);
  near the poles the window takes all columns.

Accuracy (tests/test_sunsky.py): texel sums within ~3e-4 of 1 on 64 x 128 (2e-3 on 32 x 64) for
kappa in {8, 1024, 8192} at random suns, the zenith and the horizon; per texel within ~1e-4 of
the peak texel's energy of brute-force supersampling (64 x 64 midpoints, or 16 x 16
Gauss-Legendre nodes per texel).

References
----------
- Fisher. "Dispersion on a Sphere." Proceedings of the Royal Society of London, Series A 217,
  pp. 295-305, 1953 (the von Mises-Fisher distribution on the sphere).
- Calian, Lalonde, Gotardo, Simon, Matthews, Mitchell. "From Faces to Outdoor Light Probes."
  Computer Graphics Forum (Eurographics) 37(2), 2018 (the vMF sun of the Sun+Sky model, §3.3.2).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from f2l.lighting.grid import LatLongGrid

TAIL = 40.0  # the window drops the lobe below exp(-TAIL) of its peak
SUB_ROW_SIGMAS = 2.0  # phi sub-rows at most this many lobe sigmas (1/sqrt(kappa)) tall
SMALL_Z = 1e-4  # sqrt(a/2) w below this: the column integral's series (a ~ 0, near a pole)
MAX_CHUNK = 1 << 21  # elements (nodes x columns x suns) evaluated at once
ONE_GROUP_MAX = 1 << 18  # below this many elements, all suns share one window shape
_GL_X, _GL_W = np.polynomial.legendre.leggauss(3)


def vmf_normaliser(kappa: torch.Tensor) -> torch.Tensor:
    """C(kappa) = kappa / (2 pi (1 - exp(-2 kappa))), stable for small and large kappa.

    >>> kappa = torch.tensor([1e-9, 8192.0], dtype=torch.float64)
    >>> [round(float(c), 6) for c in vmf_normaliser(kappa) * torch.tensor([4 * math.pi, 2 * math.pi / 8192])]
    [1.0, 1.0]

    (kappa -> 0: the uniform density 1 / (4 pi); large kappa: kappa / (2 pi).)
    """
    return kappa / (2.0 * math.pi * -torch.expm1(-2.0 * kappa))


def column_factor(a: torch.Tensor, b: torch.Tensor, w: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The theta integral of one column, factored as exp(log_scale) * D (both broadcast).

    int_{Delta_m - w/2}^{Delta_m + w/2} exp(a (cos Delta - 1)) dDelta
        ~ exp(a (cos Delta_m - 1)) K,   K = int_{-w/2}^{w/2} exp(-a b u - a u^2 / 2) du,  b = |Delta_m|,
    and with q = sqrt(a/2), x0 = q (b - w/2), x1 = q (b + w/2):
        K = sqrt(pi) / (2 q) exp(a (b w / 2 - w^2 / 8)) D,   D = erfcx(x0) - erfcx(x1) exp(x0^2 - x1^2)
    (= e^{x0^2} (erfc(x0) - erfc(x1)) > 0, no overflow: x0 >= -q w / 2). Returns
    (log_scale, D) with log_scale = a (cos Delta_m - 1 + b w / 2) + log(sqrt(pi) / (2 q)) - a w^2 / 8.
    For sqrt(a/2) w < SMALL_Z (a ~ 0, at a pole) D's difference would cancel, so there the series
    K = w exp((a b w)^2 / 24 - a w^2 / 24) is used instead (D = 1); every branch is fed safe
    inputs, so the unused one never makes a NaN gradient.

    With a = 0 (the sun at a pole) the integral is the column's width:

    >>> zero = torch.tensor(0.0, dtype=torch.float64)
    >>> log_scale, d = column_factor(zero, zero, 0.1)
    >>> round(float(torch.exp(log_scale) * d), 9)
    0.1
    """
    small = torch.sqrt(0.5 * a) * w < SMALL_Z
    a_s = torch.where(small, torch.ones_like(a), a)
    q = torch.sqrt(0.5 * a_s)
    qw = q * w
    x0 = (q * (b - 0.5 * w)).clamp_min(-25.0)
    d = torch.special.erfcx(x0) - torch.special.erfcx(x0 + qw) * torch.exp(-qw * (2.0 * x0 + qw))
    cos_term = torch.cos(b) - 1.0
    log_scale = a_s * (cos_term + 0.5 * w * b) + (0.5 * math.log(math.pi) - torch.log(2.0 * q) - a_s * w * w / 8.0)
    if bool(small.any()):
        log_small = a * cos_term + math.log(w) + (a * b * w) ** 2 / 24.0 - a * w * w / 24.0
        log_scale = torch.where(small, log_small, log_scale)
        d = torch.where(small, torch.ones_like(d), d)
    return log_scale, d


def _window(grid: LatLongGrid, n_rows: int, phi_s: np.ndarray, theta_s: np.ndarray, kappa: np.ndarray):
    """Per-sun window: first row, rows needed, sub-rows S, first column, columns needed."""
    H, W = grid.shape
    dphi, w = math.pi / H, 2.0 * math.pi / W
    one_minus = TAIL / kappa
    alpha = np.where(one_minus >= 2.0, math.pi, np.arccos(np.clip(1.0 - one_minus, -1.0, 1.0)))
    r_lo = np.clip(np.floor((phi_s - alpha) / dphi), 0, n_rows - 1).astype(np.int64)
    r_hi = np.clip(np.floor((phi_s + alpha) / dphi), 0, n_rows - 1).astype(np.int64)
    sub = np.maximum(1, np.ceil(dphi * np.sqrt(kappa) / SUB_ROW_SIGMAS)).astype(np.int64)
    # widest azimuth offset inside the lobe's support, over polar angles sampled across the rows:
    # cos(alpha_tail) <= cos(phi) cos(phi_s) + sin(phi) sin(phi_s) cos(Delta)
    t = np.linspace(0.0, 1.0, 33)
    phi = r_lo[:, None] * dphi + t[None, :] * ((r_hi - r_lo + 1) * dphi)[:, None]  # (B, 33)
    den = np.sin(phi) * np.sin(phi_s)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        cos_d = (np.cos(alpha)[:, None] - np.cos(phi) * np.cos(phi_s)[:, None]) / den
        half = np.where(den > 1e-12, np.arccos(np.clip(cos_d, -1.0, 1.0)), math.pi).max(1)
    half = np.minimum(half + w, math.pi)  # + a column for the sampling of phi
    c_lo = np.floor((theta_s - half + math.pi) / w)
    c_hi = np.floor((theta_s + half + math.pi) / w)
    cols = np.minimum(np.where(half >= math.pi, W, c_hi - c_lo + 1), W).astype(np.int64)
    c_lo = np.where(cols >= W, 0, c_lo).astype(np.int64)
    return r_lo, r_hi - r_lo + 1, sub, c_lo, cols


def sun_lobe_sparse(
    grid: LatLongGrid,
    sun_zenith_rad: torch.Tensor,
    sun_azimuth_rad: torch.Tensor,
    kappa: torch.Tensor,
    n_rows: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The lobe on its window only: texel means (B, K) and flat texel indices (B, K) (int64).

    Indices are row-major into the first ``n_rows`` rows; within a sun they are distinct, except
    padding entries (value 0, index 0) when suns need windows of different sizes, so scatter
    with *add*. See :func:`sun_lobe` for the arguments.

    >>> grid = LatLongGrid(32, 64)
    >>> one = lambda v: torch.tensor([v], dtype=torch.float64)
    >>> vals, flat = sun_lobe_sparse(grid, one(1.0), one(0.5), one(1024.0))
    >>> vals.shape == flat.shape, vals.shape[1] < grid.size  # only the window around the sun
    (True, True)
    >>> sa = torch.tensor(grid.solid_angles_flat)
    >>> round(float((vals[0] * sa[flat[0]]).sum()), 3)  # the window holds the lobe's unit energy
    1.0
    """
    H, W = grid.shape
    n_rows = H if n_rows is None else int(n_rows)
    dphi, w = math.pi / H, 2.0 * math.pi / W
    dtype, device = sun_zenith_rad.dtype, sun_zenith_rad.device
    B = sun_zenith_rad.shape[0]
    if B == 0:
        return sun_zenith_rad.new_zeros(0, 0), torch.zeros(0, 0, dtype=torch.int64, device=device)
    ps_np = sun_zenith_rad.detach().cpu().double().numpy()
    ts_np = sun_azimuth_rad.detach().cpu().double().numpy()
    k_np = kappa.detach().cpu().double().numpy()
    r_lo, r_need, sub, c_lo, c_need = _window(grid, n_rows, ps_np, ts_np, k_np)
    row_sa = torch.as_tensor(grid.row_solid_angles[:n_rows], dtype=dtype, device=device)
    # One window shape for all suns (the largest) when that is cheap -- torch's per-op overhead
    # dominates small windows -- else groups by sub-rows and by wide (near a pole) or narrow.
    one = B * int(r_need.max()) * 3 * int(sub.max()) * int(min(W, c_need.max())) <= ONE_GROUP_MAX
    keys = np.zeros(B, np.int64) if one else sub * 2 + (4 * c_need > W)
    parts = []
    for key in np.unique(keys):
        members = np.nonzero(keys == key)[0]
        S = int(sub[members].max())
        R = int(r_need[members].max())
        C = int(min(W, c_need[members].max()))
        step = max(1, MAX_CHUNK // (R * 3 * S * C))
        for start in range(0, members.size, step):
            idx = members[start : start + step]
            if idx.size == B:
                args = (sun_zenith_rad, sun_azimuth_rad, kappa)
            else:
                index = torch.as_tensor(idx, device=device)
                args = (sun_zenith_rad[index], sun_azimuth_rad[index], kappa[index])
            vals, flat = _group(grid, R, S, C, r_lo[idx], c_lo[idx], sub[idx], n_rows, row_sa, dphi, w, *args)
            if idx.size == B:
                return vals, flat
            parts.append((idx, vals, flat))
    K = max(v.shape[1] for _, v, _ in parts)
    vals = sun_zenith_rad.new_zeros(B, K)
    flat = torch.zeros(B, K, dtype=torch.int64, device=device)
    for idx, v, f in parts:
        index = torch.as_tensor(idx, device=device)
        vals = vals.index_put((index,), torch.nn.functional.pad(v, (0, K - v.shape[1])))
        flat[index] = torch.nn.functional.pad(f, (0, K - f.shape[1]))
    return vals, flat


def sun_lobe(
    grid: LatLongGrid,
    sun_zenith_rad: torch.Tensor,
    sun_azimuth_rad: torch.Tensor,
    kappa: torch.Tensor,
    n_rows: int | None = None,
) -> torch.Tensor:
    """(B, n_rows * W) mean radiance of the unit-energy vMF lobe in each texel (row-major).

    sun_zenith_rad = phi_s (polar angle from +Y), sun_azimuth_rad = theta_s (grid azimuth),
    kappa > 0, all (B,) tensors (float64 recommended). ``n_rows`` limits the output to the
    first rows (e.g. ``grid.sky_rows``); default all H rows, whose sum of texel means times
    solid angles is the lobe's energy, 1.

    >>> grid = LatLongGrid(32, 64)
    >>> t = lambda *v: torch.tensor(v, dtype=torch.float64)
    >>> lobe = sun_lobe(grid, t(1.0, 0.3), t(0.5, -2.0), t(8.0, 8192.0))  # a wide and a narrow sun
    >>> lobe.shape
    torch.Size([2, 2048])
    >>> (lobe * torch.tensor(grid.solid_angles_flat)).sum(dim=1).round(decimals=3).tolist()
    [1.0, 1.0]
    >>> from f2l.lighting.grid import direction_from_angles
    >>> sun = direction_from_angles(np.pi / 2 - 0.3, -2.0)  # elevation = pi/2 - zenith angle
    >>> divmod(int(lobe[1].argmax()), grid.width) == tuple(int(i) for i in grid.direction_to_texel(sun))
    True
    """
    n_rows = grid.height if n_rows is None else int(n_rows)
    out = sun_zenith_rad.new_zeros(sun_zenith_rad.shape[0], n_rows * grid.width)
    if out.shape[0] == 0:
        return out
    vals, flat = sun_lobe_sparse(grid, sun_zenith_rad, sun_azimuth_rad, kappa, n_rows)
    return out.scatter_add_(1, flat, vals)


def _group(grid, R, S, C, r_lo, c_lo, sub_rows, n_rows, row_sa, dphi, w, ps, ts, kappa):
    """Texel means (G, R*C) and their flat indices for suns sharing one window shape."""
    W = grid.width
    dtype, device = ps.dtype, ps.device
    G = len(r_lo)
    r_lo = np.minimum(r_lo, n_rows - R)
    rows = r_lo[:, None] + np.arange(R)[None, :]  # (G, R)
    # Each sun keeps its own S_g sub-rows (its quadrature never depends on the other suns of the
    # batch); the S - S_g padding sub-rows repeat real nodes with weight 0.
    s_g = np.asarray(sub_rows, dtype=np.int64)[:, None]  # (G, 1)
    k = np.arange(S)[None, :]  # (1, S)
    frac = ((k % s_g)[:, :, None] + 0.5 * (1.0 + _GL_X)[None, None, :]) / s_g[:, :, None]  # (G, S, 3)
    node_w = np.where(k < s_g, 1.0, 0.0)[:, :, None] * (0.5 * _GL_W * dphi)[None, None, :] / s_g[:, :, None]
    phi_np = ((rows[:, :, None] + frac.reshape(G, 1, 3 * S)) * dphi).reshape(G, -1)  # (G, N), N = 3 S R
    wsin_np = np.sin(phi_np) * np.tile(node_w.reshape(G, 3 * S), (1, R))  # GL weight x sin(phi)
    phi = torch.as_tensor(phi_np, dtype=dtype, device=device)
    wsin = torch.as_tensor(wsin_np.reshape(G, R, 3 * S), dtype=dtype, device=device)
    cols = (c_lo[:, None] + np.arange(C)[None, :]) % W  # (G, C)
    theta_mid = torch.as_tensor(-math.pi + (cols + 0.5) * w, dtype=dtype, device=device)
    delta = torch.remainder(theta_mid - ts[:, None] + math.pi, 2.0 * math.pi) - math.pi  # (G, C)
    k = kappa[:, None]
    a = k * torch.as_tensor(np.sin(phi_np), dtype=dtype, device=device) * torch.sin(ps)[:, None]  # (G, N)
    e_phi = k * (torch.cos(phi - ps[:, None]) - 1.0)  # (G, N)
    log_scale, d = column_factor(a[:, :, None], delta.abs()[:, None, :], w)  # (G, N, C)
    v = torch.exp(e_phi[:, :, None] + log_scale) * d
    v = torch.einsum("grnc,grn->grc", v.reshape(G, R, 3 * S, C), wsin)  # texel integrals / C(kappa)
    mean = v * vmf_normaliser(kappa)[:, None, None] / row_sa[torch.as_tensor(rows, device=device)][:, :, None]
    flat = torch.as_tensor(rows[:, :, None] * W + cols[:, None, :], device=device).reshape(G, -1)
    return mean.reshape(G, -1), flat
