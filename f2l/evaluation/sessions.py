"""``f2l eval sessions``: several photos of one session, each face alone against the session's one light.

On ``f2l eval render-faces --session-size K`` sets (K path-traced portraits of different people
under one light, each camera turned ``camera_yaw_deg`` about +Y; render meta ``session``),
fitted by ``f2l fit-faces``: per session, every photo's face (its first by face id) is estimated
by itself (:func:`f2l.estimate.estimator.estimate`) and scored against its own photo's true
probe; then all of them at once, as ``f2l estimate --joint session`` does
(:mod:`f2l.estimate.group_record`): each face turned into the first photo's camera frame by
``yaw_k − yaw_0`` (:func:`f2l.estimate.frames.turn_observation`), one exposure per photo
(:func:`f2l.estimate.joint.estimate_joint`), the joint probe scored against the first photo's true
probe. Metrics are §5.1's (:func:`f2l.metrics.evaluate_pair`; Sun-ang on clear skies only); the
singles' figures are the mean over the session's faces, their time the sum. A session needs two
fitted photos, its first among them (the joint's frame and truth).

:func:`tag_records` writes the fitted records again with ``meta["session"]`` and
``meta["camera_yaw_deg"]`` from the render meta, for ``f2l estimate --joint session``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from f2l.estimate.config import EstimatorConfig
from f2l.estimate.estimator import estimate
from f2l.estimate.frames import turn_observation
from f2l.estimate.group_record import YAW_KEY
from f2l.estimate.joint import estimate_joint
from f2l.estimate.observation import EstimationError, FaceObservation
from f2l.evaluation.evaluate import _truth_on, load_cases, records_by_case
from f2l.io.atomic import write_text_atomic
from f2l.io.shards import BadRecord, ShardWriter, iter_records
from f2l.lighting.grid import LatLongGrid
from f2l.metrics import evaluate_pair
from f2l.models.registry import load_model

METRICS = ("Sun-ang (°)", "MAE (s)", "Full-dω MAE (l)")


def session_photos(render_dir, fitted) -> dict[str, list[tuple[dict, object]]]:
    """Session id -> [(render meta, fitted record)] of its photos with a fitted face, in case order
    (a photo's first face by face id)."""
    cases = {cid: m for cid, m in load_cases(Path(render_dir)).items() if m.get("session")}
    first = {cid: recs[0] for cid, recs in records_by_case(fitted, cases).items()}
    sessions: dict[str, list] = {}
    for cid in sorted(cases, key=lambda c: cases[c]["index"]):
        if cid in first:
            sessions.setdefault(cases[cid]["session"], []).append((cases[cid], first[cid]))
    return sessions


def session_rows(render_dir, fitted, model_name: str = "sunsky", cfg: EstimatorConfig | None = None,
                 progress=None) -> list[dict]:
    """One row per session: its faces, yaws, the truth's sky kind, the singles' mean and the joint's
    metrics, their times and the faces the joint left out."""
    cfg = cfg or EstimatorConfig(sun_prior_from_capture=False)
    model, cache, rows = None, {}, []
    for sid, photos in sorted(session_photos(render_dir, fitted).items()):
        if len(photos) < 2 or photos[0][0]["camera_yaw_deg"] != 0.0:
            continue
        recs = [rec for _, rec in photos]
        grid = LatLongGrid(recs[0].grid_height, recs[0].grid_width)
        model = model if model is not None and model.grid.shape == grid.shape else load_model(model_name, grid)

        def score(meta, probe, sun):
            overcast = meta["sky"]["kind"] == "overcast"
            m = evaluate_pair(np.asarray(probe, np.float64), _truth_on(render_dir, meta["face_id"], grid, cache),
                              grid, overcast=overcast, est_sun_dir=sun,
                              gt_sun_dir=None if overcast else np.asarray(meta["sky"]["sun_direction"]))
            return [float(m[k]) for k in METRICS]

        obs = [FaceObservation(r.normals, r.observed_rgb, r.mask, r.visibility_bits, grid, r.face_id, r.points)
               for r in recs]
        singles, single_s = [], 0.0
        for (meta, _), o in zip(photos, obs):
            t = time.perf_counter()
            try:
                res = estimate(o, model, cfg)
                singles.append(score(meta, res.probe, res.sun_direction))
            except EstimationError:
                pass
            single_s += time.perf_counter() - t
        yaws = [float(meta["camera_yaw_deg"]) for meta, _ in photos]
        turned = [turn_observation(o, y - yaws[0]) for o, y in zip(obs, yaws)]
        t = time.perf_counter()
        try:
            joint = estimate_joint(turned, model, cfg, exposure_group=list(range(len(turned))),
                                   pixel_rc=[r.pixel_rc for r in recs])
        except EstimationError:
            continue
        joint_s = time.perf_counter() - t
        if not singles:
            continue
        first = photos[0][0]
        row = {"session": sid, "faces": len(photos), "yaws_deg": yaws, "source": first["lighting"]["source"],
               "overcast": first["sky"]["kind"] == "overcast", "single": np.mean(singles, axis=0).tolist(),
               "singles": singles, "joint": score(first, joint.result.probe, joint.result.sun_direction),
               "single_s": single_s, "joint_s": joint_s, "left_out": sum(not s.used for s in joint.faces)}
        rows.append(row)
        if progress is not None:
            progress(row)
    return rows


def session_table(rows: list[dict]) -> str:
    """Markdown: sessions (clear), faces, the singles' and the joint's mean metrics, times."""
    clear = [r for r in rows if not r["overcast"] and np.isfinite(r["joint"][0]) and np.isfinite(r["single"][0])]
    s_ang, j_ang = (float(np.mean([r[k][0] for r in clear])) if clear else float("nan") for k in ("single", "joint"))
    s_mae, j_mae, s_full, j_full = (float(np.mean([r[k][i] for r in rows])) if rows else float("nan")
                                    for i in (1, 2) for k in ("single", "joint"))
    ratio = (lambda a, b: f"{b / a:.2f}" if a else "–")
    return "\n".join([
        "| sessions (clear) | faces | Sun-ang ° single → joint (ratio) | MAE (s) single → joint (ratio) | "
        "Full-dω MAE (l) single → joint | faces left out | time s: singles → joint |",
        "|---|---|---|---|---|---|---|",
        f"| {len(rows)} ({len(clear)}) | {sum(r['faces'] for r in rows)} | {s_ang:.1f} → {j_ang:.1f} "
        f"({ratio(s_ang, j_ang)}) | {s_mae:.3f} → {j_mae:.3f} ({ratio(s_mae, j_mae)}) | {s_full:.4f} → {j_full:.4f} | "
        f"{sum(r['left_out'] for r in rows)} | {sum(r['single_s'] for r in rows):.0f} → "
        f"{sum(r['joint_s'] for r in rows):.0f} |"])


def write_session_report(rows: list[dict], out: Path) -> str:
    """``sessions.md`` (the table) and ``sessions.json`` (the rows) under ``out``."""
    Path(out).mkdir(parents=True, exist_ok=True)
    text = session_table(rows)
    for name, body in (("sessions.md", text + "\n"), ("sessions.json", json.dumps(rows, indent=1))):
        write_text_atomic(Path(out) / name, body)
    return text


def tag_records(render_dir, fitted, out) -> int:
    """Write ``fitted``'s records to ``out`` with their photo's ``meta["session"]`` and
    ``meta["camera_yaw_deg"]`` (from the render meta; other records unchanged). Returns the
    number tagged."""
    cases = load_cases(Path(render_dir))
    tagged = 0
    with ShardWriter(out, overwrite=True) as writer:
        for rec in iter_records(fitted):
            if isinstance(rec, BadRecord):
                continue
            meta = cases.get(Path(rec.source_path).stem, {})
            if meta.get("session"):
                rec.meta["session"] = meta["session"]
                rec.meta[YAW_KEY] = float(meta["camera_yaw_deg"])
                tagged += 1
            writer.write(rec)
    return tagged
