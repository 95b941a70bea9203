"""Ground-truth outdoor light probes for synthetic data (float32 (H, W, 3) linear radiance).

Probes live on a :class:`~f2l.lighting.grid.LatLongGrid` (row 0 zenith, +Y up, column W/2 the
camera's viewing direction -Z). The upper hemisphere (rows 0 .. H/2-1) is sky (+ sun); the lower
hemisphere (rows H/2 .. H-1) is a Lambertian ground of albedo rho lit by that sky,

    L_ground = (rho / pi) * E_h,      E_h = sum_{sky texels} max(0, omega_y) L(omega) dOmega,

a constant radiance (computed numerically on the probe's own grid).

Clear sky luminance (CIE 2003 standard general sky, type 12 "CIE standard clear sky, low
luminance turbidity"; Perez form), relative to the zenith:

    L(chi, Z) / L_z = f(chi) g(Z) / (f(Z_s) g(0)),
    g(Z) = 1 + a exp(b / cos Z),   f(chi) = 1 + c (exp(d chi) - exp(d pi/2)) + e cos^2 chi,
    a = -1, b = -0.32, c = 10, d = -3, e = 0.45,

Z the zenith angle of the sky element, Z_s that of the sun and chi the angle between them
(cos Z clamped to >= 1e-6, so the horizon is finite). Colour: a blend from a warm white (half
white, half the sun's colour) near the sun and the horizon to a saturated blue away from both,
normalised to unit Rec.709 luminance so the Perez term alone sets the luminance.

Sun: a von Mises-Fisher lobe of unit energy times the sun's RGB irradiance at normal incidence,

    L_sun(omega) = E_sun C exp(kappa (omega_sun . omega - 1)),   C = kappa / (2 pi (1 - e^{-2 kappa})),

integrated per texel (supersampled near the sun, see :func:`sun_lobe_energy`), so that
sum L_sun dOmega = E_sun to within 1% even for kappa = 8192 on a 64 x 128 grid. E_sun is
extra-terrestrial white attenuated by Rayleigh and aerosol (Angstrom, turbidity) extinction over
the Kasten-Young air mass, hence warmer and dimmer at low elevation.

Absolute scale: the sky's horizontal irradiance (luminance) is r(t) times the sun's luminance at
normal incidence, r(t) = 0.15 + 0.025 (t - 2) clamped to [0.15, 0.25] for turbidity t (hazier
skies are relatively brighter).

References
----------
- ISO 15469:2004(E) / CIE S 011/E:2003. "Spatial Distribution of Daylight - CIE Standard General
  Sky." (the clear sky, type 12, and the CIE overcast sky).
- Kasten, Young. "Revised Optical Air Mass Tables and Approximation Formula." Applied Optics
  28(22), pp. 4735-4738, 1989 (the air mass).
- Preetham, Shirley, Smits. "A Practical Analytic Model for Daylight." Proceedings of
  SIGGRAPH 99, pp. 91-100, 1999 (the Angstrom coefficient of turbidity).
- Fisher. "Dispersion on a Sphere." Proceedings of the Royal Society of London, Series A 217,
  pp. 295-305, 1953 (the von Mises-Fisher sun lobe).
"""

from __future__ import annotations

import math

import numpy as np

from f2l.lighting.grid import LatLongGrid, direction_from_angles

# CIE 2003 standard general sky, type 12 (CIE standard clear sky, low turbidity).
CIE12_A, CIE12_B, CIE12_C, CIE12_D, CIE12_E = -1.0, -0.32, 10.0, -3.0, 0.45

REC709_LUMA = np.array([0.2126, 0.7152, 0.0722])
# Linear-sRGB colour of a deep clear-sky blue (before luminance normalisation).
SKY_BLUE_RGB = np.array([0.20, 0.40, 1.00])
# Effective wavelengths (micrometres) of the R, G, B channels for extinction.
RGB_WAVELENGTHS_UM = np.array([0.61, 0.55, 0.465])

SUN_ELEVATION_RANGE_DEG = (5.0, 80.0)
TURBIDITY_RANGE = (2.0, 6.0)


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(rgb, dtype=np.float64) @ REC709_LUMA


# ---------------------------------------------------------------------------------------------
# Sun lobe
# ---------------------------------------------------------------------------------------------
def vmf_normaliser(kappa: float) -> float:
    """C = kappa / (2 pi (1 - exp(-2 kappa))): the vMF lobe C e^{kappa(cos - 1)} integrates to 1."""
    kappa = float(kappa)
    return kappa / (2.0 * math.pi * (-math.expm1(-2.0 * kappa)))


def _lobe(cos_angle: np.ndarray, kappa: float) -> np.ndarray:
    return vmf_normaliser(kappa) * np.exp(kappa * (np.clip(cos_angle, -1.0, 1.0) - 1.0))


def sun_lobe_energy(grid: LatLongGrid, direction, kappa: float, tail: float = 30.0) -> np.ndarray:
    """Per-texel mean radiance (H, W) float64 of a unit-energy vMF lobe around ``direction``.

    Every texel whose farthest point lies within the lobe's support (exp(kappa (cos a - 1)) >
    e^{-tail}) is integrated numerically: S midpoints in theta times S sub-rows in phi, each
    sub-row with a 3-node Gauss-Legendre rule on sin(phi) dphi, S = clip(ceil(2 dphi
    sqrt(kappa)), 2, 32), so the sub-sample spacing is at most half the lobe's angular sigma
    (1/sqrt(kappa)) and the poles (where the lobe is radial in phi) stay accurate; the
    window is a spherical-distance test, so it widens automatically near the poles. Other texels
    (negligible lobe) are point-sampled. sum(result * grid.solid_angles) = 1 within 1%.
    """
    d = np.asarray(direction, dtype=np.float64).reshape(3)
    d = d / np.linalg.norm(d)
    kappa = float(kappa)
    if kappa <= 0:
        raise ValueError(f"kappa must be positive, got {kappa}")
    H, W = grid.shape
    dirs = grid.directions
    cos_c = dirs @ d
    out = _lobe(cos_c, kappa)

    dphi = math.pi / H
    dtheta = 2.0 * math.pi / W
    edges = grid.phi_edges_rad
    # Upper bound of the geodesic distance from a texel centre to any point of the texel.
    reach = 0.5 * dphi + 0.5 * dtheta * np.maximum(np.sin(edges[:-1]), np.sin(edges[1:]))
    reach = np.minimum(reach, math.pi)
    # Angular radius of the lobe's support.
    one_minus_cos = tail / kappa
    alpha_max = math.pi if one_minus_cos >= 2.0 else math.acos(1.0 - one_minus_cos)
    ang_c = np.arccos(np.clip(cos_c, -1.0, 1.0))
    rows, cols = np.nonzero(ang_c <= alpha_max + reach[:, None])
    if rows.size == 0:
        return out

    S = int(np.clip(math.ceil(2.0 * dphi * math.sqrt(kappa)), 2, 32))
    # phi: S sub-rows, each with a 3-node Gauss-Legendre rule on sin(phi) dphi (the midpoint
    # rule is too coarse at the poles, where the lobe is radial in phi); theta: S midpoints.
    gl_x, gl_w = np.polynomial.legendre.leggauss(3)
    k = np.arange(S)
    h = dphi / S
    nodes = (k[:, None] + 0.5 + 0.5 * gl_x[None, :]).reshape(-1)  # (S*3,) in sub-row units
    wts = np.tile(0.5 * gl_w, S)  # (S*3,), sums to S
    phi_m = edges[rows][:, None] + h * nodes[None, :]  # (K, 3S)
    sub_sa = (dtheta / S) * h * wts[None, :] * np.sin(phi_m)  # (K, 3S)
    theta0 = grid.theta_edges_rad[cols][:, None]
    theta_m = theta0 + dtheta * (k[None, :] + 0.5) / S  # (K,S)
    sp, cp = np.sin(phi_m), np.cos(phi_m)
    st, ct = np.sin(theta_m), np.cos(theta_m)
    # cos angle to the sun for each (phi node i, sub-col j): x = sp st, y = cp, z = -sp ct
    cos_sub = (
        sp[:, :, None] * (d[0] * st[:, None, :] - d[2] * ct[:, None, :]) + (d[1] * cp)[:, :, None]
    )  # (K,3S,S)
    lobe = _lobe(cos_sub, kappa)
    integral = np.einsum("kij,ki->k", lobe, sub_sa)
    out[rows, cols] = integral / grid.solid_angles[rows, cols]
    return out


def sun_rgb_irradiance(sun_elevation_rad: float, turbidity: float) -> np.ndarray:
    """Sun RGB irradiance at normal incidence (3,), extra-terrestrial white (1, 1, 1) attenuated.

    T_c = exp(-m (tau_R(lambda) + beta lambda^-1.3)), Rayleigh tau_R = 0.008569 lambda^-4
    (1 + 0.0113 lambda^-2 + 0.00013 lambda^-4), Angstrom beta = 0.04608 t - 0.04586 (Preetham),
    air mass m from Kasten-Young (1989) at the sun's elevation (clamped to >= 0).
    """
    elev_deg = max(math.degrees(float(sun_elevation_rad)), 0.0)
    m = 1.0 / (math.sin(math.radians(elev_deg)) + 0.50572 * (elev_deg + 6.07995) ** -1.6364)
    lam = RGB_WAVELENGTHS_UM
    tau_r = 0.008569 * lam**-4 * (1.0 + 0.0113 * lam**-2 + 0.00013 * lam**-4)
    beta = max(0.04608 * float(turbidity) - 0.04586, 0.0)
    tau_a = beta * lam**-1.3
    return np.exp(-m * (tau_r + tau_a))


# ---------------------------------------------------------------------------------------------
# Sky models
# ---------------------------------------------------------------------------------------------
def cie_clear_relative_luminance(cos_zenith: np.ndarray, chi_rad: np.ndarray, sun_zenith_rad: float):
    """CIE type-12 clear sky luminance relative to the zenith (Perez form, see module doc).

    cos_zenith is clamped to [1e-6, 1] (finite at and below the horizon).
    """
    cz = np.clip(np.asarray(cos_zenith, dtype=np.float64), 1e-6, 1.0)
    chi = np.asarray(chi_rad, dtype=np.float64)

    def g(c):
        return 1.0 + CIE12_A * np.exp(CIE12_B / c)

    def f(x):
        return (
            1.0
            + CIE12_C * (np.exp(CIE12_D * x) - math.exp(CIE12_D * math.pi / 2.0))
            + CIE12_E * np.cos(x) ** 2
        )

    return f(chi) * g(cz) / (f(float(sun_zenith_rad)) * g(1.0))


def _sky_colour(cos_zenith, chi_rad, sun_rgb, saturation):
    """Unit-luminance RGB (..., 3): warm white near the sun / horizon, blue elsewhere."""
    sun_chroma = sun_rgb / _luminance(sun_rgb)
    white = 0.5 * np.ones(3) + 0.5 * sun_chroma
    white = white / _luminance(white)
    blue = SKY_BLUE_RGB / _luminance(SKY_BLUE_RGB)
    away_from_sun = 1.0 - np.exp(-np.asarray(chi_rad) / 0.5)
    above_horizon = 1.0 - np.exp(-np.clip(cos_zenith, 0.0, 1.0) / 0.15)
    w = (saturation * away_from_sun * above_horizon)[..., None]
    rgb = (1.0 - w) * white + w * blue
    return rgb / _luminance(rgb)[..., None]


_REF_GRID = LatLongGrid(128, 512)


def _relative_horizontal_irradiance(sun_zenith_rad: float, sun_dir: np.ndarray) -> float:
    """sum max(0, y) L_rel dOmega over the upper hemisphere of a fixed fine reference grid."""
    g = _REF_GRID
    dirs = g.directions[: g.sky_rows]
    cz = dirs[..., 1]
    chi = np.arccos(np.clip(dirs @ sun_dir, -1.0, 1.0))
    lrel = cie_clear_relative_luminance(cz, chi, sun_zenith_rad)
    return float(np.sum(lrel * np.maximum(cz, 0.0) * g.solid_angles[: g.sky_rows]))


def sky_to_sun_ratio(turbidity: float) -> float:
    """Sky horizontal irradiance over sun normal irradiance: 0.15 + 0.025 (t - 2), in [0.15, 0.25]."""
    return float(np.clip(0.15 + 0.025 * (float(turbidity) - 2.0), 0.15, 0.25))


def horizontal_irradiance(grid: LatLongGrid, probe: np.ndarray) -> np.ndarray:
    """E_h (3,) = sum over the sky rows of max(0, omega_y) L(omega) dOmega (numerical)."""
    n = grid.sky_rows
    w = np.maximum(grid.directions[:n, :, 1], 0.0) * grid.solid_angles[:n]
    return np.einsum("hwc,hw->c", np.asarray(probe[:n], dtype=np.float64), w)


def _add_ground(grid: LatLongGrid, probe: np.ndarray, ground_albedo: float) -> np.ndarray:
    n = grid.sky_rows
    probe[n:] = 0.0
    e_h = horizontal_irradiance(grid, probe)
    probe[n:] = (float(ground_albedo) / math.pi) * e_h
    return probe


def clear_sky(
    grid: LatLongGrid,
    sun_elevation_rad: float,
    sun_azimuth_rad: float,
    turbidity: float = 3.0,
    sun_kappa: float = 8192.0,
    ground_albedo: float = 0.2,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Clear sky + vMF sun + Lambertian ground, float32 (H, W, 3) linear radiance.

    Sun direction = direction_from_angles(sun_elevation_rad, sun_azimuth_rad) (azimuth 0 = the
    camera's viewing direction -Z, +pi/2 = +X). ``rng`` (optional) jitters the sky's blue
    saturation (x U[0.85, 1.15]) and the sky/sun ratio (+- 0.02); without it everything is a
    deterministic function of the arguments. The sun lobe's part below the horizon is replaced
    by the ground.
    """
    t = float(turbidity)
    sun_dir = direction_from_angles(float(sun_elevation_rad), float(sun_azimuth_rad))
    sun_zenith = math.pi / 2.0 - float(sun_elevation_rad)
    saturation = float(np.clip(0.85 - 0.1 * (t - 2.0), 0.3, 0.95))
    ratio = sky_to_sun_ratio(t)
    if rng is not None:
        saturation = float(np.clip(saturation * rng.uniform(0.85, 1.15), 0.0, 1.0))
        ratio = ratio + rng.uniform(-0.02, 0.02)

    sun_rgb = sun_rgb_irradiance(sun_elevation_rad, t)
    n = grid.sky_rows
    dirs = grid.directions[:n]
    cz = dirs[..., 1]
    chi = np.arccos(np.clip(dirs @ sun_dir, -1.0, 1.0))
    lrel = cie_clear_relative_luminance(cz, chi, sun_zenith)
    scale = ratio * _luminance(sun_rgb) / _relative_horizontal_irradiance(sun_zenith, sun_dir)
    sky = (scale * lrel)[..., None] * _sky_colour(cz, chi, sun_rgb, saturation)

    probe = np.zeros((grid.height, grid.width, 3), dtype=np.float64)
    probe[:n] = sky
    lobe = sun_lobe_energy(grid, sun_dir, sun_kappa)
    probe[:n] += lobe[:n, :, None] * sun_rgb[None, None, :]
    probe = _add_ground(grid, probe, ground_albedo)
    return probe.astype(np.float32)


def overcast_sky(grid: LatLongGrid, brightness: float = 1.0, ground_albedo: float = 0.2) -> np.ndarray:
    """CIE overcast sky L(Z) = brightness (1 + 2 cos Z) / 3 (zenith radiance = brightness),
    neutral white, plus the Lambertian ground; float32 (H, W, 3)."""
    n = grid.sky_rows
    cz = np.clip(grid.directions[:n, :, 1], 0.0, 1.0)
    probe = np.zeros((grid.height, grid.width, 3), dtype=np.float64)
    probe[:n] = (float(brightness) * (1.0 + 2.0 * cz) / 3.0)[..., None]
    probe = _add_ground(grid, probe, ground_albedo)
    return probe.astype(np.float32)


def parse_elevation_range(text: str) -> tuple[float, float]:
    """``"MIN:MAX"`` (degrees) -> (min, max), checked by :func:`check_elevation_range`."""
    parts = str(text).split(":")
    if len(parts) != 2:
        raise ValueError(f"sun elevation range must look like MIN:MAX in degrees, got {text!r}")
    try:
        lo, hi = (float(v) for v in parts)
    except ValueError as exc:
        raise ValueError(f"sun elevation range must look like MIN:MAX in degrees, got {text!r}") from exc
    return check_elevation_range((lo, hi))


def check_elevation_range(range_deg) -> tuple[float, float]:
    """(min, max) sun elevation in degrees as floats; requires 0 <= min <= max <= 90."""
    lo, hi = (float(v) for v in range_deg)
    if not 0.0 <= lo <= hi <= 90.0:
        raise ValueError(f"sun elevation range needs 0 <= MIN <= MAX <= 90 degrees, got {lo:g}:{hi:g}")
    return lo, hi


def random_sky(
    grid: LatLongGrid,
    rng: np.random.Generator,
    overcast_fraction: float = 0.25,
    sun_elevation_range_deg: tuple[float, float] = SUN_ELEVATION_RANGE_DEG,
):
    """A random ground-truth probe and its description.

    Draws (always, in this order, so the stream is the same for both kinds): kind (overcast with
    probability ``overcast_fraction``), sun elevation U[min, max] deg of
    ``sun_elevation_range_deg`` (default [5, 80]; the range only rescales that one draw, so the
    stream of random numbers is the same for every range), azimuth U[-180, 180) deg (the full
    circle, behind the head included), turbidity U[2, 6], then the clear sky's jitter.
    Returns (probe float32 (H, W, 3), info) with info keys kind ('clear'/'overcast'),
    sun_direction (list of 3 floats; None if overcast), sun_elevation_deg, sun_azimuth_deg,
    turbidity (None if overcast), sun_kappa.
    """
    elev_range = check_elevation_range(sun_elevation_range_deg)
    overcast = bool(rng.uniform() < overcast_fraction)
    elev_deg = float(rng.uniform(*elev_range))
    az_deg = float(rng.uniform(-180.0, 180.0))
    turbidity = float(rng.uniform(*TURBIDITY_RANGE))
    sub = np.random.default_rng(rng.integers(0, 2**63 - 1))
    if overcast:
        probe = overcast_sky(grid)
        info = dict(
            kind="overcast",
            sun_direction=None,
            sun_elevation_deg=None,
            sun_azimuth_deg=None,
            turbidity=None,
            sun_kappa=None,
        )
    else:
        kappa = 8192.0
        probe = clear_sky(
            grid, math.radians(elev_deg), math.radians(az_deg), turbidity, kappa, rng=sub
        )
        sun_dir = direction_from_angles(math.radians(elev_deg), math.radians(az_deg))
        info = dict(
            kind="clear",
            sun_direction=[float(x) for x in sun_dir],
            sun_elevation_deg=elev_deg,
            sun_azimuth_deg=az_deg,
            turbidity=turbidity,
            sun_kappa=kappa,
        )
    return probe, info


__all__ = [
    "clear_sky",
    "overcast_sky",
    "random_sky",
    "parse_elevation_range",
    "check_elevation_range",
    "SUN_ELEVATION_RANGE_DEG",
    "sun_lobe_energy",
    "sun_rgb_irradiance",
    "horizontal_irradiance",
    "cie_clear_relative_luminance",
    "vmf_normaliser",
    "sky_to_sun_ratio",
]
