"""Evaluation metrics of Calian et al. 2018, §5.1, with an explicit protocol (``docs/metrics.md``).

Per (estimated, ground-truth) probe pair on one :class:`~f2l.lighting.grid.LatLongGrid`,
:func:`evaluate_pair` returns the seven :data:`METRIC_NAMES`:

* "MAE (s)", "RMSE (s)", "si-RMSE (s)" — renderings of a fixed sphere-on-plane scene, each
  normalised to mean 1 (:mod:`f2l.metrics.render_metrics`, :mod:`f2l.metrics.scene`);
* "Full-dω MAE (l)", "Sky-dω MAE (l)", "Sun-dω MAE (l)" — solid-angle-weighted MAE of probes
  normalised to unit upper-hemisphere energy, over the upper hemisphere / it minus the 13° cap
  around gt's brightest texel / that cap (:mod:`f2l.metrics.lighting`);
* "Sun-ang (°)" — angle between the sun directions.

Sun metrics are NaN for overcast ground truth. :func:`summarise` aggregates rows per model
(mean ± sample std over the non-NaN values, with counts); :func:`to_markdown` / :func:`to_csv`
write the table.
"""

from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from f2l.lighting.grid import LatLongGrid
from f2l.metrics.lighting import (
    cap_mask,
    is_overcast,
    normalise_probe,
    probe_metrics,
    sun_direction,
)

__all__ = [
    "METRIC_NAMES",
    "RUNTIME_KEY",
    "Stat",
    "SummaryTable",
    "evaluate_pair",
    "summarise",
    "to_markdown",
    "to_csv",
    "cap_mask",
    "is_overcast",
    "normalise_probe",
    "probe_metrics",
    "sun_direction",
    "rendering_metrics",
    "render_scene",
]

METRIC_NAMES: tuple[str, ...] = (
    "MAE (s)",
    "RMSE (s)",
    "si-RMSE (s)",
    "Full-dω MAE (l)",
    "Sky-dω MAE (l)",
    "Sun-dω MAE (l)",
    "Sun-ang (°)",
)
RUNTIME_KEY = "runtime_s"


def rendering_metrics(est_probe, gt_probe, grid=None):
    """See :func:`f2l.metrics.render_metrics.rendering_metrics` (lazy import: embree/trimesh)."""
    from f2l.metrics.render_metrics import rendering_metrics as _rm

    return _rm(est_probe, gt_probe, grid)


def render_scene(probe, grid=None):
    """See :func:`f2l.metrics.scene.render_scene`."""
    from f2l.metrics.scene import render_scene as _rs

    return _rs(probe, grid)


def evaluate_pair(
    est_probe: np.ndarray,
    gt_probe: np.ndarray,
    grid: LatLongGrid | None = None,
    overcast: bool | None = None,
    est_sun_dir: np.ndarray | None = None,
    gt_sun_dir: np.ndarray | None = None,
) -> dict[str, float]:
    """All seven metrics (keys :data:`METRIC_NAMES`, in order) for one probe pair (H, W, 3).

    ``grid`` defaults to ``LatLongGrid(H, W)``; ``overcast=None`` uses :func:`is_overcast` on gt.
    """
    gt_probe = np.asarray(gt_probe)
    if grid is None:
        grid = LatLongGrid(gt_probe.shape[0], gt_probe.shape[1])
    vals = rendering_metrics(est_probe, gt_probe, grid)
    vals.update(probe_metrics(est_probe, gt_probe, grid, overcast, est_sun_dir, gt_sun_dir))
    return {k: float(vals[k]) for k in METRIC_NAMES}


# -- aggregation -------------------------------------------------------------------------------
@dataclass(frozen=True)
class Stat:
    """Mean and sample standard deviation (ddof = 1; NaN if count < 2) of the non-NaN values."""

    mean: float
    std: float
    count: int


@dataclass
class SummaryTable:
    """Per-group summary: ``groups[g][metric] -> Stat``, ``n_rows[g]`` rows per group.

    ``metrics`` lists the summarised columns: the METRIC_NAMES present in any row, in order, then
    ``runtime_s`` if present. Groups keep their order of first appearance.
    """

    by: str
    metrics: list[str]
    groups: dict[str, dict[str, Stat]] = field(default_factory=dict)
    n_rows: dict[str, int] = field(default_factory=dict)


def _as_float(v) -> float:
    if v is None:
        return math.nan
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def _stat(values: list[float]) -> Stat:
    x = np.asarray(values, dtype=np.float64)
    x = x[np.isfinite(x)]
    n = int(x.size)
    if n == 0:
        return Stat(math.nan, math.nan, 0)
    return Stat(float(x.mean()), float(x.std(ddof=1)) if n > 1 else math.nan, n)


def summarise(rows: list[dict], by: str = "model") -> SummaryTable:
    """Mean ± std per ``row[by]`` of each metric (and ``runtime_s``); NaN/None/±inf are ignored
    and each cell keeps the count of values it used."""
    present = [m for m in METRIC_NAMES if any(m in r for r in rows)]
    if any(RUNTIME_KEY in r for r in rows):
        present.append(RUNTIME_KEY)
    table = SummaryTable(by=by, metrics=present)
    buckets: dict[str, list[dict]] = {}
    for r in rows:
        buckets.setdefault(str(r.get(by)), []).append(r)
    for g, rs in buckets.items():
        table.n_rows[g] = len(rs)
        table.groups[g] = {m: _stat([_as_float(r.get(m)) for r in rs]) for m in present}
    return table


def _fmt(x: float) -> str:
    return "nan" if not np.isfinite(x) else f"{x:.4g}"


def to_markdown(table: SummaryTable) -> str:
    """Markdown table: one row per group, cells ``mean ± std``; `` (n=k)`` is appended when a cell
    used fewer values than the group has rows (e.g. sun metrics without overcast faces)."""
    head = [table.by, "n", *table.metrics]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] * len(head)) + "|"]
    for g, stats in table.groups.items():
        n = table.n_rows[g]
        cells = [g, str(n)]
        for m in table.metrics:
            s = stats[m]
            if s.count == 0:
                cells.append("—")
                continue
            c = _fmt(s.mean) if not np.isfinite(s.std) else f"{_fmt(s.mean)} ± {_fmt(s.std)}"
            if s.count < n:
                c += f" (n={s.count})"
            cells.append(c)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def to_csv(table: SummaryTable, path: str | os.PathLike) -> Path:
    """Write a CSV (UTF-8) with columns ``<by>, n, <metric> mean, <metric> std, <metric> n, …``;
    written to a temporary name then renamed. Returns the path."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        hdr = [table.by, "n"]
        for m in table.metrics:
            hdr += [f"{m} mean", f"{m} std", f"{m} n"]
        w.writerow(hdr)
        for g, stats in table.groups.items():
            row: list = [g, table.n_rows[g]]
            for m in table.metrics:
                s = stats[m]
                row += [repr(s.mean), repr(s.std), s.count]
            w.writerow(row)
    os.replace(tmp, path)
    return path
