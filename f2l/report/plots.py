"""Plots of the report and of ``f2l dev bench``: error against run time on a readable log axis."""

from __future__ import annotations

import math
from pathlib import Path

__all__ = ["log_time_axis", "plot_error_vs_runtime"]


def log_time_axis(ax, seconds: list[float]) -> None:
    """Log x axis labelled at 1, 2, 5 x 10^k in plain numbers ("0.2", "1", "5"), minor ticks
    unlabelled: matplotlib's default labels every minor tick of a sub-decade range, and they
    overlap ("2x10^-1 3x10^-1 ...")."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    ax.set_xscale("log")
    positive = [v for v in seconds if v > 0 and math.isfinite(v)]
    if positive:
        ax.set_xlim(min(positive) / 1.6, max(positive) * 1.6)
    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_formatter(NullFormatter())


def plot_error_vs_runtime(rows: list[dict], path: Path) -> None:
    """One panel per metric, log time axis with decade labels only (no crowded minor labels)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from f2l.metrics import METRIC_NAMES

    fig, axes = plt.subplots(2, 4, figsize=(12, 5.5))
    for ax, metric in zip(axes.ravel(), METRIC_NAMES):
        for r in rows:
            x, y = float(r["runtime_s mean"]), float(r[f"{metric} mean"])
            ax.scatter(x, y, s=36)
            ax.annotate(r["model"], (x, y), fontsize=8, xytext=(3, 3), textcoords="offset points")
        log_time_axis(ax, [float(r["runtime_s mean"]) for r in rows])
        ax.set_xlabel("seconds per face")
        ax.set_title(metric, fontsize=9)
        ax.grid(alpha=0.3, which="both")
    axes.ravel()[-1].axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
