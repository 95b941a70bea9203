"""``f2l video``: a clip in, a light per frame out (:mod:`f2l.video.estimate`, :mod:`f2l.video.output`)."""

from __future__ import annotations

import time
from pathlib import Path

from f2l.video.estimate import VideoOptions


def estimate_clip(clip_path, out, options: VideoOptions = VideoOptions(), *, every: int = 1, preview: bool = True,
                  max_frames: int | None = None, landmarker=None, progress=None) -> dict:
    """Track the faces of ``clip_path``, estimate its light, and write ``out`` (module
    :mod:`f2l.video.output`). Returns the summary written to ``clip.json``. Raises
    :class:`f2l.video.decode.VideoError` when the clip cannot be read."""
    from f2l.estimate.record import _get_model
    from f2l.face.landmarker import FaceLandmarker
    from f2l.video.decode import probe_video
    from f2l.video.estimate import default_grid, estimate_clip_light
    from f2l.video.head import cached_head_transport
    from f2l.video.output import plot_sun_track, write_frames_table, write_preview, write_probes, write_summary
    from f2l.video.track import track_clip

    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    info = probe_video(clip_path)
    grid = default_grid()
    head = cached_head_transport(grid)
    landmarker = landmarker or FaceLandmarker(threads=1)
    startup_s = time.perf_counter() - t0
    frames = track_clip(clip_path, landmarker, stop=max_frames, min_face_px=options.min_face_px,
                        keyframe_every=options.keyframe_every)
    total = info.frame_count if max_frames is None else min(info.frame_count, max_frames)
    light = estimate_clip_light(frames, options, fps=info.fps, width=info.width, height=info.height, head=head,
                                grid=grid, progress=progress, total_frames=total or None)
    model = _get_model(options.model, grid)
    t_write = time.perf_counter()
    probes = write_probes(light.rows, model, out, options.model, every)
    write_frames_table(light.rows, out, light.param_names, probes)
    plot_sun_track(light.rows, light.segments, light.fps, out / "sun_track.png")
    preview_path = write_preview(clip_path, light.rows, model, out, light.fps) if preview else None
    timings = {"startup_s": round(startup_s, 4), "write_s": round(time.perf_counter() - t_write, 4),
               "wall_s": round(time.perf_counter() - t0, 4)}
    light.timings.update(timings)
    return write_summary_dict(out, clip_path, light, options, probes, preview_path)


def write_summary_dict(out: Path, clip_path, light, options, probes, preview_path) -> dict:
    import json

    from f2l.video.output import write_summary

    path = write_summary(out, clip_path, light, options, probes,
                         {"preview": None if preview_path is None else str(Path(preview_path).name)})
    return json.loads(path.read_text())
