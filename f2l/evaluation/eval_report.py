"""The markdown report of ``f2l eval real`` (``eval_real.md``, ``eval_real_rows.csv``) and the
ablation table of ``f2l eval ablations``, from the rows :func:`f2l.evaluation.evaluate.evaluate_real`
scores.

- :func:`summary_table`: the seven §5.1 metrics per method, median Sun-ang and s / face;
- :func:`breakdown_table`: mean Sun-ang / MAE (s) / Full-dω per method by sky source, sun
  elevation band, sun behind the head or in front, overcast;
- :func:`diagnostics_table`: the light's colour, MAE (s) colour matched, the sun's share;
- :func:`sun_direction_table`: MAE (s) and Full-dω with the sun moved onto the truth and the
  colour matched (what the sun's direction and the light's colour are worth);
- :func:`elevation_bias_table`: the median sun elevation error per band and sky source;
- :func:`residual_table`: far-off suns that fit the photo as well as the truth;
- :func:`calibration_section`: whether the estimates' sun cones hold the true sun as often as they
  say, and the risk–coverage curve (f2l.evaluation.calibration; ``eval_real_risk_coverage.png``);
- :func:`ablation_table`: the error each ablation's re-render removes.

Order in every table: the baselines, the models fitted to the truth (:mod:`f2l.evaluation.truth_fit`),
the fitted-mesh estimates, the labelled runs ("<model> (true geometry)"). The tables of the
estimates' sun leave the first two out.
"""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from f2l.evaluation.evaluate import BASELINES, ELEVATION_BANDS_DEG, SPLITS
from f2l.evaluation.truth_fit import is_truth_fit
from f2l.io.atomic import atomic_path, write_text_atomic
from f2l.metrics import METRIC_NAMES

__all__ = ["ablation_table", "breakdown_table", "calibration_section", "diagnostics_table", "elevation_bias_table",
           "residual_table", "summary_table", "sun_direction_table", "write_report"]


def _is_reference(method: str) -> bool:
    """A baseline or a model fitted to the truth (no face): listed first, left out of the tables
    of the estimates' sun."""
    return method in BASELINES or is_truth_fit(method)


def _order(method: str) -> tuple:
    """Table order: the baselines, the models fitted to the truth, the fitted-mesh estimates, the
    labelled runs."""
    rank = 0 if method in BASELINES else 1 if is_truth_fit(method) else 2
    return (rank, "(" in method, method)


def diagnostics_table(rows: list[dict], split: str = "report") -> str:
    """Markdown: per method, the median colour ratios, mean MAE (s) as scored and colour matched,
    and the mean sun share error (clear cases)."""
    chosen = [r for r in rows if r["split"] == split]
    by = defaultdict(list)
    for r in chosen:
        by[r["method"]].append(r)

    def median(values):
        v = [float(x) for x in values if not math.isnan(float(x))]
        return float(np.median(v)) if v else math.nan

    lines = ["| method | colour R/G (median) | colour B/G (median) | MAE (s) | MAE (s), colour matched | sun share − truth (mean) |",
             "|---|---|---|---|---|---|"]
    for method in sorted(by, key=_order):
        rs = by[method]
        lines.append(f"| {method} | {_fmt(median(r['colour R/G'] for r in rs))} | {_fmt(median(r['colour B/G'] for r in rs))}"
                     f" | {_fmt(_mean(float(r['MAE (s)']) for r in rs))} | {_fmt(_mean(float(r['MAE (s), colour matched']) for r in rs))}"
                     f" | {_fmt(_mean(float(r['sun share']) for r in rs if r['sky_kind'] == 'clear'), 2)} |")
    return "\n".join(lines)


def sun_direction_table(rows: list[dict], split: str = "report") -> str:
    """Markdown: per estimating method, over the clear cases of ``split``, the means of MAE (s) and
    Full-dω MAE (l) as scored, with the colour matched, with the sun moved onto the true one
    (:func:`sun_moved`), and both: how much of each error the sun's direction and the light's
    colour account for."""
    chosen = [r for r in rows if r["split"] == split and r["sky_kind"] == "clear" and not _is_reference(r["method"])]
    methods = sorted({r["method"] for r in chosen}, key=lambda m: ("(" in m, m))
    lines = ["| method | clear cases | mean Sun-ang (°) | MAE (s) | colour matched | sun at the truth | sun at the truth, colour matched"
             " | Full-dω MAE (l) | Full-dω, sun at the truth |", "|" + "---|" * 9]
    for method in methods:
        rs = [r for r in chosen if r["method"] == method]
        cells = [_fmt(_mean(float(r[k]) for r in rs)) for k in (
            "Sun-ang (°)", "MAE (s)", "MAE (s), colour matched", "MAE (s), sun at the truth",
            "MAE (s), sun at the truth, colour matched", "Full-dω MAE (l)", "Full-dω MAE (l), sun at the truth")]
        lines.append(f"| {method} | {len(rs)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


ELEVATION_BIAS_BANDS_DEG = ((0.0, 15.0), (15.0, 45.0), (45.0, 75.0), (75.0, 90.0))


def elevation_bias_table(rows: list[dict], split: str = "report") -> str:
    """Markdown: per method (baselines left out), the median ``sun elevation error (°)`` and the
    mean Sun-ang in each sun elevation band, for the Hosek–Wilkie skies and the HDR maps apart
    (clear cases of ``split``). Cells: "median elevation error / mean Sun-ang (cases)"."""
    chosen = [r for r in rows if r["split"] == split and r["sky_kind"] == "clear" and not _is_reference(r["method"])]
    methods = sorted({r["method"] for r in chosen}, key=lambda m: ("(" in m, m))
    columns = [(kind, band) for kind in ("Hosek–Wilkie", "HDR maps") for band in ELEVATION_BIAS_BANDS_DEG]
    lines = ["| method | " + " | ".join(f"{kind}, sun {lo:.0f}–{hi:.0f}°" for kind, (lo, hi) in columns) + " |",
             "|" + "---|" * (len(columns) + 1)]
    for method in methods:
        cells = []
        for kind, (lo, hi) in columns:
            rs = [r for r in chosen if r["method"] == method and (r["source"] == "sunsky") == (kind == "Hosek–Wilkie")
                  and lo <= float(r["sun_elevation_deg"]) < (hi if hi < 90.0 else 90.01)]
            err = [float(r["sun elevation error (°)"]) for r in rs if not math.isnan(float(r["sun elevation error (°)"]))]
            cells.append(f"{np.median(err):+.1f}° / {_fmt(_mean(float(r['Sun-ang (°)']) for r in rs), 3)}° ({len(rs)})"
                         if err else "—")
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


FAR_OFF_DEG = 15.0


def residual_table(rows: list[dict], split: str | None = None, far_off_deg: float = FAR_OFF_DEG) -> str:
    """Markdown: per method with photo residuals, over clear cases of ``split`` (None: both parts),
    the median photo residual of the estimate and of the truth, and, for the cases whose Sun-ang
    exceeds ``far_off_deg``, how many fit the photo at least as well as the truth does (the photo,
    read through f2l's forward model and that record's geometry, does not point at the true sun)
    and their share of the method's summed Sun-ang."""
    chosen = [r for r in rows if (split is None or r["split"] == split) and r["sky_kind"] == "clear"
              and not math.isnan(float(r.get("photo residual", math.nan)))]
    methods = sorted({r["method"] for r in chosen}, key=lambda m: ("(" in m, m))
    lines = [f"| method | clear cases | photo residual, estimate (median) | photo residual, truth (median) | Sun-ang > {far_off_deg:g}° | of those, fit the photo as well as the truth | their share of the summed Sun-ang |",
             "|---|---|---|---|---|---|---|"]
    for method in methods:
        rs = [r for r in chosen if r["method"] == method]
        far = [r for r in rs if float(r["Sun-ang (°)"]) > far_off_deg]
        preferred = [r for r in far if float(r["photo residual"]) <= float(r["photo residual, truth"])]
        total = sum(float(r["Sun-ang (°)"]) for r in rs if not math.isnan(float(r["Sun-ang (°)"])))
        share = sum(float(r["Sun-ang (°)"]) for r in preferred) / total if total > 0 else math.nan
        lines.append(f"| {method} | {len(rs)} | {_fmt(float(np.median([float(r['photo residual']) for r in rs])))}"
                     f" | {_fmt(float(np.median([float(r['photo residual, truth']) for r in rs])))} | {len(far)}"
                     f" | {len(preferred)} | {_fmt(100.0 * share, 2)}% |")
    return "\n".join(lines)


def _mean(values) -> float:
    v = [x for x in values if x is not None and not (isinstance(x, float) and math.isnan(x))]
    return float(np.mean(v)) if v else math.nan


def _fmt(x: float, digits: int = 3) -> str:
    return "—" if x is None or math.isnan(x) else f"{x:.{digits}g}"


def summary_table(rows: list[dict], split: str | None = "report") -> str:
    """Markdown: one line per method, the seven metrics (mean; Sun metrics over clear cases),
    median Sun-ang, and mean run time per face."""
    chosen = [r for r in rows if split is None or r["split"] == split]
    by = defaultdict(list)
    for r in chosen:
        by[r["method"]].append(r)
    header = ["method", "cases", *METRIC_NAMES, "median Sun-ang (°)", "s / face"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    order = sorted(by, key=_order)
    for method in order:
        rs = by[method]
        vals = [_fmt(_mean(r[k] for r in rs)) for k in METRIC_NAMES]
        angles = [r["Sun-ang (°)"] for r in rs if not math.isnan(r["Sun-ang (°)"])]
        median = float(np.median(angles)) if angles else math.nan
        runtime = _mean(r["runtime_s"] for r in rs) if method not in BASELINES else math.nan
        lines.append(f"| {method} | {len(rs)} | " + " | ".join(vals) + f" | {_fmt(median)} | {_fmt(runtime)} |")
    return "\n".join(lines)


def breakdown_table(rows: list[dict], split: str = "report") -> str:
    """Markdown: mean Sun-ang / MAE (s) / Full-dω MAE (l) per method within each group."""
    chosen = [r for r in rows if r["split"] == split]
    groups = {}
    for r in chosen:
        keys = [f"sky: {'Hosek-Wilkie' if r['source'] == 'sunsky' else 'HDR map ' + r['source']}",
                f"sky: {'Hosek-Wilkie' if r['source'] == 'sunsky' else 'all HDR maps'}"]
        if r["sky_kind"] == "clear":
            lo, hi = next(b for b in ELEVATION_BANDS_DEG if b[0] <= r["sun_elevation_deg"] < b[1] or b[1] == 90.0)
            keys.append(f"sun {lo:.0f}–{hi:.0f}°")
            keys.append("sun behind the head" if r["sun_behind_head"] else "sun in front")
        else:
            keys.append("overcast")
        for k in dict.fromkeys(keys):
            groups.setdefault(k, []).append(r)
    methods = sorted({r["method"] for r in chosen}, key=_order)
    lines = ["| group | cases | " + " | ".join(methods) + " |", "|" + "---|" * (len(methods) + 2),
             "| *(each cell: mean Sun-ang ° / MAE (s) / Full-dω MAE (l))* | | " + " | ".join("" for _ in methods) + " |"]
    for key in sorted(groups):
        rs = groups[key]
        cells = []
        for m in methods:
            mr = [r for r in rs if r["method"] == m]
            cells.append(f"{_fmt(_mean(r['Sun-ang (°)'] for r in mr), 2)} / {_fmt(_mean(r['MAE (s)'] for r in mr), 2)}"
                         f" / {_fmt(_mean(r['Full-dω MAE (l)'] for r in mr), 2)}")
        n_cases = len({r["case"] for r in rs})
        lines.append(f"| {key} | {n_cases} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_report(rows: list[dict], out_dir: Path) -> dict:
    """``eval_real.md`` (reporting part, tuning part, breakdowns) and ``eval_real_rows.csv``."""
    import csv

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    n = {s: len({r["case"] for r in rows if r["split"] == s}) for s in SPLITS}
    sunny = len({r["case"] for r in rows if r["split"] == "report" and r["sky_kind"] == "clear"})
    if n["tune"]:
        text = (f"## Reporting part ({n['report']} cases, {sunny} with a sun; odd case indices)\n\n"
                + summary_table(rows, "report")
                + f"\n\n## Tuning part ({n['tune']} cases; even case indices)\n\n" + summary_table(rows, "tune"))
    else:  # a held-out set (`eval-real --held-out`): every case reports
        text = (f"## All cases, held out from tuning ({n['report']} cases, {sunny} with a sun)\n\n"
                + summary_table(rows, "report"))
    part = "reporting part" if n["tune"] else "all cases"
    text += (f"\n\n## Breakdowns ({part})\n\n" + breakdown_table(rows, "report")
            + f"\n\n## Diagnostics ({part}; where the error comes from, not §5.1 metrics)\n\n"
            + diagnostics_table(rows, "report")
            + f"\n\n## What the sun's direction and the light's colour are worth ({part}, clear cases)\n\n"
            + sun_direction_table(rows, "report")
            + f"\n\n## Sun elevation bias ({part}; median elevation error / mean Sun-ang (cases))\n\n"
            + elevation_bias_table(rows, "report")
            + "\n\n## Does the photo prefer the truth? (both parts; f2l's Lambertian forward model through each record)\n\n"
            + residual_table(rows) + "\n"
            + calibration_section(rows, out_dir, ("report", "tune") if n["tune"] else ("report",)))
    write_text_atomic(out_dir / "eval_real.md", text)
    keys = list(rows[0]) if rows else []
    with atomic_path(out_dir / "eval_real_rows.csv") as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=keys)
            w.writeheader()
            w.writerows(rows)
    return {"markdown": str(out_dir / "eval_real.md"), "rows": str(out_dir / "eval_real_rows.csv"), "cases": n}


def calibration_section(rows: list[dict], out_dir: Path, splits=("report", "tune")) -> str:
    """Markdown: per part, the calibration of the estimates' sun cones on the clear cases
    (f2l.evaluation.calibration.calibration_table), and the reporting part's risk–coverage curve
    drawn to ``out_dir/eval_real_risk_coverage.png``; empty when no row has a cone."""
    from f2l.evaluation.calibration import calibration_table, plot_risk_coverage, risk_coverage, usable

    clear = [r for r in usable(rows) if r["sky_kind"] == "clear" and not _is_reference(r["method"])]
    if not clear:
        return ""
    text = ""
    for split in splits:
        part = [r for r in clear if r["split"] == split]
        name = {"report": "reporting part", "tune": "tuning part"}[split] if len(splits) > 1 else "all cases"
        text += (f"\n## The sun's uncertainty ({name}, clear cases; f2l.estimate.uncertainty)\n\n"
                 + calibration_table(part) + "\n")
    report = [r for r in clear if r["split"] == splits[0]]
    curves = {m: risk_coverage([r for r in report if r["method"] == m]) for m in sorted({r["method"] for r in report})}
    plot_risk_coverage(curves, Path(out_dir) / "eval_real_risk_coverage.png",
                       f"risk–coverage, {'reporting part' if len(splits) > 1 else 'all cases'}, clear cases")
    return text + "\n![risk–coverage](eval_real_risk_coverage.png)\n"


ABLATION_METRICS = ("Sun-ang (°)", "MAE (s)", "Full-dω MAE (l)")


def write_table(rows: list[dict], out_dir: Path, stem: str, heading: str, table: str) -> Path:
    """Write ``OUT/<stem>.md`` (``## heading`` and the Markdown ``table``) and the rows beside it
    as ``OUT/<stem>_rows.json`` (atomic writes); returns the Markdown's path. For the diagnostics
    that re-estimate every face (``eval-real-geometry``, ``eval-real-search``)."""
    import json

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{stem}.md"
    write_text_atomic(path, f"## {heading}\n\n{table}\n")
    write_text_atomic(out_dir / f"{stem}_rows.json", json.dumps(rows, indent=1))
    return path


def _read_rows(path: Path) -> list[dict]:
    import csv

    rows = []
    with open(path, newline="") as fh:
        for r in csv.DictReader(fh):
            for k in (*ABLATION_METRICS, "runtime_s"):
                r[k] = float(r[k]) if r[k] not in ("", "nan") else math.nan
            rows.append(r)
    return rows


def ablation_table(eval_dir: Path, n: int) -> str:
    """Markdown: per model, the three headline metrics on the full renders (cases < ``n``) and on
    each ablation's re-renders of the same cases, with the share of the error each removes."""
    eval_dir = Path(eval_dir)
    variants = {"full render": _read_rows(eval_dir / "eval_real_rows.csv")}
    for path in sorted((eval_dir / "ablations").glob("*/eval_real_rows.csv")):
        variants[path.parent.name] = _read_rows(path)

    def index(case: str) -> int:
        return int(case.rsplit("-", 1)[1])

    for name, rows in variants.items():
        variants[name] = [r for r in rows if index(r["case"]) < n and "(" not in r["method"]]
    methods = sorted({r["method"] for r in variants["full render"] if not is_truth_fit(r["method"])},
                     key=lambda m: (m not in BASELINES, m))
    lines = ["| method | render | " + " | ".join(ABLATION_METRICS) + " | error removed (Sun-ang / MAE (s) / Full-dω) |",
             "|" + "---|" * (len(ABLATION_METRICS) + 3)]
    for m in methods:
        base = {k: _mean(r[k] for r in variants["full render"] if r["method"] == m) for k in ABLATION_METRICS}
        for name, rows in variants.items():
            vals = {k: _mean(r[k] for r in rows if r["method"] == m) for k in ABLATION_METRICS}
            removed = " / ".join("—" if name == "full render" or not base[k] or math.isnan(vals[k])
                                 else f"{100 * (base[k] - vals[k]) / base[k]:+.0f}%" for k in ABLATION_METRICS)
            lines.append(f"| {m} | {name} | " + " | ".join(_fmt(vals[k]) for k in ABLATION_METRICS) + f" | {removed} |")
    return "\n".join(lines)
