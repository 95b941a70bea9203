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
(mean ± sample std over the non-NaN values, with counts, plus the median of
:data:`MEDIAN_METRICS`, and, where rows carry sun shares (:mod:`f2l.metrics.sun_share`), the
overcast faces whose estimated sun share exceeds the ground truth's by more than 0.1);
:func:`to_markdown` / :func:`to_csv` / :func:`summary_records` write the table.

References
----------
- Calian, Lalonde, Gotardo, Simon, Matthews, Mitchell. "From Faces to Outdoor Light Probes."
  Computer Graphics Forum (Eurographics) 37(2), 2018 (§5.1: the evaluation metrics).
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
from f2l.metrics.sun_share import (
    GT_OVERCAST,
    SUN_SHARE_EST,
    SUN_SHARE_GT,
    SUN_SHARE_MARGIN,
    OvercastExcess,
    overcast_excess,
)

__all__ = [
    "METRIC_NAMES",
    "MEDIAN_METRICS",
    "RUNTIME_KEY",
    "Stat",
    "SummaryTable",
    "evaluate_pair",
    "summarise",
    "summary_records",
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
# Metrics whose median the summary reports next to mean ± std (robust to a few flipped suns).
MEDIAN_METRICS: tuple[str, ...] = ("Sun-dω MAE (l)", "Sun-ang (°)")


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

    >>> gt = np.ones((8, 16, 3))  # a small grid keeps the rendering scene quick to build
    >>> gt[1, 5] = 500.0
    >>> metrics = evaluate_pair(2.0 * gt, gt)  # right up to scale: every metric is 0
    >>> list(metrics) == list(METRIC_NAMES), max(round(v, 4) for v in metrics.values())
    (True, 0.0)
    >>> metrics = evaluate_pair(np.ones((8, 16, 3)), gt)  # the sun missed
    >>> round(metrics["Sun-dω MAE (l)"], 3), round(metrics["Sun-ang (°)"], 2)
    (1.152, 38.96)
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
    """Mean, sample standard deviation (ddof = 1; NaN if count < 2) and median of the non-NaN
    values (NaN if there are none)."""

    mean: float
    std: float
    count: int
    median: float = math.nan


@dataclass
class SummaryTable:
    """Per-group summary: ``groups[g][metric] -> Stat``, ``n_rows[g]`` rows per group.

    ``metrics`` lists the summarised columns: the METRIC_NAMES present in any row, in order, then
    ``runtime_s`` if present. ``medians`` lists the :data:`MEDIAN_METRICS` among them (their
    ``Stat.median`` is reported). ``overcast[g]`` is the group's :class:`OvercastExcess`, present
    only when some row carries sun shares. Groups keep their order of first appearance.
    """

    by: str
    metrics: list[str]
    groups: dict[str, dict[str, Stat]] = field(default_factory=dict)
    n_rows: dict[str, int] = field(default_factory=dict)
    medians: list[str] = field(default_factory=list)
    overcast: dict[str, OvercastExcess] = field(default_factory=dict)


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
    return Stat(float(x.mean()), float(x.std(ddof=1)) if n > 1 else math.nan, n, float(np.median(x)))


def _has_sun_shares(rows: list[dict]) -> bool:
    return any(all(k in r for k in (GT_OVERCAST, SUN_SHARE_EST, SUN_SHARE_GT)) for r in rows)


def summarise(rows: list[dict], by: str = "model") -> SummaryTable:
    """Mean ± std (and median) per ``row[by]`` of each metric (and ``runtime_s``); NaN/None/±inf
    are ignored and each cell keeps the count of values it used. Rows with ``gt_overcast``,
    ``sun_share_est`` and ``sun_share_gt`` also give each group its :class:`OvercastExcess`.

    >>> rows = [{"model": "a", "MAE (s)": 0.1}, {"model": "a", "MAE (s)": 0.3},
    ...         {"model": "a", "MAE (s)": float("nan")}, {"model": "b", "MAE (s)": 0.2}]
    >>> table = summarise(rows)
    >>> table.metrics, table.n_rows
    (['MAE (s)'], {'a': 3, 'b': 1})
    >>> s = table.groups["a"]["MAE (s)"]
    >>> round(s.mean, 6), round(s.std, 6), s.count  # NaN is left out
    (0.2, 0.141421, 2)
    """
    present = [m for m in METRIC_NAMES if any(m in r for r in rows)]
    if any(RUNTIME_KEY in r for r in rows):
        present.append(RUNTIME_KEY)
    table = SummaryTable(by=by, metrics=present, medians=[m for m in MEDIAN_METRICS if m in present])
    with_shares = _has_sun_shares(rows)
    buckets: dict[str, list[dict]] = {}
    for r in rows:
        buckets.setdefault(str(r.get(by)), []).append(r)
    for g, rs in buckets.items():
        table.n_rows[g] = len(rs)
        table.groups[g] = {m: _stat([_as_float(r.get(m)) for r in rs]) for m in present}
        if with_shares:
            table.overcast[g] = overcast_excess(rs)
    return table


def _fmt(x: float) -> str:
    return "nan" if not np.isfinite(x) else f"{x:.4g}"


_EXCESS_HEAD = f"overcast: est sun share > gt + {SUN_SHARE_MARGIN:g}"
_MAX_EXCESS_HEAD = "overcast: max(est − gt sun share)"


def _mean_std_cell(s: Stat, n: int) -> str:
    if s.count == 0:
        return "—"
    c = _fmt(s.mean) if not np.isfinite(s.std) else f"{_fmt(s.mean)} ± {_fmt(s.std)}"
    return c + (f" (n={s.count})" if s.count < n else "")


def _excess_cells(o: OvercastExcess) -> list[str]:
    if o.n == 0:
        return ["—", "—"]
    return [f"{o.exceed}/{o.n} ({o.fraction:.0%})", _fmt(o.max_excess)]


def to_markdown(table: SummaryTable) -> str:
    """Markdown table: one row per group, cells ``mean ± std``; `` (n=k)`` is appended when a cell
    used fewer values than the group has rows (e.g. sun metrics without overcast faces). Then one
    ``median <metric>`` column per ``table.medians`` and, when ``table.overcast`` is set, the
    overcast faces exceeding the gt sun share by the margin (``k/n (fraction)``) and the largest
    excess; ``—`` where a group has no value.

    >>> rows = [{"model": "a", "MAE (s)": 0.1}, {"model": "a", "MAE (s)": 0.3},
    ...         {"model": "b", "MAE (s)": 0.2, "runtime_s": 1.5}]
    >>> print(to_markdown(summarise(rows)))
    | model | n | MAE (s) | runtime_s |
    |---|---|---|---|
    | a | 2 | 0.2 ± 0.1414 | — |
    | b | 1 | 0.2 | 1.5 |
    <BLANKLINE>
    """
    head = [table.by, "n", *table.metrics, *(f"median {m}" for m in table.medians)]
    if table.overcast:
        head += [_EXCESS_HEAD, _MAX_EXCESS_HEAD]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] * len(head)) + "|"]
    for g, stats in table.groups.items():
        n = table.n_rows[g]
        cells = [g, str(n), *(_mean_std_cell(stats[m], n) for m in table.metrics)]
        cells += ["—" if stats[m].count == 0 else _fmt(stats[m].median) for m in table.medians]
        if table.overcast:
            cells += _excess_cells(table.overcast[g])
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def summary_records(table: SummaryTable) -> list[dict]:
    """One dict per group, keys in column order: ``<by>, n, <metric> mean, <metric> std,
    <metric> n`` for each metric, ``<metric> median`` for each of ``table.medians`` and, when
    ``table.overcast`` is set, ``overcast n``, ``overcast sun share excess count`` (est share >
    gt share + 0.1), ``overcast sun share excess fraction`` and ``overcast sun share excess max``
    (max of est − gt share). Missing values are NaN.

    >>> summary_records(summarise([{"model": "a", "MAE (s)": 0.5}]))
    [{'model': 'a', 'n': 1, 'MAE (s) mean': 0.5, 'MAE (s) std': nan, 'MAE (s) n': 1}]
    """
    records = []
    for g, stats in table.groups.items():
        rec: dict = {table.by: g, "n": table.n_rows[g]}
        for m in table.metrics:
            s = stats[m]
            rec.update({f"{m} mean": s.mean, f"{m} std": s.std, f"{m} n": s.count})
        rec.update({f"{m} median": stats[m].median for m in table.medians})
        if table.overcast:
            o = table.overcast[g]
            rec.update({
                "overcast n": o.n, "overcast sun share excess count": o.exceed,
                "overcast sun share excess fraction": o.fraction,
                "overcast sun share excess max": o.max_excess,
            })
        records.append(rec)
    return records


def to_csv(table: SummaryTable, path: str | os.PathLike) -> Path:
    """Write :func:`summary_records` as a CSV (UTF-8; floats as ``repr``, NaN as ``nan``);
    written to a temporary name then renamed. Returns the path.

    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     path = to_csv(summarise([{"model": "a", "MAE (s)": 0.5}]), Path(tmp) / "summary.csv")
    ...     print(path.read_text(encoding="utf-8"))
    model,n,MAE (s) mean,MAE (s) std,MAE (s) n
    a,1,0.5,nan,1
    <BLANKLINE>
    """
    path = Path(path)
    records = summary_records(table)
    hdr = list(records[0]) if records else [table.by, "n"]
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(hdr)
        for rec in records:
            w.writerow([repr(v) if isinstance(v, float) else v for v in rec.values()])
    os.replace(tmp, path)
    return path
