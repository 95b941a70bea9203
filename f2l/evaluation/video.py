"""``f2l eval video``: light from clips against the truth, and against f2l on each frame alone.

On ``f2l eval render-faces --sequence`` folders (path-traced clips of a head turning and nodding:
static light, a cloud over the sun, a cut to another shot; ``truth/<clip>.json``), each clip is
run through ``f2l video`` (:func:`f2l.video.run.estimate_clip`) and scored frame by frame:

* **Sun-ang**: the angle between each frame's estimated sun and the true one (frames whose face is
  usable, in clear-sky segments); the clip's mean, and the same frames' mean when each is
  estimated alone as a photo (every ``alone_every``-th frame: detection, fit with ray-cast
  transport and ``estimate``, as ``f2l estimate photo.png`` does);
* **jitter**: the RMS of the estimated sun's change from frame to frame within a true segment
  (a static light should not move);
* **settling** after a change (cloud or cut): the time from the change until the error stays
  within ``SETTLE_DEG`` of the segment's final median error, and whether a new segment started
  within ``DETECT_FRAMES`` frames of it;
* **§5.1**: MAE (s) of the relit scene and Full-dω MAE (l) of the probe, every ``metrics_every``-th
  frame, for the clip's light and for the frame alone;
* **speed**: frames per second of the whole clip (tracking, fits, estimates) after start-up.

Clips of seed 0 tune, the others report (as ``make eval-groups``' seeds).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np

SETTLE_DEG = 5.0
DETECT_FRAMES = 3


def load_truths(render_dir) -> list[tuple[Path, dict]]:
    """(clip path, truth) of every rendered clip of a ``render-faces --sequence`` folder, by id."""
    render_dir = Path(render_dir)
    out = []
    for path in sorted((render_dir / "truth").glob("*.json")):
        truth = json.loads(path.read_text())
        out.append((render_dir / truth.get("video", f"clips/{truth['clip_id']}.mp4"), truth))
    return out


def _angle_deg(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return math.degrees(math.acos(float(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0))))


def _person_rows(rows: list[dict]) -> dict[int, dict]:
    """frame -> the row of the clip's main person (the one with the most usable frames)."""
    counts: dict[int, int] = {}
    for r in rows:
        if r["status"] == "ok":
            counts[r["person"]] = counts.get(r["person"], 0) + 1
    main = max(counts, key=counts.get) if counts else (rows[0]["person"] if rows else -1)
    return {r["frame"]: r for r in rows if r["person"] == main}


def jitter_rms_deg(frames: list[int], suns: dict[int, np.ndarray], segment_of: dict[int, int]) -> float | None:
    """RMS of the sun's change between consecutive frames of one true segment (None: < 2 frames)."""
    steps = [_angle_deg(suns[f], suns[f + 1]) for f in frames
             if f + 1 in suns and segment_of.get(f) == segment_of.get(f + 1)]
    return float(np.sqrt(np.mean(np.square(steps)))) if steps else None


def settle_s(errors: dict[int, float], change_frame: int, last_frame: int, fps: float) -> float | None:
    """Seconds from ``change_frame`` until the error stays within ``SETTLE_DEG`` of the segment's
    final median (its second half's); None when the segment has no scored frame."""
    after = sorted(f for f in errors if change_frame <= f <= last_frame)
    if not after:
        return None
    final = float(np.median([errors[f] for f in after[len(after) // 2:]]))
    settle = after[-1]
    for f in reversed(after):
        if errors[f] > final + SETTLE_DEG:
            break
        settle = f
    return (settle - change_frame) / fps


def _alone(frame_rgb, truth, model, cfg, landmarker, fit_options):
    """One frame estimated as a photo: (sun direction, probe, seconds) or None."""
    from f2l.estimate.estimator import estimate
    from f2l.estimate.observation import EstimationError, FaceObservation
    from f2l.face.fit import FaceFit, fit_photo_faces
    from f2l.io.photo.core import Photo

    t0 = time.perf_counter()
    photo = Photo(path="frame", kind="video", codes=frame_rgb, focal_px=float(truth["focal_px"]),
                  focal_source="truth", orientation=1, exif={})
    fits = [f for f in fit_photo_faces(photo, landmarker, fit_options) if isinstance(f, FaceFit)]
    if not fits:
        return None
    f = fits[0]
    obs = FaceObservation(f.normals, f.observed_rgb, f.mask, f.visibility_bits, model.grid, "alone", f.points)
    try:
        res = estimate(obs, model, cfg)
    except EstimationError:
        return None
    return res.sun_direction, res.probe, time.perf_counter() - t0


def _in_cone(errors: dict[int, float], rows: dict[int, dict], key: str) -> float | None:
    """The share of the frames in ``errors`` (Sun-ang, deg) whose row's cone ``key`` holds the true sun."""
    held = [errors[f] <= rows[f][key] for f in errors if rows[f].get(key) is not None]
    return float(np.mean(held)) if held else None


def eval_clip(clip_path: Path, truth: dict, render_dir: Path, out: Path, options, *, alone_every: int = 4,
              metrics_every: int = 8, landmarker=None) -> dict:
    """One clip's row (module docstring)."""
    from f2l.estimate.config import EstimatorConfig
    from f2l.estimate.record import _get_model
    from f2l.face.landmarker import FaceLandmarker
    from f2l.io.exr import read_exr
    from f2l.lighting.resample import resample
    from f2l.metrics import evaluate_pair
    from f2l.pipeline.faces import fit_options as pipeline_fit_options
    from f2l.pipeline.spec import load_pipeline
    from f2l.video.decode import read_frames
    from f2l.video.estimate import default_grid
    from f2l.video.run import estimate_clip

    clip_id = truth["clip_id"]
    opts = dataclasses.replace(options, focal_px=float(truth["focal_px"]))
    summary = estimate_clip(clip_path, out / clip_id, opts, every=metrics_every, preview=False)
    import pyarrow.parquet as pq

    rows = _person_rows(pq.read_table(out / clip_id / "frames.parquet").to_pylist())
    per_frame = {int(f["frame"]): f for f in truth["per_frame"]}
    segments = {int(s["segment"]): s for s in truth["segments"]}
    clear = {k for k, s in segments.items() if s.get("sky_kind", "clear") == "clear" and s.get("sun_direction") is not None}
    segment_of = {f: int(p["segment"]) for f, p in per_frame.items()}
    suns = {f: np.asarray(r["sun_direction"]) for f, r in rows.items() if r["sun_direction"] is not None}
    scored = [f for f in sorted(suns) if rows[f]["status"] == "ok" and segment_of.get(f) in clear]
    errors = {f: _angle_deg(suns[f], per_frame[f]["sun_direction"]) for f in scored}

    grid = default_grid()
    model = _get_model(options.model, grid)
    cfg = EstimatorConfig(sun_prior_from_capture=False)
    spec = load_pipeline()
    fit_opts = pipeline_fit_options(dict(spec.params("fit-faces")), spec.params("transport"), (grid.height, grid.width))
    landmarker = landmarker or FaceLandmarker()
    truth_probes: dict[int, np.ndarray] = {}

    def truth_probe(segment: int) -> np.ndarray:
        if segment not in truth_probes:
            truth_probes[segment] = resample(read_exr(render_dir / segments[segment]["probe"]).astype(np.float64),
                                             grid.height, grid.width)
        return truth_probes[segment]

    def metrics(probe, sun, f) -> tuple[float, float]:
        k = segment_of[f]
        m = evaluate_pair(np.asarray(probe, np.float64), truth_probe(k), grid, overcast=k not in clear,
                          est_sun_dir=sun, gt_sun_dir=None if k not in clear else segments[k]["sun_direction"])
        return float(m["MAE (s)"]), float(m["Full-dω MAE (l)"])

    alone_err, alone_video_err, alone_s, m_video, m_alone = {}, {}, [], [], []
    for index, _, rgb in read_frames(clip_path):
        row = rows.get(index)
        if row is None or row["status"] != "ok" or row["params"] is None:
            continue
        want_alone = index % alone_every == 0
        want_metrics = index % metrics_every == 0 and row.get("probe_path")
        if not (want_alone or want_metrics):
            continue
        single = _alone(rgb, truth, model, cfg, landmarker, fit_opts)
        if want_alone and single is not None:
            alone_s.append(single[2])
            if index in errors and single[0] is not None:
                alone_err[index] = _angle_deg(single[0], per_frame[index]["sun_direction"])
                alone_video_err[index] = errors[index]
        if want_metrics and single is not None:
            probe = read_exr(out / clip_id / row["probe_path"])
            m_video.append(metrics(probe, suns.get(index), index))
            m_alone.append(metrics(single[1], single[0], index))

    change = truth.get("change_frame")
    seg1_last = max((f for f, k in segment_of.items() if k == 1), default=None)
    starts = [s["first_frame"] for s in summary["segments"][1:]]
    timings = summary["timings"]
    return {
        "clip": clip_id, "kind": truth["kind"], "frames": truth["frames"],
        "part": "tune" if clip_id.split("-")[1] == "s0" else "report",
        "scored_frames": len(errors),
        "sun_ang_video": float(np.mean(list(errors.values()))) if errors else None,
        "sun_ang_video_median": float(np.median(list(errors.values()))) if errors else None,
        "alone_frames": len(alone_err),
        "sun_ang_video_same_frames": float(np.mean(list(alone_video_err.values()))) if alone_err else None,
        "sun_ang_alone": float(np.mean(list(alone_err.values()))) if alone_err else None,
        "jitter_rms_deg": jitter_rms_deg(sorted(suns), suns, segment_of),
        # the share of scored frames whose true sun lies in the window's 68% / 90% cone
        "in_cone68": _in_cone(errors, rows, "sun_cone68_deg"), "in_cone90": _in_cone(errors, rows, "sun_cone90_deg"),
        "change_frame": change,
        "change_found": None if change is None else any(abs(s - change) <= DETECT_FRAMES for s in starts),
        "false_changes": sum(1 for s in starts if change is None or abs(s - change) > DETECT_FRAMES),
        "settle_s": None if change is None or seg1_last is None or 1 not in clear
        else settle_s(errors, change, seg1_last, float(truth["fps"])),
        "mae_s_video": float(np.mean([m[0] for m in m_video])) if m_video else None,
        "mae_s_alone": float(np.mean([m[0] for m in m_alone])) if m_alone else None,
        "full_domega_video": float(np.mean([m[1] for m in m_video])) if m_video else None,
        "full_domega_alone": float(np.mean([m[1] for m in m_alone])) if m_alone else None,
        "frames_per_s": timings.get("frames_per_s"), "startup_s": timings.get("startup_s"),
        "alone_s_per_frame": float(np.mean(alone_s)) if alone_s else None,
    }


def eval_video(render_dirs, out, options, *, alone_every: int = 4, metrics_every: int = 8, progress=None) -> list[dict]:
    """Every clip's row (:func:`eval_clip`); writes ``OUT/video.json`` and ``OUT/video.md``."""
    from f2l.face.landmarker import FaceLandmarker
    from f2l.io.progress import Progress

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    clips = [(d, c, t) for d in map(Path, render_dirs) for c, t in load_truths(d)]
    report = Progress(progress, "clips", "clip", len(clips))
    landmarker = FaceLandmarker()
    rows = []
    for render_dir, clip_path, truth in clips:
        rows.append(eval_clip(clip_path, truth, render_dir, out / "runs", options, alone_every=alone_every,
                              metrics_every=metrics_every, landmarker=landmarker))
        report.advance()
    (out / "video.json").write_text(json.dumps(rows, indent=1))
    (out / "video.md").write_text(video_table(rows))
    return rows


def _fmt(v, digits: int = 1) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    return f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def _mean(rows, key):
    vals = [r[key] for r in rows if r.get(key) is not None]
    return float(np.mean(vals)) if vals else None


def _pct(v) -> str:
    return "–" if v is None else f"{v:.0%}"


def video_table(rows: list[dict]) -> str:
    """The markdown tables: per clip, then per part and kind."""
    head = ("| clip | part | kind | Sun-ang ° clip (median) | same frames: clip → alone | jitter ° RMS | change found | "
            "false changes | settles s | MAE (s) clip / alone | Full-dω clip / alone | frames/s |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    lines = [head]
    for r in rows:
        lines.append(
            f"| {r['clip']} | {r['part']} | {r['kind']} | {_fmt(r['sun_ang_video'])} ({_fmt(r['sun_ang_video_median'])}) | "
            f"{_fmt(r['sun_ang_video_same_frames'])} → {_fmt(r['sun_ang_alone'])} | {_fmt(r['jitter_rms_deg'], 2)} | "
            f"{_fmt(r['change_found'])} | {r['false_changes']} | {_fmt(r['settle_s'], 2)} | "
            f"{_fmt(r['mae_s_video'], 3)} / {_fmt(r['mae_s_alone'], 3)} | "
            f"{_fmt(r['full_domega_video'], 4)} / {_fmt(r['full_domega_alone'], 4)} | {_fmt(r['frames_per_s'])} |\n")
    lines.append("\n| part | clips | Sun-ang ° clip | same frames: clip → alone (ratio) | jitter ° RMS (static clips) | "
                 "changes found | settles s (mean) | MAE (s) clip / alone | in 68% / 90% cone | frames/s |\n"
                 "|---|---|---|---|---|---|---|---|---|---|\n")
    for part in ("tune", "report", "all"):
        sel = [r for r in rows if part == "all" or r["part"] == part]
        if not sel:
            continue
        same, alone = _mean(sel, "sun_ang_video_same_frames"), _mean(sel, "sun_ang_alone")
        ratio = None if not same or not alone else same / alone
        static = [r for r in sel if r["kind"] == "static"]
        changes = [r for r in sel if r["change_found"] is not None]
        lines.append(
            f"| {part} | {len(sel)} | {_fmt(_mean(sel, 'sun_ang_video'))} | {_fmt(same)} → {_fmt(alone)} "
            f"({_fmt(ratio, 2)}×) | {_fmt(_mean(static, 'jitter_rms_deg'), 2)} | "
            f"{sum(r['change_found'] for r in changes)}/{len(changes)} | {_fmt(_mean(sel, 'settle_s'), 2)} | "
            f"{_fmt(_mean(sel, 'mae_s_video'), 3)} / {_fmt(_mean(sel, 'mae_s_alone'), 3)} | "
            f"{_pct(_mean(sel, 'in_cone68'))} / {_pct(_mean(sel, 'in_cone90'))} | {_fmt(_mean(sel, 'frames_per_s'))} |\n")
    return "".join(lines)
