"""``f2l video``: the light of a clip, frame by frame (:mod:`f2l.video`). Thin: options, progress, exit codes."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from f2l.cli.common import JsonOut, fail

VIDEO_RESOLUTION = 104  # f2l.video.estimate.VideoOptions.resolution (not imported: --help stays light)


def video_cmd(
    clip: Path = typer.Argument(..., help="A video file (MP4, MOV, MKV, AVI...; decoded by OpenCV's FFmpeg, rotation metadata applied)."),
    model: str = typer.Option("sunsky", "--model", "-m", help="Lighting model (a compact-sun model: sunsky, hw, ...)."),
    out: Path = typer.Option(..., "--out", help="Output folder: frames.parquet, probes/, sun_track.png, preview.mp4, clip.json."),
    every: int = typer.Option(1, "--every", min=0, help="Write a probe EXR every N frames (0: none; the table has every frame)."),
    preview: bool = typer.Option(True, "--preview/--no-preview", help="Write preview.mp4: the clip beside its probe and the sun's track."),
    sample_every: int = typer.Option(8, "--sample-every", min=1, help="Fit a face every N frames (each sample joins the light's window)."),
    window_s: float = typer.Option(4.0, "--window-s", min=0.05, help="Samples of the last so many seconds share one light."),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", min=1, help="Only the first N frames."),
    focal_35mm_mm: float = typer.Option(50.0, "--focal-35mm", min=5.0, help="The camera's 35 mm-equivalent focal length (clips rarely record it)."),
    min_face_px: float = typer.Option(40.0, "--min-face-px", min=8.0, help="The smallest face to follow, in px."),
    resolution: int = typer.Option(VIDEO_RESOLUTION, "--resolution", min=32, max=256, help="Working px of a sampled face (a photo's: 104)."),
    share_suns: bool = typer.Option(True, "--share-suns/--no-share-suns", help="Consecutive segments whose suns agree within their 90% cones (a cloud, not a cut to another sun) share one sun direction."),
    json_out: JsonOut = False,
) -> None:
    """Estimate a clip's light per frame: faces tracked, one light per window of frames, restarted at cuts and sudden changes."""
    from f2l.cli.progress import progress_bars
    from f2l.models.registry import ModelNotFoundError, model_class
    from f2l.video.decode import VideoError
    from f2l.video.estimate import VideoOptions
    from f2l.video.run import estimate_clip

    try:
        model_class(model)
    except ModelNotFoundError as exc:
        fail(str(exc))
    options = VideoOptions(model=model, sample_every=sample_every, window_s=window_s, focal_35mm_mm=focal_35mm_mm,
                           min_face_px=min_face_px, resolution=resolution, share_agreeing_suns=share_suns)
    try:
        with progress_bars(not json_out) as progress:
            summary = estimate_clip(clip, out, options, every=every, preview=preview, max_frames=max_frames,
                                    progress=progress)
    except VideoError as exc:
        fail(str(exc), code=1)
    if json_out:
        typer.echo(json.dumps({k: summary[k] for k in ("clip", "fps", "frames", "segments", "timings", "preview", "probes")}))
        return
    t = summary["timings"]
    lit = len(summary["estimates"])
    typer.echo(f"{summary['frames']} frames at {summary['fps']:.3g} fps, {len(summary['segments'])} segment(s), "
               f"{lit} window estimates; {t['frames_per_s']:.1f} frames/s after a {t['startup_s']:.1f} s start-up")
    for seg in summary["segments"][1:]:
        typer.echo(f"  frame {seg['first_frame']}: {seg['why']}")
    typer.echo(f"wrote {out}/frames.parquet, {summary['probes']} probe(s), sun_track.png"
               + (", preview.mp4" if summary.get("preview") else ""))
    if not summary["estimates"]:
        fail("no usable face in the clip: no light estimated (see frames.parquet's status column)", code=1)


def eval_video_cmd(
    render_dirs: list[Path] = typer.Argument(..., help="`f2l eval render-faces --sequence` folders."),
    out: Path = typer.Option(..., "--out", help="Output folder: video.md, video.json, runs/<clip>/."),
    model: str = typer.Option("sunsky", "--model", "-m", help="Lighting model."),
    alone_every: int = typer.Option(4, "--alone-every", min=1, help="Estimate every Nth frame alone, as a photo, to compare."),
    metrics_every: int = typer.Option(8, "--metrics-every", min=1, help="The §5.1 metrics every Nth frame."),
    sample_every: int = typer.Option(8, "--sample-every", min=1, help="f2l video's --sample-every."),
    window_s: float = typer.Option(4.0, "--window-s", min=0.05, help="f2l video's --window-s."),
    resolution: int = typer.Option(VIDEO_RESOLUTION, "--resolution", min=32, max=256, help="f2l video's --resolution."),
    json_out: JsonOut = False,
) -> None:
    """Light from clips against the truth and against each frame alone: Sun-ang, jitter, settling, §5.1, frames/s."""
    from f2l.cli.progress import progress_bars
    from f2l.evaluation.video import eval_video
    from f2l.video.estimate import VideoOptions

    options = VideoOptions(model=model, sample_every=sample_every, window_s=window_s, resolution=resolution)
    with progress_bars(not json_out) as progress:
        rows = eval_video(render_dirs, out, options, alone_every=alone_every, metrics_every=metrics_every,
                          progress=progress)
    if json_out:
        typer.echo(json.dumps(rows))
        return
    typer.echo((out / "video.md").read_text())


def bench_video_cmd(
    clips: list[Path] = typer.Argument(..., help="Video files, or folders of them (a render-faces --sequence folder: its clips/, with the truth's Sun-ang)."),
    model: str = typer.Option("sunsky", "--model", "-m", help="Lighting model."),
    cold_cache: bool = typer.Option(False, "--cold-cache", help="Build the head's transport table first (what a machine's first clip pays once)."),
    repeat: int = typer.Option(1, "--repeat", min=1, help="Play each clip back and forth N times (a long clip from a short render)."),
    resolution: int = typer.Option(VIDEO_RESOLUTION, "--resolution", min=32, max=256, help="f2l video's --resolution."),
    json_out: JsonOut = False,
) -> None:
    """Frames per second of f2l video on 2 cores, the start-up, and the error beside them (each clip a fresh process)."""
    from f2l.dev.bench_video import bench_video, table

    rows = bench_video(clips, model, extra=["--resolution", str(resolution)], cold_cache=cold_cache, repeat=repeat)
    typer.echo(json.dumps(rows) if json_out else table(rows))
