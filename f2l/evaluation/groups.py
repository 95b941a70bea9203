"""``f2l eval groups``: error against the number of faces, the joint estimate against each face's own.

On ``f2l eval render-faces --framing group`` sets (2–5 path-traced people in one photo, one light,
heads shading each other), fitted by ``f2l fit-faces``: for every photo with at least n fitted
faces, its first n faces (by face id) are estimated one at a time and jointly
(:func:`f2l.estimate.joint.estimate_joint`), and every estimate is scored against the photo's
true probe with the §5.1 metrics, as ``make eval-real`` scores (Sun-ang on clear skies only).
The singles' figures are the mean over the same faces; the time columns are the sum of the
singles' times and the joint's time, on the same machine in the same process. Cases with an even
index tune, odd ones report (as eval-real's parts).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from f2l.estimate.config import EstimatorConfig
from f2l.estimate.estimator import estimate
from f2l.estimate.joint import estimate_joint
from f2l.estimate.observation import EstimationError, FaceObservation
from f2l.evaluation.evaluate import _truth_on, baseline_probes, load_cases, records_by_case
from f2l.lighting.grid import LatLongGrid
from f2l.metrics import evaluate_pair
from f2l.models.registry import load_model

SIZES = (1, 2, 3, 5)
METRICS = ("Sun-ang (°)", "MAE (s)", "Full-dω MAE (l)")


def group_rows(render_dirs, fitted, model_name: str = "sunsky", sizes=SIZES, cfg: EstimatorConfig | None = None,
               progress=None) -> list[dict]:
    """One row per (photo, n): the truth's sky kind, the singles' and the joint's metrics and times."""
    cfg = cfg or EstimatorConfig(sun_prior_from_capture=False)
    cases, where = {}, {}
    for d in map(Path, render_dirs):
        for cid, meta in load_cases(d).items():
            cases[cid], where[cid] = meta, d
    records = records_by_case(fitted, cases)
    model, cache, rows = None, {}, []
    for cid in sorted(records):
        recs = records[cid]
        meta = cases[cid]
        grid = LatLongGrid(recs[0].grid_height, recs[0].grid_width)
        model = model if model is not None and model.grid.shape == grid.shape else load_model(model_name, grid)
        truth = _truth_on(where[cid], cid, grid, cache)
        overcast = meta["sky"]["kind"] == "overcast"
        gt_sun = None if overcast else np.asarray(meta["sky"]["sun_direction"])

        def score(probe, sun):
            m = evaluate_pair(np.asarray(probe, np.float64), truth, grid, overcast=overcast, est_sun_dir=sun,
                              gt_sun_dir=gt_sun)
            return [float(m[k]) for k in METRICS]

        uniform = score(baseline_probes(truth, grid, gt_sun)["uniform sky"], None)
        obs = [FaceObservation(r.normals, r.observed_rgb, r.mask, r.visibility_bits, grid, r.face_id, r.points)
               for r in recs]
        singles = {}
        for n in sizes:
            if len(obs) < n:
                continue
            for i in range(n):
                if i not in singles:
                    t = time.perf_counter()
                    try:
                        res = estimate(obs[i], model, cfg)
                        singles[i] = (score(res.probe, res.sun_direction), time.perf_counter() - t, _cones(res))
                    except EstimationError:
                        singles[i] = (None, time.perf_counter() - t, None)
            ok = [singles[i][0] for i in range(n) if singles[i][0] is not None]
            if not ok:
                continue
            t = time.perf_counter()
            try:
                joint = estimate_joint(obs[:n], model, cfg, pixel_rc=[r.pixel_rc for r in recs[:n]])
            except EstimationError:
                continue
            joint_s = time.perf_counter() - t
            row = {"case": cid, "part": _part(cid), "n": n,
                   "overcast": overcast, "single": np.mean(ok, axis=0).tolist(),
                   "joint": score(joint.result.probe, joint.result.sun_direction), "uniform": uniform,
                   "single_s": float(sum(singles[i][1] for i in range(n))), "joint_s": joint_s,
                   "left_out": sum(not s.used for s in joint.faces),
                   "left_out_reasons": [s.reason for s in joint.faces if not s.used],
                   "joint_cones": _cones(joint.result), "single_cones": [singles[i][2] for i in range(n)],
                   "single_sun_ang": [None if singles[i][0] is None else singles[i][0][0] for i in range(n)]}
            rows.append(row)
            if progress is not None:
                progress(row)
    return rows


def _cones(result) -> list[float] | None:
    """[r_68, r_90] (deg) of an estimate's sun (f2l.estimate.uncertainty), None without them."""
    u = getattr(result, "sun_uncertainty", None)
    return None if u is None else [float(u.cone68_deg), float(u.cone90_deg)]


def cone_table(rows: list[dict], part: str | None = None) -> str:
    """Markdown: per n, how often the true sun lies inside the joint's and the singles' 68% and
    90% cones (clear skies), and the cones' mean radius."""
    lines = ["| faces | joint: in 68% / 90% cone (mean r_90 °) | each face alone: in 68% / 90% cone (mean r_90 °) |",
             "|---|---|---|"]
    sel = [r for r in rows if (part is None or r["part"] == part) and not r["overcast"]]
    for n in sorted({r["n"] for r in sel}):
        joint = [(r["joint"][0], *r["joint_cones"]) for r in sel if r["n"] == n and r.get("joint_cones")
                 and np.isfinite(r["joint"][0])]
        alone = [(a, *c) for r in sel if r["n"] == n for a, c in zip(r.get("single_sun_ang", []), r.get("single_cones", []))
                 if a is not None and c is not None and np.isfinite(a)]

        def cell(v):
            if not v:
                return "–"
            v = np.asarray(v, np.float64)
            return (f"{np.mean(v[:, 0] <= v[:, 1]):.0%} / {np.mean(v[:, 0] <= v[:, 2]):.0%} of {len(v)} "
                    f"({np.mean(v[:, 2]):.1f})")

        lines.append(f"| {n} | {cell(joint)} | {cell(alone)} |")
    return "\n".join(lines)


def _part(case_id: str) -> str:
    """"tune" for an even case index (the id's last ``-`` field), else "report"."""
    tail = case_id.rsplit("-", 1)[-1]
    return "tune" if tail.isdigit() and int(tail) % 2 == 0 else "report"


def group_table(rows: list[dict], part: str | None = None) -> str:
    """Markdown: per n, photos, the singles' and the joint's mean metrics, their ratio, times."""
    sel = [r for r in rows if part is None or r["part"] == part]
    lines = ["| faces | photos (clear) | Sun-ang ° single → joint (ratio) | MAE (s) single → joint (ratio) | "
             "Full-dω MAE (l) single → joint (uniform sky) | faces left out | time s: singles → joint |",
             "|---|---|---|---|---|---|---|"]
    for n in sorted({r["n"] for r in sel}):
        rs = [r for r in sel if r["n"] == n]
        clear = [r for r in rs if not r["overcast"] and np.isfinite(r["joint"][0]) and np.isfinite(r["single"][0])]
        s_ang, j_ang = (float(np.mean([r[k][0] for r in clear])) if clear else float("nan") for k in ("single", "joint"))
        s_mae, j_mae = (float(np.mean([r[k][1] for r in rs])) for k in ("single", "joint"))
        s_full, j_full, u_full = (float(np.mean([r[k][2] for r in rs])) for k in ("single", "joint", "uniform"))
        lines.append(
            f"| {n} | {len(rs)} ({len(clear)}) | {s_ang:.1f} → {j_ang:.1f} ({j_ang / s_ang:.2f}) | "
            f"{s_mae:.3f} → {j_mae:.3f} ({j_mae / s_mae:.2f}) | {s_full:.4f} → {j_full:.4f} ({u_full:.4f}) | "
            f"{sum(r['left_out'] for r in rs)} | {sum(r['single_s'] for r in rs):.0f} → {sum(r['joint_s'] for r in rs):.0f} |")
    return "\n".join(lines)


def write_group_report(rows: list[dict], out: Path) -> str:
    """``groups.md`` (a table per part and for all) and ``groups.json`` (the rows) under ``out``."""
    from f2l.io.atomic import write_text_atomic

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    text = "\n\n".join(f"### {title}\n\n{group_table(rows, part)}\n\nThe sun's cones "
                         f"(f2l.estimate.uncertainty):\n\n{cone_table(rows, part)}" for title, part in
                         (("Reporting part (odd cases)", "report"), ("Tuning part (even cases)", "tune"), ("All", None)))
    write_text_atomic(out / "groups.md", text + "\n")
    write_text_atomic(out / "groups.json", json.dumps(rows, indent=1))
    return text
