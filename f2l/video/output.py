"""What ``f2l video`` writes: the frames table, probes, the sun's track and a preview clip.

``OUT/``
  ``frames.parquet``   one row per frame and person (:data:`FRAME_COLUMNS`): status and reason,
                       segment, whether the frame was sampled, the light's parameters, the sun's
                       direction, elevation and azimuth (degrees, f2l's grid convention: azimuth 0
                       = the camera's -Z, +90° = +X), the window (frames of the samples) the light
                       came from, the face's residual under it (sampled frames), the probe's path,
                       the sun's 68% / 90% cones (deg) and the predicted relit-scene MAE (s) of
                       the window's estimate (f2l.estimate.uncertainty; null for warm refits).
                       A frame without any known person has one row with person -1.
  ``probes/<model>/frame-NNNNNN.exr``  the light of every ``every``-th frame (lat-long, +Y up,
                       relative units: the clip's linear values).
  ``sun_track.png``    the sun's elevation and azimuth over the clip, segments marked.
  ``preview.mp4``      the clip beside its probe (the sun ringed) and the sun's track so far.
  ``clip.json``        the clip, the options, the segments and the timings.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict
from pathlib import Path

import numpy as np

FRAMES_SCHEMA_VERSION = 2  # 2: the sun cone columns
PREVIEW_HEIGHT = 360


def _probe(model, params, ground_albedo) -> np.ndarray:
    from f2l.estimate.latent import _probe_with_ground

    return _probe_with_ground(model, np.asarray(params, np.float64), 0.2 if ground_albedo is None else ground_albedo)


def frame_lights(rows: list[dict]) -> dict[int, dict]:
    """The light of each frame (persons share it): frame -> its first row with parameters."""
    out: dict[int, dict] = {}
    for row in rows:
        if row.get("params") is not None and row["frame"] not in out:
            out[row["frame"]] = row
    return out


def write_probes(rows: list[dict], model, out: Path, model_name: str, every: int) -> dict[int, str]:
    """EXR probes of every ``every``-th frame with a light; frame -> path relative to ``out``."""
    from f2l.io.exr import write_exr

    written: dict[int, str] = {}
    if every < 1:
        return written
    for frame, row in sorted(frame_lights(rows).items()):
        if frame % every:
            continue
        rel = f"probes/{model_name}/frame-{frame:06d}.exr"
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        write_exr(out / rel, _probe(model, row["params"], row["ground_albedo"]),
                  metadata={"f2l_model": model_name, "f2l_frame": str(frame), "f2l_time_s": repr(float(row["time_s"])),
                            "f2l_segment": str(row["segment"]), "f2l_convention": "latlong,+Y up,centre=-Z",
                            "f2l_units": "relative: the clip's linear values (1 = full scale)",
                            **{f"f2l_{k}": "" if row.get(k) is None else repr(float(row[k]))
                               for k in ("sun_cone68_deg", "sun_cone90_deg", "predicted_mae_s")}})
        written[frame] = rel
    return written


def write_frames_table(rows: list[dict], out: Path, param_names: list[str], probes: dict[int, str]) -> Path:
    """``frames.parquet`` (atomic)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    columns = {
        "frame": pa.int64(), "time_s": pa.float64(), "person": pa.int64(), "status": pa.string(),
        "message": pa.string(), "segment": pa.int64(), "sample": pa.bool_(), "box": pa.list_(pa.float64()),
        "yaw_deg": pa.float64(), "pitch_deg": pa.float64(), "params": pa.list_(pa.float64()),
        "sun_direction": pa.list_(pa.float64()), "sun_elevation_deg": pa.float64(), "sun_azimuth_deg": pa.float64(),
        "ground_albedo": pa.float64(), "window": pa.list_(pa.int64()), "estimate_frame": pa.int64(),
        "residual": pa.float64(), "probe_path": pa.string(),
        "sun_cone68_deg": pa.float64(), "sun_cone90_deg": pa.float64(), "predicted_mae_s": pa.float64(),
    }
    data = {name: [] for name in columns}
    for row in rows:
        for name in columns:
            value = probes.get(row["frame"]) if name == "probe_path" else row.get(name)
            if isinstance(value, float) and not math.isfinite(value):
                value = None
            data[name].append(value)
    schema = pa.schema([pa.field(n, t) for n, t in columns.items()],
                       metadata={"f2l_frames_schema": str(FRAMES_SCHEMA_VERSION), "param_names": json.dumps(param_names)})
    table = pa.table({n: pa.array(v, type=columns[n]) for n, v in data.items()}, schema=schema)
    path = out / "frames.parquet"
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    pq.write_table(table, tmp)
    os.replace(tmp, path)
    return path


def sun_track(rows: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(time_s, elevation_deg, azimuth_deg) of each frame with a sun, in frame order."""
    lights = frame_lights(rows)
    frames = [f for f in sorted(lights) if lights[f].get("sun_elevation_deg") is not None]
    return (np.array([lights[f]["time_s"] for f in frames]), np.array([lights[f]["sun_elevation_deg"] for f in frames]),
            np.array([lights[f]["sun_azimuth_deg"] for f in frames]))


def plot_sun_track(rows: list[dict], segments: list[tuple[int, str]], fps: float, path: Path,
                   truth: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> Path | None:
    """``sun_track.png``: elevation and azimuth against time, segment starts dashed (None: no sun)."""
    t, el, az = sun_track(rows)
    if not len(t):
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(7, 4), sharex=True)
    for ax, values, name, k in ((axes[0], el, "elevation (°)", 1), (axes[1], az, "azimuth (°)", 2)):
        ax.plot(t, values, lw=1.5, label="estimate")
        if truth is not None:
            ax.plot(truth[0], truth[k], "k--", lw=1, label="truth")
        for frame, _ in segments[1:]:
            ax.axvline(frame / fps, color="r", ls=":", lw=1)
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8)
    axes[1].set_xlabel("time (s)")
    fig.tight_layout()
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)
    return path


def write_preview(clip_path, rows: list[dict], model, out: Path, fps: float, every: int = 1) -> Path | None:
    """``preview.mp4``: each frame beside its probe (one exposure for the clip, the sun ringed) and
    the sun's elevation so far. None when no frame has a light."""
    import cv2

    from f2l.io.preview import auto_exposure_scale, tonemap
    from f2l.video.decode import read_frames

    lights = frame_lights(rows)
    if not lights:
        return None
    grid = model.grid
    first = _probe(model, lights[min(lights)]["params"], lights[min(lights)]["ground_albedo"])
    exposure_ev = math.log2(max(auto_exposure_scale(first[: grid.sky_rows], 99.0), 1e-30))
    t_all, el_all, az_all = sun_track(rows)
    path = out / "preview.mp4"
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.mp4")
    writer = None
    probe_img = None
    try:
        for index, time_s, rgb in read_frames(clip_path, every=every):
            scale = PREVIEW_HEIGHT / rgb.shape[0]
            left = cv2.resize(rgb, (max(2, round(rgb.shape[1] * scale)) // 2 * 2, PREVIEW_HEIGHT),
                              interpolation=cv2.INTER_AREA)
            row = lights.get(index)
            if row is not None:
                probe = _probe(model, row["params"], row["ground_albedo"])
                probe_img = cv2.resize(tonemap(probe, exposure_ev=exposure_ev), (PREVIEW_HEIGHT, PREVIEW_HEIGHT // 2),
                                       interpolation=cv2.INTER_NEAREST)
                if row.get("sun_direction") is not None:
                    (r, c) = grid.direction_to_texel(np.asarray(row["sun_direction"], np.float64)[None])
                    k = probe_img.shape[0] / grid.height
                    cv2.circle(probe_img, (int((int(c[0]) + 0.5) * k), int((int(r[0]) + 0.5) * k)), 8, (255, 64, 64), 2)
            right_top = probe_img if probe_img is not None else np.zeros((PREVIEW_HEIGHT // 2, PREVIEW_HEIGHT, 3), np.uint8)
            track = _track_panel(t_all, el_all, time_s, right_top.shape[1], PREVIEW_HEIGHT - right_top.shape[0], az_all)
            frame = np.concatenate([left, np.concatenate([right_top, track], 0)], 1)
            if writer is None:
                writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps / max(every, 1),
                                         (frame.shape[1], frame.shape[0]))
            writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    finally:
        if writer is not None:
            writer.release()
    if writer is None:
        return None
    os.replace(tmp, path)
    return path


def _track_panel(t: np.ndarray, el: np.ndarray, now_s: float, width: int, height: int,
                 az: np.ndarray | None = None) -> np.ndarray:
    """A small plot (RGB) of the sun's elevation (0–90°, orange) and azimuth (±180°, blue) over the
    clip, up to ``now_s``."""
    import cv2

    panel = np.full((height, width, 3), 24, np.uint8)
    if len(t) < 2 or height < 8:
        return panel
    span = max(float(t[-1] - t[0]), 1e-6)
    x = ((t - t[0]) / span * (width - 1)).astype(np.int32)
    shown = t <= now_s
    lines = [(np.clip(el, 0, 90) / 90.0, (255, 170, 40))]
    if az is not None:
        lines.append(((np.asarray(az) + 180.0) / 360.0, (90, 160, 255)))
    for frac, colour in lines:
        y = (height - 8 - frac * (height - 24)).astype(np.int32)
        if shown.sum() >= 2:
            cv2.polylines(panel, [np.stack([x[shown], y[shown]], 1)], False, colour, 2)
    cx = int((min(max(now_s, t[0]), t[-1]) - t[0]) / span * (width - 1))
    cv2.line(panel, (cx, 0), (cx, height - 1), (128, 128, 128), 1)
    cv2.putText(panel, "sun: elevation 0-90", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 170, 40), 1)
    cv2.putText(panel, "azimuth +-180", (150, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (90, 160, 255), 1)
    return panel


def write_summary(out: Path, clip_path, light, options, probes: dict[int, str], extra: dict | None = None) -> Path:
    """``clip.json`` (atomic)."""
    summary = {"clip": str(clip_path), "fps": light.fps, "width": light.width, "height": light.height,
               "frames": len({r["frame"] for r in light.rows}),
               "segments": [{"first_frame": f, "why": why} for f, why in light.segments],
               "estimates": [{"frame": e.frame, "time_s": e.time_s, "segment": e.segment, "window": e.window,
                              "persons": e.persons, "cold": e.cold, "runtime_s": round(e.runtime_s, 4),
                              "sun_direction": None if e.sun_direction is None else [float(v) for v in e.sun_direction]}
                             for e in light.estimates],
               "probes": len(probes), "options": asdict(options), "timings": light.timings, **(extra or {})}
    path = out / "clip.json"
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(summary, indent=1))
    os.replace(tmp, path)
    return path
