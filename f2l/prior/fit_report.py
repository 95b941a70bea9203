"""The probe-fit report (``f2l eval fit-probe``, paper Table 1): counts, sun-angle statistics and run
time of :func:`f2l.prior.build.fit_probes`' records, the §5.1 lighting metrics per fit (the model
and each of its fit variants) and per kind of sky, as a dict with Markdown tables and a CSV."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from f2l.io.atomic import write_text_atomic
from f2l.metrics.lighting import PROBE_METRIC_NAMES
from f2l.prior.probe_fit import ProbeRecord

__all__ = ["write_fit_report", "kind_table", "metrics_table"]


def write_fit_report(records: list[ProbeRecord], model, out_dir: str | Path | None = None) -> dict:
    """Summary of fit_probes (counts, sun angle statistics, run time) as a dict with a Markdown
    table; with ``out_dir``: ``fit_probe.csv`` (one row per probe) is written there."""
    ok = [r for r in records if r.status == "ok"]
    angles = np.array([r.sun_angle_deg for r in ok if r.sun_angle_deg is not None], dtype=np.float64)
    times = np.array([r.runtime_s for r in ok], dtype=np.float64)
    summary = {
        "model": model.name, "total": len(records), "ok": len(ok), "errors": len(records) - len(ok),
        "sun_angle_deg_median": float(np.median(angles)) if len(angles) else None,
        "sun_angle_deg_mean": float(np.mean(angles)) if len(angles) else None,
        "sun_angle_deg_p90": float(np.percentile(angles, 90)) if len(angles) else None,
        "sun_angle_n": int(len(angles)),
        "runtime_s_median": float(np.median(times)) if len(times) else None,
    }
    fmt = lambda v, f: "-" if v is None else format(v, f)  # noqa: E731
    lines = [
        "| model | probes | fitted | Sun-ang median (°) | mean | 90th pct | n (sun known) | time per probe (s) |",
        "|---|---|---|---|---|---|---|---|",
        f"| {model.name} | {len(records)} | {len(ok)} | {fmt(summary['sun_angle_deg_median'], '.3f')} | "
        f"{fmt(summary['sun_angle_deg_mean'], '.3f')} | {fmt(summary['sun_angle_deg_p90'], '.3f')} | "
        f"{len(angles)} | {fmt(summary['runtime_s_median'], '.2f')} |",
    ]
    for r in records:
        if r.status != "ok":
            lines.append(f"\nerror: {r.message}")
    table = metrics_table(records, model.name)
    summary["metrics"] = table["rows"]
    if table["rows"]:
        lines += ["", *table["lines"]]
    by_kind = kind_table(records, model.name)
    summary["by_kind"] = by_kind["rows"]
    if by_kind["rows"]:
        lines += ["", *by_kind["lines"]]
    summary["markdown"] = "\n".join(lines)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        variants = sorted({name for r in ok for name in r.extra.get("variants", {})})
        metric_cols = list(PROBE_METRIC_NAMES) + [f"{v} {m}" for v in variants for m in PROBE_METRIC_NAMES]
        buf = io.StringIO()
        writer = csv.writer(buf)
        writer.writerow(["path", "status", "message", "kind", "loss", "runtime_s", "sun_angle_deg",
                         *model.param_names, *metric_cols])
        for r in records:
            metrics = r.extra.get("metrics", {})
            var = r.extra.get("variants", {})
            cells = [metrics.get(m, "") for m in PROBE_METRIC_NAMES]
            cells += [var.get(v, {}).get("metrics", {}).get(m, "") for v in variants for m in PROBE_METRIC_NAMES]
            writer.writerow([r.path, r.status, r.message, r.kind or "", r.loss, r.runtime_s,
                             r.sun_angle_deg, *(r.params or [""] * model.num_params), *cells])
        write_text_atomic(out / "fit_probe.csv", buf.getvalue())
        summary["csv"] = str(out / "fit_probe.csv")
    return summary


def kind_table(records: list[ProbeRecord], model_name: str) -> dict:
    """Full-dω and Sky-dω MAE (l) means per kind of sky (the probes' side files: clear, partly,
    overcast, ...) for the model and each fit variant; empty when no probe has a kind.
    {"rows": [{"fit", "kind", "n", "Full-dω MAE (l)", "Sky-dω MAE (l)"}], "lines": Markdown}."""
    names = ("Full-dω MAE (l)", "Sky-dω MAE (l)")
    ok = [r for r in records if r.status == "ok" and r.kind and r.extra.get("metrics")]
    kinds = sorted({r.kind for r in ok})
    fits = [model_name] + sorted({v for r in ok for v in r.extra.get("variants", {})})
    rows = []
    for fit in fits:
        for kind in kinds:
            ms = [r.extra["metrics"] if fit == model_name else r.extra.get("variants", {}).get(fit, {}).get("metrics")
                  for r in ok if r.kind == kind]
            ms = [m for m in ms if m]
            if ms:
                rows.append({"fit": fit, "kind": kind, "n": len(ms),
                             **{n: float(np.mean([m[n] for m in ms])) for n in names}})
    if not rows:
        return {"rows": [], "lines": []}
    counts = {k: max(r["n"] for r in rows if r["kind"] == k) for k in kinds}
    lines = ["| fit | " + " | ".join(f"{k} ({counts[k]}): Full-dω (Sky-dω) MAE (l)" for k in kinds) + " |",
             "|---|" + "---|" * len(kinds)]
    for fit in fits:
        cells = []
        for k in kinds:
            row = next((r for r in rows if r["fit"] == fit and r["kind"] == k), None)
            cells.append("-" if row is None else f"{row[names[0]]:.4g} ({row[names[1]]:.4g})")
        lines.append(f"| {fit} | " + " | ".join(cells) + " |")
    return {"rows": rows, "lines": lines}


def metrics_table(records: list[ProbeRecord], model_name: str) -> dict:
    """Table-1-style rows (mean over the fitted probes of each §5.1 lighting metric; sun metrics
    over the probes that are not overcast) for the model and each of its fit variants:
    {"rows": [{"model", "n", metric: mean, "<metric> median", "<metric> n", "runtime_s"}],
    "lines": Markdown}."""
    ok = [r for r in records if r.status == "ok" and "metrics" in r.extra]
    sources = {model_name: [(r.extra["metrics"], r.runtime_s) for r in ok]}
    for r in ok:
        for name, v in r.extra.get("variants", {}).items():
            sources.setdefault(name, []).append((v["metrics"], v["runtime_s"]))
    rows = []
    for name, items in sources.items():
        if not items:
            continue
        row = {"model": name, "n": len(items), "runtime_s": float(np.median([t for _, t in items]))}
        for m in PROBE_METRIC_NAMES:
            vals = np.array([mt[m] for mt, _ in items], dtype=np.float64)
            vals = vals[np.isfinite(vals)]
            row[m] = float(vals.mean()) if vals.size else None
            row[f"{m} median"] = float(np.median(vals)) if vals.size else None
            row[f"{m} n"] = int(vals.size)
        rows.append(row)
    fmt = lambda v: "-" if v is None else f"{v:.4g}"  # noqa: E731
    lines = ["| fit | probes | " + " | ".join(f"{m} mean (median)" for m in PROBE_METRIC_NAMES) + " | sunny | time (s) |",
             "|---|---|" + "---|" * len(PROBE_METRIC_NAMES) + "---|---|"]
    for row in rows:
        cells = [f"{fmt(row[m])} ({fmt(row[m + ' median'])})" for m in PROBE_METRIC_NAMES]
        lines.append(f"| {row['model']} | {row['n']} | " + " | ".join(cells)
                     + f" | {row[PROBE_METRIC_NAMES[-1] + ' n']} | {row['runtime_s']:.2f} |")
    return {"rows": rows, "lines": lines}
