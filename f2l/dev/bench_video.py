"""``f2l dev bench-video``: frames per second of ``f2l video``, start-up, and the error beside them.

Each clip runs as a fresh process (``python -m f2l.cli video CLIP --json --no-preview --every 0``),
as a user runs it, so the start-up counts Python, the imports, the models and the head's table
(from its disk cache; ``--cold-cache`` builds it first, once). Reported per clip: the clip's size,
the start-up (wall time before the first frame: the process's wall time less the clip's own
processing and writing), frames per second over the clip (tracking, fits and estimates: what the
``>= 10 frames/s`` target counts), the split of that time, peak memory, and where the clip has a
``render-faces --sequence`` truth beside it, the mean Sun-ang of its frames.
"""

from __future__ import annotations

import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _truth_for(clip: Path) -> dict | None:
    path = clip.parent.parent / "truth" / f"{clip.stem}.json"
    return json.loads(path.read_text()) if path.exists() else None


def ping_pong(clip: Path, repeat: int, out: Path) -> tuple[Path, list[int]]:
    """A clip ``repeat`` times as long: played forward, backward, forward... (the same light; a
    long clip for the frames-per-second figure from a short render). Returns it and, per frame,
    its frame in ``clip``."""
    import cv2

    from f2l.video.decode import probe_video, read_frames

    info = probe_video(clip)
    frames = [rgb for _, _, rgb in read_frames(clip)]
    order = []
    for k in range(repeat):
        order += list(range(len(frames))) if k % 2 == 0 else list(range(len(frames) - 1, -1, -1))
    path = out / f"{clip.stem}-x{repeat}.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), info.fps, (info.width, info.height))
    for i in order:
        writer.write(cv2.cvtColor(frames[i], cv2.COLOR_RGB2BGR))
    writer.release()
    return path, order


def _jitter(out: Path) -> float | None:
    """RMS (degrees) of the sun's change between consecutive frames of one segment."""
    import pyarrow.parquet as pq

    rows = {r["frame"]: r for r in pq.read_table(out / "frames.parquet").to_pylist() if r["sun_direction"] is not None}
    steps = [math.degrees(math.acos(float(np.clip(np.dot(rows[f]["sun_direction"], rows[f + 1]["sun_direction"]), -1, 1))))
             for f in rows if f + 1 in rows and rows[f]["segment"] == rows[f + 1]["segment"]]
    return float(np.sqrt(np.mean(np.square(steps)))) if steps else None


def _sun_ang(out: Path, truth: dict, frame_map: list[int] | None = None) -> float | None:
    import pyarrow.parquet as pq

    per_frame = {int(f["frame"]): f for f in truth["per_frame"]}
    errors = []
    for r in pq.read_table(out / "frames.parquet").to_pylist():
        if r["status"] != "ok" or r["sun_direction"] is None:
            continue
        t = np.asarray(per_frame[r["frame"] if frame_map is None else frame_map[r["frame"]]]["sun_direction"], np.float64)
        errors.append(math.degrees(math.acos(float(np.clip(t @ np.asarray(r["sun_direction"]), -1, 1)))))
    return float(np.mean(errors)) if errors else None


def bench_clip(clip: Path, model: str = "sunsky", extra: list[str] | None = None, repeat: int = 1) -> dict:
    """One clip in a fresh process (module docstring); ``repeat`` > 1 plays it back and forth
    (:func:`ping_pong`) that many times."""
    truth = _truth_for(clip)
    with tempfile.TemporaryDirectory() as tmp:
        frame_map = None
        if repeat > 1:
            clip, frame_map = ping_pong(clip, repeat, Path(tmp))
        run_out = Path(tmp) / "out"
        cmd = [sys.executable, "-m", "f2l.cli", "video", str(clip), "-m", model, "--out", str(run_out), "--json", "--no-preview",
               "--every", "0", *(extra or [])]
        if truth is not None and "--focal-35mm" not in (extra or []):
            from f2l.io.photo.exif import DIAGONAL_35MM_MM

            f35 = float(truth["focal_px"]) / math.hypot(truth["width_px"], truth["height_px"]) * DIAGONAL_35MM_MM
            cmd += ["--focal-35mm", f"{f35:.4f}"]
        env = dict(os.environ)
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            return {"clip": clip.name, "error": (proc.stderr or proc.stdout).strip()[-400:]}
        summary = json.loads(proc.stdout.strip().splitlines()[-1])
        timings = summary["timings"]
        peak_mib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
        row = {
            "clip": clip.name, "frames": summary["frames"], "size": f"{timings.get('width', '')}",
            "wall_s": round(wall, 2), "startup_s": round(wall - timings["total_s"] - timings.get("write_s", 0.0), 2),
            "frames_per_s": timings["frames_per_s"], "track_s": timings["track_s"], "fit_s": timings["fit_s"],
            "estimate_s": timings["estimate_s"], "estimates": timings["estimates"], "peak_mib": round(peak_mib),
            "sun_ang": _sun_ang(run_out, truth, frame_map) if truth is not None else None,
            "jitter_deg": _jitter(run_out),
        }
        from f2l.video.decode import probe_video

        info = probe_video(clip)
        row["size"] = f"{info.width}x{info.height}"
        return row


def bench_video(clips: list[Path], model: str = "sunsky", extra: list[str] | None = None,
                cold_cache: bool = False, repeat: int = 1) -> list[dict]:
    """Every clip (folders: their ``clips/*.mp4`` or video files)."""
    files: list[Path] = []
    for c in map(Path, clips):
        files += sorted((c / "clips").glob("*.mp4")) if (c / "clips").is_dir() else sorted(c.glob("*.mp4")) if c.is_dir() else [c]
    if cold_cache:
        from f2l.video.estimate import default_grid
        from f2l.video.head import cache_dir, cached_head_transport

        for old in (cache_dir() / "heads").glob("*.npz"):
            old.unlink()
        t0 = time.perf_counter()
        cached_head_transport(default_grid())
        print(f"head table built and cached in {time.perf_counter() - t0:.1f} s (once a machine)", file=sys.stderr)
    return [bench_clip(f, model, extra, repeat) for f in files]


def table(rows: list[dict]) -> str:
    lines = ["| clip | size | frames | start-up s | frames/s | track / fit / estimate s | estimates | peak MiB | Sun-ang ° | jitter ° RMS |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['clip']} | failed: {r['error']} ||||||||")
            continue
        sun = "–" if r["sun_ang"] is None else f"{r['sun_ang']:.1f}"
        jitter = "–" if r["jitter_deg"] is None else f"{r['jitter_deg']:.3f}"
        lines.append(f"| {r['clip']} | {r['size']} | {r['frames']} | {r['startup_s']:.2f} | {r['frames_per_s']:.1f} | "
                     f"{r['track_s']:.2f} / {r['fit_s']:.2f} / {r['estimate_s']:.2f} | {r['estimates']} | "
                     f"{r['peak_mib']} | {sun} | {jitter} |")
    return "\n".join(lines) + "\n"
