"""``f2l eval framings``: accuracy against the face's size on framed render sets
(``f2l eval render-faces --framing half|full|group``, :mod:`f2l.render.framing`).

A true face of a render's ``meta/<id>.json`` (its box in photo px, x0, y0, x1, y1) is matched to
the fitted record of its photo (photo stem = case id) whose landmark box overlaps it most; its band
is the true face width in px (:data:`WIDTH_BANDS`, lower bound included).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from f2l.evaluation.evaluate import _truth_on, load_cases
from f2l.face.detector import iou
from f2l.io.exr import read_exr
from f2l.io.shards import iter_records
from f2l.lighting.grid import LatLongGrid
from f2l.metrics import evaluate_pair

__all__ = ["WIDTH_BANDS", "accuracy_by_face_width"]

WIDTH_BANDS = ((40, 80), (80, 160), (160, 320), (320, float("inf")))


def _band(width: float) -> str | None:
    for lo, hi in WIDTH_BANDS:
        if lo <= width < hi:
            return f"> {lo}" if hi == float("inf") else f"{lo}-{hi}"
    return None


def accuracy_by_face_width(render_dirs, fitted, est_dir) -> dict:
    """Detection, fitting and the §5.1 metrics per band of true face width on framed render sets.

    Each true face (in the frame, at least 40 px wide) is matched to the fitted record of its photo
    whose landmark box overlaps its box most (IoU > 0.3): found (a record or a refusal with its
    box), fitted (a record) and estimated (an ``ok`` row per model) are counted per band, and each
    estimate is scored against the photo's true probe (area-resampled to its grid) with the case's
    own sky kind and sun, as ``make eval-real`` does. Returns ``{"rows": per-face rows, "table":
    markdown}``."""
    import pyarrow.parquet as pq

    cases, where = {}, {}
    for d in map(Path, render_dirs):
        for cid, meta in load_cases(d).items():
            cases[cid], where[cid] = meta, d
    records = {}
    for rec in iter_records(fitted):
        if hasattr(rec, "face_id") and hasattr(rec, "meta"):
            records.setdefault(Path(rec.source_path).stem, []).append(rec)
    refused = {}
    status = Path(fitted) / "status" / "fit_faces.parquet"
    if status.is_file():
        for row in pq.read_table(status).to_pylist():
            refused[Path(row["source_path"]).stem] = json.loads(row["rejected_json"])
    estimates = pq.read_table(Path(est_dir) / "estimates.parquet").to_pylist()
    by_face: dict[str, list[dict]] = {}
    for est in estimates:
        by_face.setdefault(est["face_id"], []).append(est)
    truth_cache: dict = {}
    rows = []
    for cid, meta in sorted(cases.items()):
        recs = records.get(cid, [])
        boxes = np.array([r.meta.get("face_box_px", [0, 0, 0, 0]) for r in recs], np.float64).reshape(-1, 4)
        refused_boxes = [r for r in refused.get(cid, []) if r.get("box") is not None]
        for face in meta.get("faces", []):
            if not face["in_frame"] or face["width_px"] < WIDTH_BANDS[0][0]:
                continue
            box = np.asarray(face["box"], np.float64)
            row = {"case": cid, "framing": meta.get("framing", "portrait"), "width_px": face["width_px"],
                   "band": _band(face["width_px"]), "yaw_deg": face["pose"]["yaw_deg"], "found": False,
                   "fitted": False, "estimates": {}}
            overlap = iou(box, boxes) if len(boxes) else np.zeros(0)
            if len(overlap) and overlap.max() > 0.3:
                rec = recs[int(np.argmax(overlap))]
                row.update(found=True, fitted=True, face_id=rec.face_id)
                for est in by_face.get(rec.face_id, []):
                    if est["status"] != "ok":
                        continue
                    grid = LatLongGrid(est["grid_height"], est["grid_width"])
                    probe = read_exr(Path(est_dir) / est["probe_path"]).astype(np.float64)
                    truth = _truth_on(where[cid], cid, grid, truth_cache)
                    sky = meta["sky"]
                    overcast = sky["kind"] == "overcast"
                    est_sun = None if est.get("sun_direction") is None else np.asarray(est["sun_direction"])
                    row["estimates"][est["model"]] = evaluate_pair(
                        probe, truth, grid, overcast=overcast, est_sun_dir=est_sun,
                        gt_sun_dir=None if overcast else np.asarray(sky["sun_direction"]))
                    row["overcast"] = overcast
            elif any(iou(box, np.asarray([r["box"]], np.float64))[0] > 0.3 for r in refused_boxes):
                row["found"] = True
                row["refused"] = next(r["reason"] for r in refused_boxes
                                      if iou(box, np.asarray([r["box"]], np.float64))[0] > 0.3)
            rows.append(row)
    return {"rows": rows, "table": _width_table(rows)}


def _width_table(rows: list[dict]) -> str:
    models = sorted({m for r in rows for m in r["estimates"]})
    lines = ["| face width (px) | faces | found | fitted | " + " | ".join(
        f"{m}: estimated | Sun-ang ° mean (median), clear | MAE (s) | Full-dω MAE (l)" for m in models) + " |",
        "|---|---|---|---|" + "---|---|---|---|" * len(models)]
    bands = [_band(lo) for lo, _ in WIDTH_BANDS] + ["all"]
    for band in bands:
        sel = [r for r in rows if band == "all" or r["band"] == band]
        if not sel:
            continue
        cells = [band, str(len(sel)), f"{sum(r['found'] for r in sel)}", f"{sum(r['fitted'] for r in sel)}"]
        for m in models:
            ests = [r["estimates"][m] for r in sel if m in r["estimates"]]
            clear = [e["Sun-ang (°)"] for r, e in ((r, r["estimates"].get(m)) for r in sel)
                     if e is not None and not r.get("overcast") and np.isfinite(e["Sun-ang (°)"])]
            sun = f"{np.mean(clear):.1f} ({np.median(clear):.1f}), n = {len(clear)}" if clear else "—"
            mae = f"{np.mean([e['MAE (s)'] for e in ests]):.3f}" if ests else "—"
            full = f"{np.mean([e['Full-dω MAE (l)'] for e in ests]):.4f}" if ests else "—"
            cells += [str(len(ests)), sun, mae, full]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
