"""Real spherical harmonics in the f2l frame (polar axis +Y, azimuth = the grid's theta).

Conventions (see ``f2l.lighting.grid``): for a unit direction d = (x, y, z)

    phi   = acos(y)              polar angle from +Y (up)
    theta = atan2(x, -z)         azimuth; 0 is the camera's viewing direction (-Z)

    Y_lm(d) = N_lm P_l^|m|(cos phi) * { sqrt(2) cos(m theta)     m > 0
                                       { 1                        m = 0
                                       { sqrt(2) sin(|m| theta)   m < 0
    N_lm    = sqrt((2l + 1) / (4 pi) * (l - |m|)! / (l + |m|)!)

with P_l^m the associated Legendre functions *without* the Condon-Shortley phase (so
P_1^1(t) = +sqrt(1 - t^2)). The basis is orthonormal on the sphere. Low orders, explicitly:

    Y_00 = 1 / (2 sqrt(pi)),   Y_1,-1 = sqrt(3/(4 pi)) x,   Y_10 = sqrt(3/(4 pi)) y,
    Y_11 = -sqrt(3/(4 pi)) z   (theta = 0 is -Z, so cos(theta) sin(phi) = -z).

Coefficients are stored flat, k = l (l + 1) + m, K = (order + 1)^2, first axis of a (K, ...)
array. The normalised Legendre values N_lm P_l^m are computed with the standard stable
three-term recursion on the normalised functions (no factorials), valid for any order.

Irradiance (``lambert_band_factors``, ``irradiance_coeffs``): convolution with the clamped cosine
is a per-band scale A_l of the radiance coefficients (Ramamoorthi & Hanrahan 2001).

References
----------
- Ramamoorthi, Hanrahan. "An Efficient Representation for Irradiance Environment Maps."
  Proceedings of SIGGRAPH 2001, pp. 497-500.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from f2l.lighting.grid import LatLongGrid

__all__ = [
    "num_coeffs",
    "sh_index",
    "sh_band_of_index",
    "sh_basis",
    "sh_basis_grid",
    "sh_texel_mean_grid",
    "project",
    "reconstruct",
    "lambert_band_factors",
    "irradiance_coeffs",
    "rotate_y_coeffs",
]


def num_coeffs(order: int) -> int:
    """Number of coefficients K = (order + 1)^2 for bands l = 0 .. order.

    >>> num_coeffs(2), num_coeffs(4)  # the SH9 and SH25 models
    (9, 25)
    """
    order = _check_order(order)
    return (order + 1) ** 2


def sh_index(l: int, m: int) -> int:  # noqa: E741 - the usual SH name
    """Flat index k = l (l + 1) + m of Y_lm (|m| <= l).

    >>> sh_index(0, 0), sh_index(1, -1), sh_index(1, 1), sh_index(2, 0)
    (0, 1, 3, 6)
    """
    if l < 0 or abs(m) > l:
        raise ValueError(f"invalid SH index l={l}, m={m}")
    return l * (l + 1) + m


def sh_band_of_index(num: int) -> np.ndarray:
    """Band l of each flat index 0 .. num - 1, shape (num,), int64.

    >>> sh_band_of_index(9).tolist()
    [0, 1, 1, 1, 2, 2, 2, 2, 2]
    """
    return np.floor(np.sqrt(np.arange(num, dtype=np.float64)) + 1e-9).astype(np.int64)


def _check_order(order: int) -> int:
    if int(order) != order or order < 0:
        raise ValueError(f"SH order must be a non-negative integer, got {order!r}")
    return int(order)


def _order_of(num: int) -> int:
    order = math.isqrt(num) - 1
    if (order + 1) ** 2 != num or order < 0:
        raise ValueError(f"number of SH coefficients must be a perfect square, got {num}")
    return order


def _normalised_legendre(cos_phi: np.ndarray, sin_phi: np.ndarray, order: int) -> dict:
    """Pbar[l, m] = N_lm P_l^m(cos phi) for 0 <= m <= l <= order (no Condon-Shortley phase).

    Recursion on the normalised functions (all factors O(1), stable to high order):
        Pbar_00     = 1 / sqrt(4 pi)
        Pbar_mm     = sqrt((2m + 1) / (2m)) sin(phi) Pbar_{m-1,m-1}
        Pbar_{m+1,m} = sqrt(2m + 3) cos(phi) Pbar_mm
        Pbar_lm     = a_lm (cos(phi) Pbar_{l-1,m} - b_lm Pbar_{l-2,m}),
            a_lm = sqrt((4l^2 - 1) / (l^2 - m^2)),  b_lm = sqrt(((l-1)^2 - m^2) / (4(l-1)^2 - 1))
    """
    pbar: dict[tuple[int, int], np.ndarray] = {}
    pmm = np.full_like(cos_phi, 1.0 / math.sqrt(4.0 * math.pi))
    for m in range(order + 1):
        if m > 0:
            pmm = math.sqrt((2.0 * m + 1.0) / (2.0 * m)) * sin_phi * pmm
        pbar[(m, m)] = pmm
        if m + 1 <= order:
            pbar[(m + 1, m)] = math.sqrt(2.0 * m + 3.0) * cos_phi * pmm
        for l in range(m + 2, order + 1):  # noqa: E741
            a = math.sqrt((4.0 * l * l - 1.0) / (l * l - m * m))
            b = math.sqrt(((l - 1.0) ** 2 - m * m) / (4.0 * (l - 1.0) ** 2 - 1.0))
            pbar[(l, m)] = a * (cos_phi * pbar[(l - 1, m)] - b * pbar[(l - 2, m)])
    return pbar


def sh_basis(directions: np.ndarray, order: int) -> np.ndarray:
    """Evaluate all Y_lm, l <= order, at directions (..., 3) -> (..., K), float64.

    Directions are normalised first (zero vectors give NaN). See the module docstring for the
    convention (polar axis +Y, theta = atan2(x, -z), no Condon-Shortley phase).

    >>> y = sh_basis(np.array([0.0, 1.0, 0.0]), 1)  # at the zenith only m = 0 is non-zero
    >>> y.shape, np.round(np.abs(y), 4).tolist()
    ((4,), [0.2821, 0.0, 0.4886, 0.0])
    >>> round(float(sh_basis(np.array([0.0, 0.0, -1.0]), 1)[3]), 4)  # Y_11 = -sqrt(3 / (4 pi)) z
    0.4886
    >>> sh_basis(np.ones((5, 7, 3)), 2).shape
    (5, 7, 9)
    """
    order = _check_order(order)
    d = np.asarray(directions, dtype=np.float64)
    if d.shape[-1:] != (3,):
        raise ValueError(f"directions must have shape (..., 3), got {d.shape}")
    lead = d.shape[:-1]
    d = d.reshape(-1, 3)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    cos_phi = np.clip(y, -1.0, 1.0)
    sin_phi = np.hypot(x, z)
    theta = np.arctan2(x, -z)
    pbar = _normalised_legendre(cos_phi, sin_phi, order)

    out = np.empty((d.shape[0], (order + 1) ** 2), dtype=np.float64)
    sqrt2 = math.sqrt(2.0)
    for m in range(order + 1):
        if m == 0:
            for l in range(order + 1):  # noqa: E741
                out[:, l * (l + 1)] = pbar[(l, 0)]
            continue
        cos_m = sqrt2 * np.cos(m * theta)
        sin_m = sqrt2 * np.sin(m * theta)
        for l in range(m, order + 1):  # noqa: E741
            out[:, l * (l + 1) + m] = pbar[(l, m)] * cos_m
            out[:, l * (l + 1) - m] = pbar[(l, m)] * sin_m
    return out.reshape(*lead, out.shape[-1])


@lru_cache(maxsize=16)
def _sh_basis_grid_cached(height: int, width: int, order: int) -> np.ndarray:
    basis = np.ascontiguousarray(sh_basis(LatLongGrid(height, width).directions_flat, order))
    basis.setflags(write=False)
    return basis


def sh_basis_grid(grid: LatLongGrid, order: int) -> np.ndarray:
    """Y_k at the texel centres of ``grid``, shape (L, K), texels flattened row-major.

    Cached per (height, width, order); the returned array is read-only.

    >>> basis = sh_basis_grid(LatLongGrid(8, 16), 2)
    >>> basis.shape, basis.flags.writeable
    ((128, 9), False)
    """
    return _sh_basis_grid_cached(int(grid.height), int(grid.width), _check_order(order))


@lru_cache(maxsize=16)
def _sh_texel_mean_cached(height: int, width: int, order: int) -> np.ndarray:
    grid = LatLongGrid(height, width)
    # Polar factor: mean of Pbar_lm(cos phi) over each row w.r.t. solid angle, by Gauss-Legendre
    # in phi (integrand Pbar(cos phi) sin phi is smooth; 'nodes' points per row is ample).
    nodes = max(8, order + 4)
    t, w = np.polynomial.legendre.leggauss(nodes)
    edges = grid.phi_edges_rad
    half = 0.5 * (edges[1:] - edges[:-1])[:, None]
    phi_q = (0.5 * (edges[1:] + edges[:-1]))[:, None] + half * t[None, :]  # (H, nodes)
    weight_q = half * w[None, :] * np.sin(phi_q)
    d_mu = (np.cos(edges[:-1]) - np.cos(edges[1:]))[:, None]
    pbar = _normalised_legendre(np.cos(phi_q), np.sin(phi_q), order)
    K = (order + 1) ** 2
    row = np.empty((height, K))
    col = np.empty((width, K))
    theta = grid.theta_rad
    half_dtheta = math.pi / width
    sqrt2 = math.sqrt(2.0)
    for l in range(order + 1):  # noqa: E741
        for m in range(-l, l + 1):
            k = l * (l + 1) + m
            am = abs(m)
            row[:, k] = (pbar[(l, am)] * weight_q).sum(axis=1) / d_mu[:, 0]
            if m == 0:
                col[:, k] = 1.0
                continue
            # Mean of cos/sin(m theta) over a column = centre value * sinc(m dtheta / 2).
            sinc = math.sin(am * half_dtheta) / (am * half_dtheta)
            trig = np.cos(m * theta) if m > 0 else np.sin(am * theta)
            col[:, k] = sqrt2 * sinc * trig
    basis = np.ascontiguousarray((row[:, None, :] * col[None, :, :]).reshape(grid.size, K))
    basis.setflags(write=False)
    return basis


def sh_texel_mean_grid(grid: LatLongGrid, order: int) -> np.ndarray:
    """Mean of Y_k over each texel (w.r.t. solid angle), shape (L, K), row-major; cached, read-only.

    Ybar_k(texel) = (1 / dOmega) int_texel Y_k dOmega, computed separably: the azimuthal mean is
    the centre value times sinc(|m| dtheta / 2) (exact), the polar mean uses Gauss-Legendre in
    phi (to ~machine precision). Sum_texels Ybar_k dOmega = int Y_k dOmega exactly.

    >>> grid = LatLongGrid(8, 16)
    >>> mean = sh_texel_mean_grid(grid, 2)
    >>> mean.shape
    (128, 9)
    >>> integral = grid.solid_angles_flat @ mean  # int Y_00 = 2 sqrt(pi); the others integrate to 0
    >>> round(float(integral[0]), 6), float(np.abs(integral[1:]).max()) < 1e-12
    (3.544908, True)
    """
    return _sh_texel_mean_cached(int(grid.height), int(grid.width), _check_order(order))


def project(probe: np.ndarray, grid: LatLongGrid, order: int, quadrature: str = "texel") -> np.ndarray:
    """SH coefficients c_k = int f Y_k dOmega of a lat-long probe.

    ``probe`` is (H, W, C) -> returns (K, C); or (H, W) -> returns (K,). Float64.

    quadrature="texel" (default): the probe is taken as what it stores, the mean radiance of
        each texel, and integrated exactly: c_k = sum_texels f Ybar_k dOmega with Ybar_k the
        texel mean of Y_k (``sh_texel_mean_grid``). Constants project exactly (c_k = 0, k > 0);
        point samples of a band-limited function are recovered to O((pi / H)^2).
    quadrature="point": midpoint rule c_k = sum_texels f Y_k(centre) dOmega. A single lit texel
        of power P gives exactly P Y_k(centre); constants leak O((pi / H)^2) into even m = 0 bands.
    Both rules' azimuthal sums are exact for |m| < W / 2, so column rolls commute with
    ``rotate_y_coeffs`` exactly.

    A constant radiance of 1 projects onto Y_00 alone, c_0 = 4 pi Y_00 = 2 sqrt(pi):

    >>> grid = LatLongGrid(8, 16)
    >>> c = project(np.ones(grid.shape), grid, 2)
    >>> c.shape, round(float(c[0]), 6), round(2 * float(np.sqrt(np.pi)), 6)
    ((9,), 3.544908, 3.544908)
    >>> float(np.abs(c[1:]).max()) < 1e-12
    True
    >>> project(np.ones((8, 16, 3)), grid, 1).shape  # RGB: one column per channel
    (4, 3)
    """
    f = np.asarray(probe, dtype=np.float64)
    if f.shape[:2] != grid.shape or f.ndim not in (2, 3):
        raise ValueError(f"probe shape {f.shape} does not match grid {grid.shape} (+ channels)")
    if quadrature == "texel":
        basis = sh_texel_mean_grid(grid, order)
    elif quadrature == "point":
        basis = sh_basis_grid(grid, order)
    else:
        raise ValueError(f"quadrature must be 'texel' or 'point', got {quadrature!r}")
    weights = grid.solid_angles_flat
    if f.ndim == 2:
        return basis.T @ (f.reshape(-1) * weights)
    return basis.T @ (f.reshape(grid.size, -1) * weights[:, None])


def reconstruct(coeffs: np.ndarray, grid: LatLongGrid) -> np.ndarray:
    """Evaluate sum_k c_k Y_k at texel centres: (K, C) -> (H, W, C); (K,) -> (H, W). Float64.

    >>> grid = LatLongGrid(8, 16)
    >>> probe = reconstruct(project(np.full(grid.shape, 3.0), grid, 2), grid)
    >>> probe.shape, round(float(probe.min()), 9), round(float(probe.max()), 9)
    ((8, 16), 3.0, 3.0)
    """
    c = np.asarray(coeffs, dtype=np.float64)
    order = _order_of(c.shape[0])
    basis = sh_basis_grid(grid, order)
    if c.ndim == 1:
        return (basis @ c).reshape(grid.shape)
    return (basis @ c.reshape(c.shape[0], -1)).reshape(*grid.shape, *c.shape[1:])


def lambert_band_factors(order: int) -> np.ndarray:
    """Clamped-cosine convolution factors A_l, l = 0 .. order, shape (order + 1,).

    A_l = 2 pi int_0^1 t P_l(t) dt (Funk-Hecke), so irradiance E(n) = sum_lm A_l L_lm Y_lm(n):
        A_0 = pi,  A_1 = 2 pi / 3,  A_l = 0 for odd l > 1, and for even l
        A_l = 2 pi (-1)^(l/2 - 1) / ((l + 2)(l - 1)) * l! / (2^l ((l/2)!)^2)
    (A_2 = pi/4, A_4 = -pi/24, A_6 = pi/64, ...).

    >>> np.round(lambert_band_factors(4) / np.pi, 6).tolist()  # A_l / pi
    [1.0, 0.666667, 0.25, 0.0, -0.041667]
    """
    order = _check_order(order)
    a = np.zeros(order + 1, dtype=np.float64)
    for l in range(order + 1):  # noqa: E741
        if l == 1:
            a[l] = 2.0 * math.pi / 3.0
        elif l % 2 == 0:
            binom_over_pow = math.comb(l, l // 2) / (2**l)  # l! / (2^l ((l/2)!)^2), exact ints
            sign = -1.0 if (l // 2 - 1) % 2 else 1.0
            a[l] = 2.0 * math.pi * sign / ((l + 2) * (l - 1)) * binom_over_pow
    return a


def irradiance_coeffs(coeffs: np.ndarray, order: int | None = None) -> np.ndarray:
    """Irradiance SH coefficients: E_lm = A_l L_lm, so E(n) = sum_k E_k Y_k(n).

    ``coeffs`` is (K, ...) radiance coefficients; ``order`` (if given) must match K.

    A white furnace (radiance 1 everywhere) gives an irradiance of pi at every normal:

    >>> grid = LatLongGrid(8, 16)
    >>> e = irradiance_coeffs(project(np.ones(grid.shape), grid, 2))
    >>> round(float(e @ sh_basis(np.array([0.0, 1.0, 0.0]), 2) / np.pi), 9)
    1.0
    """
    c = np.asarray(coeffs, dtype=np.float64)
    inferred = _order_of(c.shape[0])
    if order is not None and _check_order(order) != inferred:
        raise ValueError(f"order {order} does not match {c.shape[0]} coefficients")
    factors = lambert_band_factors(inferred)[sh_band_of_index(c.shape[0])]
    return c * factors.reshape(-1, *([1] * (c.ndim - 1)))


def rotate_y_coeffs(coeffs: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotate lighting about +Y by ``angle_rad`` in the SH domain (exact).

    Same meaning as ``grid.rotate_y``: content at azimuth theta moves to theta - angle, i.e.
    g(theta) = f(theta + angle). For each l and m > 0, with c = L_{l,m}, s = L_{l,-m}:
        c' =  c cos(m a) + s sin(m a)
        s' = -c sin(m a) + s cos(m a)
    m = 0 coefficients are unchanged. ``coeffs`` is (K, ...).

    Light along +X (azimuth +pi/2) rotated by +pi/2 moves to azimuth 0, the -Z direction:

    >>> c = sh_basis(np.array([1.0, 0.0, 0.0]), 1)
    >>> rotated = rotate_y_coeffs(c, np.pi / 2)
    >>> bool(np.allclose(rotated, sh_basis(np.array([0.0, 0.0, -1.0]), 1)))
    True
    """
    c = np.asarray(coeffs, dtype=np.float64)
    order = _order_of(c.shape[0])
    out = c.copy()
    for m in range(1, order + 1):
        cos_a, sin_a = math.cos(m * angle_rad), math.sin(m * angle_rad)
        for l in range(m, order + 1):  # noqa: E741
            kp, kn = l * (l + 1) + m, l * (l + 1) - m
            out[kp] = cos_a * c[kp] + sin_a * c[kn]
            out[kn] = -sin_a * c[kp] + cos_a * c[kn]
    return out
