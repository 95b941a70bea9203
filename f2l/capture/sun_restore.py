"""Restore a clipped sun's energy from the unclipped sky (``f2l make-probes --restore-sun``).

Where the sun saturates every frame of a bracket, the merged probe holds only a lower bound there
(often 10⁻³ of the truth). The sky around it is measured, and in a clear sky its luminance
distribution and the sun's brightness are both set by the atmosphere's turbidity. So:

1. Match the probe's covered, unsaturated sky texels (more than ``EXCLUDE_DEG`` from the sun,
   above ``MIN_ELEVATION_DEG``) against Hosek–Wilkie clear skies (Hosek & Wilkie 2012, with the
   solar radiance of 2013, as Mitsuba 3's ``sunsky`` evaluates them) of the same sun elevation:
   log luminance relative to the zenith, tabulated over zenith angle θ and azimuth from the sun φ
   for each tabulated sun elevation × turbidity, interpolated in elevation and in turbidity. The
   turbidity minimising a Huber loss of the log residual (its median being the log zenith
   luminance Y_z in probe units) wins.
2. The sun's energy (illuminance at normal incidence) is that sky's tabulated ratio to its zenith
   luminance, times Y_z; its colour the tabulated sun colour.
3. Energy missing from the saturated texels (restored minus their lower bound, per channel, if
   positive) goes into the texel of the sun's direction (the 0.53° disc lies within one texel).

The table (``f2l/data/sun_table.npz``, ~0.3 MB, made by ``make sun-table``:
:func:`f2l.render.sun_table.build_table`, which needs ``f2l[render]``) ships with f2l, so restoring needs no renderer. Two cheaper routes were
measured and rejected: Preetham's absolute zenith luminance against a Preetham-atmosphere sun gives
0.03-0.56 × Hosek–Wilkie's sun/zenith ratio (too bright a sky, worst for hazy skies and a low sun);
a Perez (Preetham) shape fit's turbidity barely moves (1.94-1.99) over Hosek–Wilkie turbidities
1.5-4 while the ratio falls from 42 to 30, and it leaves 10% median log error.

The result is flagged (a model's estimate, not a measurement: :class:`SunRestoration`). It is
refused, with the reason, when the sky does not look clear (median |log residual| above
``MAX_LOG_RESIDUAL``, or the best turbidity at the table's edge), when too few sky texels are
measured, or when the sun is below the table. On f2l's seven real CC0 outdoor maps (trees,
buildings, clouds and all) it refuses all seven.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

__all__ = ["SunRestoration", "restore_sun", "match_sky", "build_table", "TABLE_FILE"]

EXCLUDE_DEG = 6.0
MIN_ELEVATION_DEG = 3.0
MAX_LOG_RESIDUAL = 0.10
MIN_TEXELS = 200
TURBIDITY_EDGE = 0.01
TABLE_FILE = Path(__file__).resolve().parents[1] / "data" / "sun_table.npz"
TABLE_ELEVATIONS_DEG = (3, 5, 8, 12, 16, 20, 25, 30, 35, 40, 45, 50, 55, 60, 65, 70, 75, 80, 85, 89)
TABLE_TURBIDITIES = (1.5, 2, 2.5, 3, 3.5, 4, 5, 6, 7, 8, 9, 10)
THETA_STEP_DEG, PHI_STEP_DEG = 3.0, 6.0
_LUMA = np.array([0.2126, 0.7152, 0.0722])


@dataclass(frozen=True)
class SunRestoration:
    """``restored``: whether energy was added; the matched sky's ``turbidity`` (Hosek–Wilkie),
    ``zenith_luminance`` (probe units) and ``log_residual`` (median |log residual|); ``sun_energy`` (RGB, probe units × sr:
    the irradiance it gives a surface facing it), ``lower_bound_energy`` (what the saturated texels
    held), ``factor`` (restored / lower-bound luminance), and ``reason`` when not restored."""

    restored: bool
    turbidity: float | None = None
    zenith_luminance: float | None = None
    log_residual: float | None = None
    sun_energy: tuple[float, float, float] | None = None
    lower_bound_energy: tuple[float, float, float] | None = None
    factor: float | None = None
    reason: str = ""

    def message(self) -> str:
        if not self.restored:
            return f"sun not restored: {self.reason}"
        return (f"sun restored from the sky (Hosek-Wilkie turbidity {self.turbidity:.2f}, median |log residual| "
                f"{self.log_residual:.3f}): energy x{self.factor:.3g} its clipped lower bound")


def _sun_frame(sun: np.ndarray):
    """Unit vectors: east-like e1 (horizontal, toward the sun's azimuth) and e2, for φ."""
    horiz = np.array([sun[0], 0.0, sun[2]])
    n = np.linalg.norm(horiz)
    e1 = horiz / n if n > 1e-9 else np.array([0.0, 0.0, -1.0])
    e2 = np.cross(np.array([0.0, 1.0, 0.0]), e1)
    return e1, e2


def theta_phi(directions: np.ndarray, sun: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Zenith angle θ and azimuth from the sun φ in [0, π] (degrees) of world directions."""
    e1, e2 = _sun_frame(sun)
    theta = np.degrees(np.arccos(np.clip(directions[..., 1], -1.0, 1.0)))
    phi = np.degrees(np.abs(np.arctan2(directions @ e2, directions @ e1)))
    return theta, phi


@lru_cache(maxsize=1)
def _table() -> dict:
    with np.load(TABLE_FILE) as z:
        return {k: z[k] for k in z.files}


def _interp_rows(values: np.ndarray, elevs: np.ndarray, elevation_deg: float) -> np.ndarray:
    i = int(np.clip(np.searchsorted(elevs, elevation_deg) - 1, 0, len(elevs) - 2))
    a = (elevation_deg - elevs[i]) / (elevs[i + 1] - elevs[i])
    return (1 - a) * values[i] + a * values[i + 1]


def _template_at(log_rel: np.ndarray, theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Bilinear lookup of (..., n_theta, n_phi) log-luminance templates at (θ, φ) degrees."""
    ti = np.clip(theta / THETA_STEP_DEG, 0, log_rel.shape[-2] - 1 - 1e-9)
    pj = np.clip(phi / PHI_STEP_DEG, 0, log_rel.shape[-1] - 1 - 1e-9)
    i0, j0 = ti.astype(int), pj.astype(int)
    a, b = ti - i0, pj - j0
    return ((1 - a) * (1 - b) * log_rel[..., i0, j0] + a * (1 - b) * log_rel[..., i0 + 1, j0]
            + (1 - a) * b * log_rel[..., i0, j0 + 1] + a * b * log_rel[..., i0 + 1, j0 + 1])


def match_sky(lum: np.ndarray, theta_deg: np.ndarray, phi_deg: np.ndarray, elevation_deg: float):
    """(turbidity, Y_z, median |log residual|, sun energy / Y_z, sun RGB (luminance 1)) of the
    Hosek–Wilkie sky that best matches sky texels' luminance, or None below the table."""
    table = _table()
    elevs = table["elevation_deg"]
    if not elevs[0] <= elevation_deg <= elevs[-1]:
        return None
    log_rel = _interp_rows(table["log_rel"].astype(np.float64), elevs, elevation_deg)  # (T, nθ, nφ)
    log_ratio = _interp_rows(np.log(table["sun_over_zenith"]), elevs, elevation_deg)  # (T,)
    rgb = _interp_rows(table["sun_rgb"], elevs, elevation_deg)  # (T, 3)
    turb = table["turbidity"]
    models = _template_at(log_rel, theta_deg, phi_deg)  # (T, N)
    log_lum = np.log(lum)

    def fit(w: float):  # templates linear in turbidity between neighbours
        k = int(np.clip(np.searchsorted(turb, w) - 1, 0, len(turb) - 2))
        a = (w - turb[k]) / (turb[k + 1] - turb[k])
        r = log_lum - ((1 - a) * models[k] + a * models[k + 1])
        off = float(np.median(r))
        return r - off, off, k, a

    def cost(w: float) -> float:
        r = np.abs(fit(w)[0])
        return float(np.mean(np.where(r < 0.1, 0.5 * r * r, 0.1 * (r - 0.05))))

    from scipy.optimize import minimize_scalar

    coarse = turb[int(np.argmin([cost(float(t)) for t in turb]))]
    lo, hi = float(max(turb[0], coarse - 1.0)), float(min(turb[-1], coarse + 1.0))
    w = float(minimize_scalar(cost, bounds=(lo, hi), method="bounded", options={"xatol": 1e-3}).x)
    r, off, k, a = fit(w)
    ratio = math.exp((1 - a) * log_ratio[k] + a * log_ratio[k + 1])
    colour = (1 - a) * rgb[k] + a * rgb[k + 1]
    return w, math.exp(off), float(np.median(np.abs(r))), ratio, colour / float(colour @ _LUMA)


def restore_sun(probe: np.ndarray, saturated: np.ndarray, coverage: np.ndarray, sun_direction: np.ndarray,
                grid) -> tuple[np.ndarray, SunRestoration]:
    """(probe with the sun's energy restored, or unchanged; what was done). ``probe`` (H, W, 3)
    linear Rec.709 on ``grid``; ``saturated`` texels hold lower bounds; ``coverage`` the seen ones."""
    sun = np.asarray(sun_direction, dtype=np.float64)
    sun = sun / np.linalg.norm(sun)
    elevation = math.degrees(math.asin(float(np.clip(sun[1], -1, 1))))
    if not saturated.any():
        return probe, SunRestoration(False, reason="no texel is saturated: nothing to restore")
    d = grid.directions
    gamma = np.degrees(np.arccos(np.clip(d @ sun, -1.0, 1.0)))
    lum = probe.astype(np.float64) @ _LUMA
    keep = (coverage & ~saturated & (gamma > EXCLUDE_DEG) & (lum > 0)
            & (np.degrees(np.arcsin(np.clip(d[..., 1], -1, 1))) > MIN_ELEVATION_DEG))
    if int(keep.sum()) < MIN_TEXELS:
        return probe, SunRestoration(False, reason=f"only {int(keep.sum())} measured sky texels (need {MIN_TEXELS})")
    theta, phi = theta_phi(d[keep], sun)
    found = match_sky(lum[keep], theta, phi, elevation)
    if found is None:
        return probe, SunRestoration(False, reason=f"sun at {elevation:.1f}° elevation, below the table")
    t, yz, resid, ratio, rgb = found
    sa = grid.solid_angles
    lower = tuple(float(v) for v in (probe[saturated] * sa[saturated][:, None]).sum(axis=0))
    info = {"turbidity": t, "zenith_luminance": yz, "log_residual": resid, "lower_bound_energy": lower}
    if resid > MAX_LOG_RESIDUAL:
        return probe, SunRestoration(False, **info, reason=f"the sky does not match a clear sky (median |log residual| "
                                                           f"{resid:.2f} > {MAX_LOG_RESIDUAL})")
    lo, hi = (float(v) for v in _table()["turbidity"][[0, -1]])
    if not lo + TURBIDITY_EDGE < t < hi - TURBIDITY_EDGE:
        return probe, SunRestoration(False, **info, reason=f"the matched turbidity {t:.2f} is at the edge of the "
                                                           "table (the sky is outside what it covers)")
    energy = ratio * yz * rgb
    missing = np.maximum(energy - np.asarray(lower), 0.0)
    out = probe.copy()
    row, col = grid.direction_to_texel(sun)
    out[int(row), int(col)] += (missing / sa[int(row), int(col)]).astype(out.dtype)
    factor = float((energy @ _LUMA) / max(float(np.asarray(lower) @ _LUMA), 1e-300))
    return out, SunRestoration(True, **info, sun_energy=tuple(float(v) for v in energy), factor=factor)
