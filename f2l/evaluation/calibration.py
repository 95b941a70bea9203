"""Tuning and drawing the estimates' sun uncertainty (f2l.estimate.uncertainty) on ``make
eval-real``'s tuning part; the calibration measures themselves are :mod:`f2l.metrics.calibration`
(re-exported here).

- :func:`gather_evidence`: estimate each tuning face in memory, keeping the uncertainty's evidence
  with its true Sun-ang and relit MAE (s) (a heavy path: one estimate a face);
- :func:`recompute`: the uncertainty of that evidence under other settings (no refit);
- :func:`fit_uncertainty_model`: the calibrated cone's and the relit-error regression's constants;
- :func:`plot_risk_coverage`: the risk–coverage curve, one line per method (f2l.report.plots' style).

docs/experiments/uncertainty.md gives the commands and the figures.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from f2l.metrics.calibration import (ANGLE, CONE68, CONE90, FRACTIONS, calibration_table, cone_coverage,  # noqa: F401
                                     predicted_vs_measured, risk_coverage, usable)

__all__ = ["ANGLE", "CONE68", "CONE90", "FRACTIONS", "usable", "cone_coverage", "risk_coverage", "calibration_table",
           "predicted_vs_measured", "fit_mae_model", "gather_evidence", "recompute", "fit_uncertainty_model",
           "plot_risk_coverage"]


def fit_mae_model(features: np.ndarray, mae_s: np.ndarray) -> np.ndarray:
    """Least-squares coefficients c of mae_s ≈ features @ c (rows: f2l.estimate.uncertainty.mae_features)."""
    coef, *_ = np.linalg.lstsq(np.asarray(features, np.float64), np.asarray(mae_s, np.float64), rcond=None)
    return coef


def plot_risk_coverage(curves: dict[str, list[tuple[float, int, float]]], path: Path, title: str = "") -> None:
    """Mean Sun-ang (°) of the most confident faces against the share kept, one line per method
    (``curves``: :func:`risk_coverage` per method); the x axis runs from all
    faces (1) down to the most confident quarter, so a useful confidence slopes down to the right."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 4))
    for name, curve in sorted(curves.items()):
        points = [(f, m) for f, k, m in curve if k > 0 and math.isfinite(m)]
        if points:
            ax.plot([f for f, _ in points], [m for _, m in points], marker="o", label=name)
    ax.set_xlim(1.05, 0.2)
    ax.set_xlabel("share of faces kept (most confident first: narrowest 90% sun cone)")
    ax.set_ylabel("mean Sun-ang of the faces kept (°)")
    ax.set_title(title or "risk–coverage", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


# -- tuning on make eval-real's tuning part (docs/experiments/uncertainty.md) ------------------------
def gather_evidence(render_dir, fitted_dir, split: str = "tune", model: str = "sunsky", cfg=None,
                    limit: int | None = None) -> list[dict]:
    """Estimate each fitted face of ``split``'s clear cases of an ``f2l eval render-faces`` folder
    with ``model`` in memory (as ``f2l estimate`` does) and keep, per face: its case, Sun-ang and
    MAE (s) against the truth, its pixel count and the uncertainty's evidence (a heavy path: one
    estimate a face)."""
    from f2l.estimate.config import EstimatorConfig
    from f2l.estimate.record import estimate_in_memory
    from f2l.evaluation.evaluate import _truth_on, load_cases, records_by_case, split_of
    from f2l.lighting.grid import LatLongGrid
    from f2l.metrics import evaluate_pair

    cfg = cfg or EstimatorConfig()
    cases = {c: m for c, m in load_cases(render_dir).items() if split_of(m) == split and m["sky"]["kind"] == "clear"}
    out, cache = [], {}
    for case, recs in sorted(records_by_case(fitted_dir, cases).items()):
        meta = cases[case]
        for rec in recs:
            done = estimate_in_memory(rec, model, cfg)
            if done.result is None or done.result.sun_uncertainty is None:
                continue
            res = done.result
            grid = LatLongGrid(rec.grid_height, rec.grid_width)
            true_sun = np.asarray(meta["sky"]["sun_direction"], np.float64)
            metrics = evaluate_pair(res.probe.astype(np.float64), _truth_on(render_dir, case, grid, cache), grid,
                                    overcast=False, est_sun_dir=res.sun_direction, gt_sun_dir=true_sun)
            out.append({"case": case, "face_id": rec.face_id, ANGLE: metrics[ANGLE], "MAE (s)": metrics["MAE (s)"],
                        "sun_behind_head": meta["sky"]["sun_behind_head"], "sun_direction": res.sun_direction,
                        "true_sun": true_sun, "uncertainty": res.sun_uncertainty, "runtime_s": res.runtime_s})
            if limit is not None and len(out) >= limit:
                return out
    return out


def recompute(evidence: list[dict], **settings) -> list[dict]:
    """Rows (Sun-ang, MAE (s), cones and their inputs) of ``evidence`` with the uncertainty
    recomputed under ``settings`` (keyword arguments of f2l.estimate.uncertainty.sun_uncertainty)."""
    from f2l.estimate.uncertainty import sun_uncertainty

    rows = []
    for e in evidence:
        u, ev = e["uncertainty"], e["uncertainty"].evidence
        v = sun_uncertainty(e["sun_direction"], ev["candidate_directions"], ev["totals"], ev["yy"], ev["normals"],
                            u.overcast_fit, ev["profile_directions"], ev["profile_weights"], **settings)
        rows.append({"case": e["case"], "face_id": e["face_id"], ANGLE: e[ANGLE], "MAE (s)": e["MAE (s)"],
                     CONE68: v.cone68_deg, CONE90: v.cone90_deg, "predicted_mae_s": v.predicted_mae_s,
                     "posterior90_deg": v.posterior90_deg, "lit_fraction": v.lit_fraction,
                     "overcast_fit": v.overcast_fit, "relative_residual": v.relative_residual,
                     "sun_behind_head": e["sun_behind_head"]})
    return rows


def fit_uncertainty_model(evidence: list[dict], temperature: float, floor_deg: float = 0.5) -> dict:
    """The calibrated cone's and the relit-error regression's constants from tuning ``evidence``
    (:func:`gather_evidence`) with the posterior at ``temperature`` (f2l.estimate.uncertainty):
    β by least squares of ln max(Sun-ang, ``floor_deg``) on the cone features, k_q the
    ceil((n + 1) q)-th smallest of the n ratios Sun-ang / exp(β · x) (split conformal: a new face
    like these has its sun inside with probability at least q), then the MAE (s) coefficients by
    least squares on the calibrated r_90. Returns {"cone_coefficients", "cone_quantiles", "mae_coefficients"}."""
    from f2l.estimate.uncertainty import cone_features, mae_features

    rows = recompute(evidence, temperature=temperature)
    x = np.array([cone_features(r["posterior90_deg"], r["lit_fraction"], r["overcast_fit"]) for r in rows])
    angle = np.array([r[ANGLE] for r in rows])
    beta = fit_mae_model(x, np.log(np.maximum(angle, floor_deg)))
    ratio = np.sort(angle / np.exp(x @ beta))
    k = tuple(float(ratio[min(len(ratio), math.ceil((len(ratio) + 1) * q)) - 1]) for q in (0.68, 0.90))
    rows = recompute(evidence, temperature=temperature, cone_coefficients=tuple(beta), cone_quantiles=k)
    f = np.array([mae_features(r[CONE90], r["lit_fraction"], r["relative_residual"]) for r in rows])
    mae = fit_mae_model(f, np.array([r["MAE (s)"] for r in rows]))
    return {"cone_coefficients": tuple(float(b) for b in beta), "cone_quantiles": k,
            "mae_coefficients": tuple(float(c) for c in mae)}
