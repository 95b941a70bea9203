"""Probe metrics "(l)", sun direction and the overcast heuristic (Calian et al. 2018, §5.1).

Conventions (see ``docs/metrics.md``): probes are (H, W, 3) linear RGB on a
:class:`~f2l.lighting.grid.LatLongGrid`; ``dΩ`` is the texel solid angle; "upper" is the upper
hemisphere ``grid.upper_mask`` (the first H/2 rows, Σ dΩ = 2π exactly). Luminance uses the
Rec.709 weights ``Y = 0.2126 R + 0.7152 G + 0.0722 B``. Angles are radians inside, degrees in
the metric values and keyword names ending in ``_deg``.

* normalisation: ``l ← l / Σ_{ω∈upper, c} l_c(ω) dΩ`` (a probe with no positive upper energy
  becomes all zeros);
* ``dω-MAE(R) = Σ_{ω∈R, c} |l̂_c(ω) − l*_c(ω)| dΩ / (3 Σ_{ω∈R} dΩ)`` on normalised probes;
* regions: Full = upper; Sun = upper ∩ cap(13°) around the centre of the brightest (max Y)
  upper texel of the ground truth; Sky = Full \\ Sun. Cap membership is by texel centre.

References
----------
- Calian, Lalonde, Gotardo, Simon, Matthews, Mitchell. "From Faces to Outdoor Light Probes."
  Computer Graphics Forum (Eurographics) 37(2), 2018 (§5.1: the lighting metrics "(l)" and the
  sun angle).
"""

from __future__ import annotations

import numpy as np

from f2l.lighting.grid import LatLongGrid
from f2l.lighting.sun import (LUMA_709, SUN_CAP_DEG, SUN_WINDOW_DEG, _check, brightest_direction,  # noqa: F401
                             cap_mask, luminance, sun_direction)

__all__ = [
    "LUMA_709",
    "SUN_CAP_DEG",
    "SUN_WINDOW_DEG",
    "OVERCAST_THRESHOLD",
    "PROBE_METRIC_NAMES",
    "luminance",
    "normalise_probe",
    "brightest_direction",
    "sun_direction",
    "cap_mask",
    "sun_energy_fraction",
    "is_overcast",
    "weighted_mae",
    "angle_deg",
    "probe_metrics",
]

OVERCAST_THRESHOLD = 0.15
PROBE_METRIC_NAMES = ("Full-dω MAE (l)", "Sky-dω MAE (l)", "Sun-dω MAE (l)", "Sun-ang (°)")


def upper_energy(probe: np.ndarray, grid: LatLongGrid) -> float:
    """``Σ_{ω∈upper, c} l_c(ω) dΩ``.

    >>> round(upper_energy(np.ones((16, 32, 3)), LatLongGrid(16, 32)) / np.pi, 9)  # 3 channels x 2 pi
    6.0
    """
    p = _check(probe, grid)
    return float(np.sum(p.sum(-1) * grid.solid_angles * grid.upper_mask))


def normalise_probe(probe: np.ndarray, grid: LatLongGrid) -> np.ndarray:
    """Scale ``probe`` so that ``Σ_{ω∈upper, c} l_c(ω) dΩ = 1`` (float64, all-zero if energy <= 0).

    >>> grid = LatLongGrid(16, 32)
    >>> round(upper_energy(normalise_probe(np.full((16, 32, 3), 7.0), grid), grid), 9)
    1.0
    >>> float(np.abs(normalise_probe(np.zeros((16, 32, 3)), grid)).max())
    0.0
    """
    p = _check(probe, grid)
    e = upper_energy(p, grid)
    if not np.isfinite(e):
        return np.full_like(p, np.nan)
    return p / e if e > 0 else np.zeros_like(p)


def sun_energy_fraction(
    probe: np.ndarray, grid: LatLongGrid, radius_deg: float = SUN_CAP_DEG
) -> float:
    """Fraction of the upper energy ``Σ_c l_c dΩ`` inside the cap around the brightest upper texel.

    >>> grid = LatLongGrid(16, 32)
    >>> clear = np.ones((16, 32, 3))
    >>> clear[3, 20] = 2000.0  # a sun
    >>> round(sun_energy_fraction(clear, grid), 3), round(sun_energy_fraction(np.ones((16, 32, 3)), grid), 3)
    (0.889, 0.032)
    """
    p = _check(probe, grid)
    _, d0 = brightest_direction(p, grid)
    e = p.sum(-1) * grid.solid_angles * grid.upper_mask
    tot = float(e.sum())
    if not tot > 0:
        return 0.0
    return float(e[cap_mask(grid, d0, radius_deg)].sum() / tot)


def is_overcast(
    probe: np.ndarray,
    grid: LatLongGrid,
    threshold: float = OVERCAST_THRESHOLD,
    radius_deg: float = SUN_CAP_DEG,
) -> bool:
    """Heuristic: overcast iff ``sun_energy_fraction(probe) < threshold`` (0.15, 13° cap).

    A uniform sky scores ``1 − cos 13° ≈ 0.026`` (overcast); a clear sky whose sun carries at least
    15% of the upper-hemisphere energy is not overcast. A probe with no energy is overcast.

    >>> grid = LatLongGrid(16, 32)
    >>> clear = np.ones((16, 32, 3))
    >>> clear[3, 20] = 2000.0
    >>> is_overcast(np.ones((16, 32, 3)), grid), is_overcast(clear, grid), is_overcast(np.zeros((16, 32, 3)), grid)
    (True, False, True)
    """
    return sun_energy_fraction(probe, grid, radius_deg) < threshold


def weighted_mae(a: np.ndarray, b: np.ndarray, grid: LatLongGrid, region: np.ndarray) -> float:
    """``Σ_{ω∈R, c} |a − b| dΩ / (3 Σ_{ω∈R} dΩ)``; NaN for an empty region.

    >>> grid = LatLongGrid(16, 32)
    >>> a, b = np.zeros((16, 32, 3)), np.full((16, 32, 3), 0.5)
    >>> round(weighted_mae(a, b, grid, grid.upper_mask), 9)
    0.5
    >>> weighted_mae(a, b, grid, np.zeros((16, 32), bool))
    nan
    """
    sa = grid.solid_angles * region
    den = 3.0 * float(sa.sum())
    if den <= 0:
        return float("nan")
    return float(np.sum(np.abs(a - b).sum(-1) * sa) / den)


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two directions in degrees (atan2 form, accurate near 0°).

    >>> angle_deg([1.0, 0.0, 0.0], [0.0, 2.0, 0.0]), angle_deg([0.0, 0.0, -1.0], [0.0, 0.0, -1.0])
    (90.0, 0.0)
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), float(a @ b))))


def probe_metrics(
    est: np.ndarray,
    gt: np.ndarray,
    grid: LatLongGrid,
    overcast: bool | None = None,
    est_sun_dir: np.ndarray | None = None,
    gt_sun_dir: np.ndarray | None = None,
) -> dict[str, float]:
    """Full/Sky/Sun-dω MAE (l) and Sun-ang (°) of ``est`` against ``gt`` (both (H, W, 3)).

    ``overcast=None`` applies :func:`is_overcast` to ``gt``; if overcast, "Sun-dω MAE (l)" and
    "Sun-ang (°)" are NaN. Sun directions default to :func:`sun_direction` of each probe; pass
    ``est_sun_dir`` / ``gt_sun_dir`` (unit vectors, grid frame) to use explicit ones (they affect
    Sun-ang only; the Sun/Sky regions always centre on gt's brightest texel).
    Raises ``ValueError`` if ``gt`` has no positive upper-hemisphere energy.

    The probe metrics ignore scale; an overcast ground truth has no sun metrics:

    >>> grid = LatLongGrid(16, 32)
    >>> clear = np.ones((16, 32, 3))
    >>> clear[3, 20] = 2000.0
    >>> {name: round(value, 9) for name, value in probe_metrics(5.0 * clear, clear, grid).items()}
    {'Full-dω MAE (l)': 0.0, 'Sky-dω MAE (l)': 0.0, 'Sun-dω MAE (l)': 0.0, 'Sun-ang (°)': 0.0}
    >>> probe_metrics(clear, np.ones((16, 32, 3)), grid)["Sun-ang (°)"]
    nan
    """
    est = _check(est, grid)
    gt = _check(gt, grid)
    if not upper_energy(gt, grid) > 0:
        raise ValueError("ground-truth probe has no positive upper-hemisphere energy")
    a = normalise_probe(est, grid)
    b = normalise_probe(gt, grid)
    upper = np.asarray(grid.upper_mask)
    _, d0 = brightest_direction(gt, grid)
    sun = cap_mask(grid, d0) & upper
    sky = upper & ~sun
    if overcast is None:
        overcast = is_overcast(gt, grid)
    out = {
        "Full-dω MAE (l)": weighted_mae(a, b, grid, upper),
        "Sky-dω MAE (l)": weighted_mae(a, b, grid, sky),
        "Sun-dω MAE (l)": float("nan"),
        "Sun-ang (°)": float("nan"),
    }
    if not overcast:
        out["Sun-dω MAE (l)"] = weighted_mae(a, b, grid, sun)
        de = sun_direction(est, grid) if est_sun_dir is None else est_sun_dir
        dg = sun_direction(gt, grid) if gt_sun_dir is None else gt_sun_dir
        out["Sun-ang (°)"] = angle_deg(de, dg)
    return out
