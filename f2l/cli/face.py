"""CLI layer of face fitting (registered by :mod:`f2l.cli.app`): ``fit-faces``,
``compare-geometry``, ``bench-faces``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from f2l.cli.common import Grid, JsonOut, exit_for, fail, parse_grid, require_render_dirs
from f2l.cli.progress import progress_bars


def fit_faces_cmd(
    photos: list[Path] = typer.Argument(..., help="Photos (JPEG/PNG/TIFF or camera RAW) or folders of them."),
    out: Path = typer.Option(..., "--out", help="Output shard directory."),
    resolution: int = typer.Option(104, help="Working face resolution: the square crop around a face is resampled to this many px."),
    grid: Grid = "64x128",
    depth: str = typer.Option("rigid", help="Face shape: rigid (MediaPipe's canonical face, posed by a perspective fit to the landmarks), canonical (landmark x, y with the posed canonical depth) or landmarks (landmark x, y, z: per person, noisier)."),
    overlays: bool = typer.Option(True, "--overlays/--no-overlays", help="Write a debug overlay PNG per face."),
    landmarker: Optional[Path] = typer.Option(None, help="face_landmarker.task to use (default: $F2L_FACE_LANDMARKER or the pinned copy)."),
    gt_probes: Optional[Path] = typer.Option(None, help="Folder of ground-truth probes <photo stem>.exr to attach to the records."),
    threads: int = typer.Option(2, help="Embree threads for the transport."),
    transport_pixels: str = typer.Option("mask", help="Pixels whose visibility is ray-traced: mask (the usable skin the estimator reads; the others keep their unshadowed front hemisphere) or all."),
    body_proxy: bool = typer.Option(False, "--body-proxy/--no-body-proxy", help="Add a neck-and-shoulders occluder (average adult dimensions, posed with the head) to the visibility (f2l.face.body)."),
    hairline: str = typer.Option("colour", help="The upper forehead's hairline band: colour (keep its pixels that have the skin's colour; f2l.face.hair), exclude (leave it out) or keep."),
    min_face_px: float = typer.Option(40.0, "--min-face-px", help="Smallest face to find and fit: its width in photo pixels (cheek to cheek along the eye line). Detection time grows as its inverse square; narrower faces found on the way are refused as too_small."),
    json_out: JsonOut = False,
) -> None:
    """Detect every face of each photo (any size from --min-face-px, anywhere, any number), fit a 3D face mesh, mask skin and compute transport into face-record shards.

    Every photo gets a status row (ok, rejected with each face's reason, no_face, error). Exit code 4 when some photos could not be read, 1 when none could."""
    from f2l.face.fit import FitOptions
    from f2l.face.landmarker import LandmarkerError
    from f2l.face.run import fit_faces
    from f2l.face.mesh import FaceMeshError

    from f2l.face.geometry import DEPTH_SOURCES

    if depth not in DEPTH_SOURCES:
        raise typer.BadParameter(f"must be one of {', '.join(DEPTH_SOURCES)}", param_hint="--depth")
    if resolution < 32:
        raise typer.BadParameter("must be at least 32", param_hint="--resolution")
    from f2l.face.fit import HAIRLINE_MODES, TRANSPORT_PIXELS

    if hairline not in HAIRLINE_MODES:
        raise typer.BadParameter(f"must be one of {', '.join(HAIRLINE_MODES)}", param_hint="--hairline")

    if transport_pixels not in TRANSPORT_PIXELS:
        raise typer.BadParameter(f"must be one of {', '.join(TRANSPORT_PIXELS)}",
                                 param_hint="--transport-pixels")
    if not 8.0 <= min_face_px <= 10_000.0:
        raise typer.BadParameter("must be between 8 and 10000", param_hint="--min-face-px")
    options = FitOptions(resolution=resolution, grid=parse_grid(grid), depth_source=depth, threads=threads,
                         transport_pixels=transport_pixels, body_proxy=body_proxy, hairline=hairline,
                         min_face_px=min_face_px)
    try:
        with progress_bars(not json_out) as progress:
            summary = fit_faces(photos, out, options, overlays=overlays, landmarker_path=landmarker,
                                gt_probes=gt_probes, progress=progress)
    except (LandmarkerError, FaceMeshError) as exc:
        fail(str(exc))
    typer.echo(json.dumps(summary, indent=None if json_out else 2))
    exit_for(summary["status"]["error"], summary["photos"] - summary["status"]["error"])


def compare_geometry_cmd(
    fitted: list[Path] = typer.Argument(..., help="Shards written by `f2l fit-faces` from synthetic photos."),
    truth: Path = typer.Option(..., "--truth", help="The `f2l eval synth` shards the photos came from."),
    twin_out: Optional[Path] = typer.Option(
        None, "--twin-out",
        help="Write the true-geometry twins here (the fitted pixels and observations with the true mesh's "
             "normals and visibility) to estimate side by side with the fitted records."),
    json_out: JsonOut = False,
) -> None:
    """Normal error (degrees) of fitted face geometry against the synthetic ground truth, on the mask."""
    import numpy as np

    from f2l.evaluation.compare_geometry import compare_geometry

    rows = compare_geometry(fitted, truth, twin_out=twin_out)
    if not rows:
        fail("no fitted record matched a ground-truth face (photo stem = ground-truth face id)")
    medians = [r["median_deg"] for r in rows]
    summary = {"faces": len(rows), "median_of_medians_deg": round(float(np.median(medians)), 2),
               "worst_median_deg": round(float(np.max(medians)), 2),
               "twin_out": None if twin_out is None else str(twin_out)}
    if json_out:
        typer.echo(json.dumps({"rows": rows, "summary": summary}))
        return
    typer.echo("| face | compared px | normal err median ° | p90 ° | yaw true / fit ° | pitch true / fit ° |")
    typer.echo("|---|---|---|---|---|---|")
    for r in rows:
        typer.echo(f"| {r['face_id']} | {r['compared_px']} | {r['median_deg']:.1f} | {r['p90_deg']:.1f} | "
                   f"{r['yaw_true']:+.1f} / {r['yaw_fit']:+.1f} | {r['pitch_true']:+.1f} / {r['pitch_fit']:+.1f} |")
    typer.echo(json.dumps(summary))


def bench_faces_cmd(
    faces: int = typer.Option(4, help="Synthetic photos to fit (after one warm-up photo)."),
    image_size: int = typer.Option(256, help="Synthetic photo size in pixels."),
    resolution: int = typer.Option(104, help="Working face resolution (as `f2l fit-faces --resolution`)."),
    grid: Grid = "64x128",
    photo: Optional[list[Path]] = typer.Option(None, "--photo", help="Also time these real photos (repeatable)."),
    threads: int = typer.Option(2, help="Embree threads."),
    json_out: JsonOut = False,
) -> None:
    """Face fitting run time per stage (decode, landmarks, geometry, transport) next to its normal error."""
    from f2l.dev.bench_faces import format_table, run_face_bench, to_json

    result = run_face_bench(faces=faces, image_size=image_size, resolution=resolution, grid=parse_grid(grid),
                            threads=threads, photos=photo)
    typer.echo(to_json(result) if json_out else format_table(result))


def bench_detect_cmd(
    photos: int = typer.Option(60, help="Composite photos (real faces on real backgrounds, 0.3-12 MP) for the recall table."),
    negatives: int = typer.Option(100, help="Face-free real photos for the false-detection count."),
    sizes_mp: str = typer.Option("1,4,12,24,50", "--sizes-mp", help="Photo sizes (megapixels, comma-separated) to time."),
    repeats: int = typer.Option(3, help="Timed runs per size (the median is reported)."),
    detector: str = typer.Option("full_range", help="full_range (shipped) or short_range (the landmark bundle's detector, tiled alike)."),
    min_face_px: float = typer.Option(40.0, "--min-face-px", help="Smallest face searched for (px)."),
    seed: int = typer.Option(0, help="Seed of the composites."),
    rendered: Optional[list[Path]] = typer.Option(None, "--rendered", help="Also the recall on `f2l eval render-faces --framing ...` folders (their meta holds every true face box); repeatable."),
    json_out: JsonOut = False,
) -> None:
    """Face detection on real photographs framed wide: recall by face width, false detections per 100 face-free photos, time by photo size."""
    from f2l.dev.bench_detect import format_rendered, format_table, rendered_recall, run_detect_bench

    try:
        sizes = tuple(float(v) for v in sizes_mp.split(",") if v.strip())
    except ValueError:
        raise typer.BadParameter("comma-separated numbers, e.g. 1,12,50", param_hint="--sizes-mp") from None
    try:
        result = run_detect_bench(photos=photos, negatives=negatives, sizes_mp=sizes, repeats=repeats, seed=seed,
                                  detector=detector, min_face_px=min_face_px)
    except (RuntimeError, ValueError) as exc:
        fail(str(exc))
    if rendered:
        require_render_dirs(rendered)
        result["rendered"] = rendered_recall(rendered, min_face_px=min_face_px, detector=detector)
    if json_out:
        typer.echo(json.dumps(result))
    else:
        typer.echo(format_table(result) + ("\n\n" + format_rendered(result["rendered"]) if rendered else ""))
