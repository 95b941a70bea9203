"""Whether estimates' sun uncertainty can be trusted: calibration of their credible sun cones
(f2l.estimate.uncertainty) and a risk–coverage curve, from per-face rows.

A row is a dict with the true sun's angular error ``"Sun-ang (°)"`` (:mod:`f2l.metrics.lighting`)
and the estimate's ``sun_cone68_deg`` / ``sun_cone90_deg`` (estimates.parquet); rows where any of
them is missing or NaN (overcast truth, a model without a sun cone) are left out.

- :func:`cone_coverage`: the share of faces whose true sun lies inside the 68% and the 90% cone
  (calibrated cones: about 0.68 and 0.90);
- :func:`risk_coverage`: the faces sorted by their 90% cone, narrowest (most confident) first;
  for each fraction f the mean Sun-ang of the ceil(f n) most confident (a useful confidence:
  falling as f falls);
- :func:`calibration_table`: both per method, with the predicted relit error against the
  measured one, as Markdown.

References: selective prediction's risk–coverage curve (Geifman & El-Yaniv 2017); the metric
Sun-ang of Calian et al. 2018, §5.1.
"""

from __future__ import annotations

import math
from collections import defaultdict

import numpy as np

__all__ = ["ANGLE", "CONE68", "CONE90", "FRACTIONS", "usable", "cone_coverage", "risk_coverage",
           "calibration_table", "predicted_vs_measured"]

ANGLE, CONE68, CONE90 = "Sun-ang (°)", "sun_cone68_deg", "sun_cone90_deg"
FRACTIONS = (1.0, 0.75, 0.5, 0.25)


def _finite(value) -> bool:
    try:
        return value is not None and math.isfinite(float(value))
    except (TypeError, ValueError):
        return False


def usable(rows: list[dict]) -> list[dict]:
    """The rows with a finite Sun-ang and both cones."""
    return [r for r in rows if all(_finite(r.get(k)) for k in (ANGLE, CONE68, CONE90))]


def cone_coverage(rows: list[dict]) -> dict:
    """{"n", "inside 68%", "inside 90%"}: how many usable rows, and the share whose Sun-ang is at
    most their 68% (90%) cone radius (NaN when none is usable).

    >>> cone_coverage([{"Sun-ang (°)": 3, "sun_cone68_deg": 4, "sun_cone90_deg": 6},
    ...                {"Sun-ang (°)": 5, "sun_cone68_deg": 4, "sun_cone90_deg": 6}])
    {'n': 2, 'inside 68%': 0.5, 'inside 90%': 1.0}
    """
    rs = usable(rows)
    if not rs:
        return {"n": 0, "inside 68%": math.nan, "inside 90%": math.nan}
    angle = np.array([float(r[ANGLE]) for r in rs])
    return {"n": len(rs),
            "inside 68%": float(np.mean(angle <= np.array([float(r[CONE68]) for r in rs]))),
            "inside 90%": float(np.mean(angle <= np.array([float(r[CONE90]) for r in rs])))}


def risk_coverage(rows: list[dict], fractions=FRACTIONS) -> list[tuple[float, int, float]]:
    """(fraction, faces kept, mean Sun-ang) per fraction: the usable rows sorted by their 90% cone
    (narrowest first, ties in input order), the ceil(fraction n) first kept.

    >>> rows = [{"Sun-ang (°)": a, "sun_cone68_deg": c, "sun_cone90_deg": c} for a, c in ((40, 30), (2, 3), (6, 5), (10, 8))]
    >>> risk_coverage(rows, (1.0, 0.5, 0.25))
    [(1.0, 4, 14.5), (0.5, 2, 4.0), (0.25, 1, 2.0)]
    """
    rs = usable(rows)
    order = sorted(range(len(rs)), key=lambda i: (float(rs[i][CONE90]), i))
    angle = np.array([float(rs[i][ANGLE]) for i in order])
    out = []
    for f in fractions:
        k = min(len(rs), int(math.ceil(f * len(rs) - 1e-9)))
        out.append((float(f), k, float(angle[:k].mean()) if k else math.nan))
    return out


def _fmt(x: float, digits: int = 3) -> str:
    return "—" if x is None or math.isnan(x) else f"{x:.{digits}g}"


def calibration_table(rows: list[dict], key: str = "method", fractions=FRACTIONS) -> str:
    """Markdown: per ``key`` value with usable rows, the faces, the shares inside the 68% and 90%
    cones, the median cone radii and the mean Sun-ang of the most confident fractions."""
    by = defaultdict(list)
    for r in usable(rows):
        by[r[key]].append(r)
    head = [key, "faces", "inside 68% cone", "inside 90% cone", "median 68% / 90% cone (°)",
            *[f"mean Sun-ang, most confident {f:.0%} (°)" for f in fractions],
            "MAE (s) predicted / measured (mean)", "rank corr. (predicted, measured MAE (s))"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name in sorted(by):
        rs = by[name]
        cov = cone_coverage(rs)
        cones = f"{_fmt(float(np.median([r[CONE68] for r in rs])))} / {_fmt(float(np.median([r[CONE90] for r in rs])))}"
        risks = [_fmt(m) for _, _, m in risk_coverage(rs, fractions)]
        pred, mae = predicted_vs_measured(rs)
        lines.append(f"| {name} | {cov['n']} | {cov['inside 68%']:.0%} | {cov['inside 90%']:.0%} | {cones} | "
                     + " | ".join(risks) + f" | {pred} | {mae} |")
    return "\n".join(lines)


def predicted_vs_measured(rows: list[dict]) -> tuple[str, str]:
    """("mean predicted / mean measured MAE (s)", "Spearman rank correlation") over the rows with
    both ``predicted_mae_s`` and ``MAE (s)`` ("—" when fewer than 3)."""
    from scipy.stats import spearmanr

    pairs = [(float(r["predicted_mae_s"]), float(r["MAE (s)"])) for r in rows
             if _finite(r.get("predicted_mae_s")) and _finite(r.get("MAE (s)"))]
    if len(pairs) < 3:
        return "—", "—"
    p, m = np.array(pairs).T
    rho = spearmanr(p, m).statistic if np.ptp(p) > 0 and np.ptp(m) > 0 else math.nan
    return f"{_fmt(float(p.mean()))} / {_fmt(float(m.mean()))}", _fmt(float(rho), 2)
