"""``f2l eval shade``: is a face in an occluder's shadow left out of the joint estimate, and what it costs.

On ``f2l eval render-faces --framing group --shade-one`` sets (a dark board puts one person's
face in its shadow under a clear sky: meta ``shaded_person``; :mod:`f2l.render.occluder`), fitted
by ``f2l fit-faces``: each fitted record of a shaded photo is matched to the person whose true face
box overlaps its landmark box most (IoU > :data:`MATCH_IOU`, as ``f2l eval framings`` matches).
Every photo whose shaded face was fitted, with at least one other fitted face, is estimated with
:func:`f2l.estimate.joint.estimate_joint` three ways on the same faces and truth:

- ``check on``: all the photo's faces, the default disagreement limit;
- ``without``: all but the shaded face (what the joint should match when it leaves that face out);
- ``check off``: all the faces, ``disagree_ratio=None`` (every face used).

Reported: how often the shaded face is flagged (``used`` False) with its ``agreement``, the
sunlit faces flagged too (some may be in another head's shadow under a low sun), and the §5.1
metrics of each estimate against the photo's true probe (:func:`f2l.metrics.evaluate_pair`;
Sun-ang: every shaded photo is clear), as ``f2l eval groups`` scores them.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from f2l.estimate.config import EstimatorConfig
from f2l.estimate.joint import DISAGREE_RATIO, estimate_joint
from f2l.estimate.observation import EstimationError, FaceObservation
from f2l.evaluation.evaluate import _truth_on, baseline_probes, load_cases, records_by_case
from f2l.face.detector import iou
from f2l.io.atomic import write_text_atomic
from f2l.lighting.grid import LatLongGrid
from f2l.metrics import evaluate_pair
from f2l.models.registry import load_model

__all__ = ["VARIANTS", "shade_rows", "shade_table", "write_shade_report"]

MATCH_IOU = 0.3
METRICS = ("Sun-ang (°)", "MAE (s)", "Full-dω MAE (l)")
VARIANTS = ("check on", "without", "check off")


def match_persons(faces: list[dict], records) -> list[int | None]:
    """Per record, the person (index of ``faces``, meta order) whose true box overlaps its landmark
    box most, None below :data:`MATCH_IOU`."""
    boxes = np.array([f["box"] for f in faces], np.float64).reshape(-1, 4)
    out = []
    for rec in records:
        box = np.asarray(rec.meta.get("face_box_px", [0, 0, 0, 0]), np.float64)
        overlap = iou(box, boxes) if len(boxes) else np.zeros(0)
        out.append(int(np.argmax(overlap)) if len(overlap) and overlap.max() > MATCH_IOU else None)
    return out


def _shaded_cases(render_dirs) -> tuple[dict, dict]:
    cases, where = {}, {}
    for d in map(Path, render_dirs):
        for cid, meta in load_cases(d).items():
            if meta.get("shaded_person") is not None:
                cases[cid], where[cid] = meta, d
    return cases, where


def shade_rows(render_dirs, fitted, model_name: str = "sunsky", cfg: EstimatorConfig | None = None,
               disagree_ratio: float = DISAGREE_RATIO, progress=None) -> list[dict]:
    """One row per shaded photo (module docstring): its faces, which is shaded, whether it was
    fitted and flagged, the agreements, and per variant the §5.1 metrics and time (None where
    the photo has no such estimate)."""
    cfg = cfg or EstimatorConfig(sun_prior_from_capture=False)
    cases, where = _shaded_cases(render_dirs)
    records = records_by_case(fitted, cases)
    model, cache, rows = None, {}, []
    for cid in sorted(cases):
        meta = cases[cid]
        recs = records.get(cid, [])
        persons = match_persons(meta["faces"], recs)
        shaded = meta["shaded_person"]
        row = {"case": cid, "people": len(meta["faces"]), "faces": len(recs), "shaded_person": shaded,
               "persons": persons, "shaded_fitted": shaded in persons, "flagged": None, "agreements": None,
               "reasons": None, **{v: None for v in VARIANTS}}
        rows.append(row)
        if not row["shaded_fitted"] or len(recs) < 2:
            continue
        k = persons.index(shaded)
        grid = LatLongGrid(recs[0].grid_height, recs[0].grid_width)
        model = model if model is not None and model.grid.shape == grid.shape else load_model(model_name, grid)
        truth = _truth_on(where[cid], cid, grid, cache)
        gt_sun = np.asarray(meta["sky"]["sun_direction"])
        overcast = meta["sky"]["kind"] == "overcast"

        def score(res):
            m = evaluate_pair(np.asarray(res.probe, np.float64), truth, grid, overcast=overcast,
                              est_sun_dir=res.sun_direction, gt_sun_dir=None if overcast else gt_sun)
            return [float(m[key]) for key in METRICS]

        obs = [FaceObservation(r.normals, r.observed_rgb, r.mask, r.visibility_bits, grid, r.face_id, r.points)
               for r in recs]
        rc = [r.pixel_rc for r in recs]
        keep = [i for i in range(len(recs)) if i != k]
        runs = {"check on": (obs, rc, disagree_ratio), "without": ([obs[i] for i in keep], [rc[i] for i in keep],
                                                                   disagree_ratio),
                "check off": (obs, rc, None)}
        for variant, (o, p, ratio) in runs.items():
            t = time.perf_counter()
            try:
                joint = estimate_joint(o, model, cfg, pixel_rc=p, disagree_ratio=ratio)
            except EstimationError as exc:
                row[variant] = {"error": str(exc)}
                continue
            row[variant] = {"metrics": score(joint.result), "s": time.perf_counter() - t,
                            "used": [s.used for s in joint.faces]}
            if variant == "check on":
                row["flagged"] = not joint.faces[k].used
                row["agreements"] = [s.agreement for s in joint.faces]
                row["sun_seen"] = [s.sun_seen for s in joint.faces]
                row["sun_share"] = [s.sun_share for s in joint.faces]
                row["darkness"] = [s.darkness for s in joint.faces]
                row["reasons"] = [s.reason for s in joint.faces]
                row["sunlit_flagged"] = sum(not s.used for i, s in enumerate(joint.faces) if i != k)
        row["shaded_index"] = k
        row["uniform"] = score(_Probe(baseline_probes(truth, grid, gt_sun)["uniform sky"]))
        if progress is not None:
            progress(row)
    return rows


class _Probe:
    """A baseline probe scored as an estimate (no sun direction)."""

    def __init__(self, probe):
        self.probe, self.sun_direction = probe, None


def _mean(values, digits: int = 3) -> str:
    values = [v for v in values if v is not None and np.isfinite(v)]
    return f"{np.mean(values):.{digits}f}" if values else "—"


def shade_table(rows: list[dict]) -> str:
    """Markdown: the flag counts, then per variant the mean metrics over the photos scored in all
    three, then one line per photo (agreements)."""
    scored = [r for r in rows if all(isinstance(r[v], dict) and "metrics" in r[v] for v in VARIANTS)]
    fitted = [r for r in rows if r["shaded_fitted"] and r["faces"] >= 2]
    flagged = sum(bool(r["flagged"]) for r in fitted)
    sunlit = sum(r["faces"] - 1 for r in fitted)
    false = sum(r.get("sunlit_flagged", 0) for r in fitted)
    lines = ["| shaded photos | shaded face fitted, ≥ 2 faces | shaded face flagged | sunlit faces flagged |",
             "|---|---|---|---|",
             f"| {len(rows)} | {len(fitted)} | {flagged} / {len(fitted)} ({100 * flagged / max(len(fitted), 1):.0f}%) | "
             f"{false} / {sunlit} |", "",
             f"Mean over the {len(scored)} photos scored every way (Sun-ang: all clear):", "",
             "| joint estimate | Sun-ang ° mean | Sun-ang ° median | MAE (s) | Full-dω MAE (l) |", "|---|---|---|---|---|"]
    for label, key in (("(a) check on", "check on"), ("(b) without the shaded face", "without"),
                       ("(c) check off (every face used)", "check off")):
        m = np.array([r[key]["metrics"] for r in scored], np.float64).reshape(-1, len(METRICS))
        med = f"{np.median(m[:, 0]):.1f}" if len(m) else "—"
        lines.append(f"| {label} | {_mean(m[:, 0], 1)} | {med} | {_mean(m[:, 1])} | {_mean(m[:, 2], 4)} |")
    u = np.array([r["uniform"] for r in scored], np.float64).reshape(-1, len(METRICS))
    lines.append(f"| uniform sky (baseline) | — | — | {_mean(u[:, 1])} | {_mean(u[:, 2], 4)} |")
    lines += ["", "| photo | faces | shaded face: agreement, flagged | sunlit faces: agreements (flagged) | "
              "Sun-ang ° (a) / (b) / (c) |", "|---|---|---|---|---|"]
    for r in fitted:
        k, ag = r["shaded_index"], r["agreements"] or []
        fmt = (lambda a: "—" if a is None else f"{a:.2f}")
        others = ", ".join(fmt(a) + (" (flagged)" if not u_ else "") for i, (a, u_) in
                           enumerate(zip(ag, r["check on"].get("used", []) if r["check on"] else [])) if i != k)
        angles = " / ".join(f"{r[v]['metrics'][0]:.1f}" if r[v] and "metrics" in r[v] else "—" for v in VARIANTS)
        lines.append(f"| {r['case']} | {r['faces']} | {fmt(ag[k] if ag else None)}, "
                     f"{'yes' if r['flagged'] else 'no'} | {others} | {angles} |")
    return "\n".join(lines)


def write_shade_report(rows: list[dict], out: Path) -> str:
    """``shade.md`` (the tables) and ``shade.json`` (the rows) under ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    text = shade_table(rows)
    write_text_atomic(out / "shade.md", text + "\n")
    write_text_atomic(out / "shade.json", json.dumps(rows, indent=1))
    return text
