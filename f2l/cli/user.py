"""The user's commands (the top of ``f2l --help``): models, estimate, evaluate, report, demo.
Registered by :mod:`f2l.cli.app`; thin: parsing, progress and exit codes, no algorithms."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from f2l.cli.common import JsonOut, Seed, estimate_settings, exit_for, fail as _fail, print_settings
from f2l.cli.progress import progress_bars

VIDEO_EXTENSIONS = frozenset({".mp4", ".mov", ".m4v", ".mkv", ".avi", ".webm", ".mts", ".m2ts", ".3gp", ".mpg", ".mpeg"})


def models(json_out: JsonOut = False) -> None:
    """List the installed lighting models (entry-point group f2l.lighting_models)."""
    from f2l.lighting.grid import LatLongGrid
    from f2l.models.registry import ModelNotFoundError, discover, load_model

    rows = []
    grid = LatLongGrid(16, 32)
    for name, info in discover().items():
        row = {"name": name, "package": info.package, "target": info.target, "ok": info.ok,
               "capabilities": list(info.capabilities)}
        if info.ok:
            try:
                inst = load_model(name, grid)  # checks the declared capabilities on a small grid
                row.update(params=inst.num_params, domain=inst.domain, version=inst.version,
                           description=inst.description)
            except ModelNotFoundError as exc:
                row.update(ok=False, error=str(exc))
        else:
            row.update(error=info.error)
        rows.append(row)
    if json_out:
        typer.echo(json.dumps(rows, indent=2))
        return
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    table = Table(title="f2l lighting models")
    for col in ("name", "params", "domain", "capabilities", "package", "description"):
        table.add_column(col)
    for r in rows:
        caps = ", ".join(r["capabilities"]) or "-"
        if r["ok"]:
            table.add_row(r["name"], str(r["params"]), r["domain"], caps, r["package"], r["description"])
        else:
            table.add_row(r["name"], "-", "-", caps, r["package"], f"[red]failed to load: {escape(r['error'])}[/red]")
    Console().print(table)


def estimate(
    shards: list[Path] = typer.Argument(..., help="Photos (JPEG/PNG/TIFF or camera RAW), folders of photos, shard directories or .parquet files. Every face of a photo is fitted on the way and cached by content under OUT/faces."),
    model: list[str] = typer.Option(..., "--model", "-m", help="Lighting model name (repeatable)."),
    out: Path = typer.Option(..., "--out", help="Output directory (estimates.parquet, probes/, previews/; faces/ for photos)."),
    min_face_px: Optional[float] = typer.Option(None, "--min-face-px", min=8.0, help="Photos: the smallest face to find and fit, in px (default: the pipeline's, 40)."),
    workers: Optional[int] = typer.Option(None, help="Parallel workers (default: cores // threads)."),
    threads: int = typer.Option(2, help="Torch/Embree threads per worker."),
    executor: str = typer.Option("local", help="local (a process pool on this machine) or ray (Ray Data; needs the 'ray' extra)."),
    address: Optional[str] = typer.Option(None, help="Ray cluster address for --executor ray (default: start a local Ray with --workers CPUs)."),
    max_pixels: Optional[int] = typer.Option(None, help="Use at most this many face pixels per face."),
    max_iter: Optional[int] = typer.Option(None, help="L-BFGS iterations of non-linear models (sunsky: all phases together; default 18)."),
    sun_prior: Optional[bool] = typer.Option(
        None, "--sun-prior/--no-sun-prior",
        help="Constrain the sun's elevation from the photo's capture time and GPS position (EXIF or "
             "the record's meta 'capture'); sun models only (default on). The heading is unknown: azimuth stays free."),
    skin_gloss: Optional[float] = typer.Option(
        None, "--skin-gloss", min=0.0, max=1.0,
        help="The skin's gloss, an achromatic albedo added to the diffuse one (sun models; default "
             "0.05, for real skin). 0 reads the skin as Lambertian, as f2l's own synthetic faces are."),
    skin_reflection: Optional[float] = typer.Option(
        None, "--skin-reflection", min=0.0, max=1.0,
        help="The skin's reflection of the sky, sun and ground about the mirror direction (sun models; "
             "needs the records' 3-D points; default 0 = off). 0.01 is the value measured on make eval-real "
             "(docs/experiments/accuracy_issue16.md); it costs about 15% more time a face, and on Lambertian faces (f2l's own renders) "
             "it is a bias."),
    joint: str = typer.Option(
        "photo", "--joint",
        help="photo: the faces of one photo share one light (one probe per photo, a row per face saying how well "
             "it agrees; a face that disagrees, e.g. in another's shadow, is left out and gets its own); "
             "session: the faces of one session (records' meta 'session', e.g. from build-dataset) share one light, "
             "each photo turned by its camera's heading (session.toml [[shots]] yaw_deg; where one is unknown, f2l "
             "says so and groups by photo); none: every face alone."),
    also_single: bool = typer.Option(
        False, "--also-single", help="With --joint photo or session, also estimate every face alone into OUT/single (for comparison)."),
    set_: Optional[list[str]] = typer.Option(
        None, "--set", metavar="NAME=VALUE",
        help="An estimator setting (repeatable), e.g. --set sun_starts=5 --set fixed_albedo=0.5,0.4,0.3 "
             "(None for none; tuples comma-separated). --settings lists them."),
    settings_flag: bool = typer.Option(
        False, "--settings", is_eager=True, expose_value=False, callback=print_settings,
        help="List the estimator's settings (for --set) by group, with defaults and help, and exit."),
    json_out: JsonOut = False,
) -> None:
    """Estimate an HDR probe for every face record with the given lighting model(s); reruns skip
    faces already estimated with the same model, version and settings.

    A record that cannot be read or estimated is a row with its status and reason; the others are
    written. Exit code 4 when some failed, 1 when none succeeded."""
    from f2l.pipeline.photos import is_photo_input

    def read_settings() -> dict:
        return estimate_settings(set_, max_iter=max_iter, max_pixels=max_pixels, sun_prior_from_capture=sun_prior,
                                 skin_gloss=skin_gloss, skin_reflection=skin_reflection)

    # only a --set can be refused: then it is checked before any photo is fitted (importing torch, so the fit
    # runs here, not forked); without one, the settings are read while the photos are fitted
    config_settings = read_settings() if set_ else None
    missing = [str(s) for s in shards if not Path(s).exists()]
    if missing:
        _fail(f"no such photo or shard path: {', '.join(missing)}")
    clips = [str(s) for s in shards if Path(s).suffix.lower() in VIDEO_EXTENSIONS]
    if clips:
        _fail(f"{', '.join(clips)}: a video; its light per frame comes from `f2l video CLIP -m {model[0]} --out DIR`")
    if executor not in ("local", "ray"):
        raise typer.BadParameter("must be local or ray", param_hint="--executor")
    if joint not in ("photo", "session", "none"):
        raise typer.BadParameter("must be photo, session or none", param_hint="--joint")
    photos = [s for s in shards if is_photo_input(s)]
    fitting = _start_fit(photos, out, min_face_px, not json_out) if photos else None
    try:  # while the photos' faces are fitted (a forked child), torch and the estimator load here
        if config_settings is None:
            config_settings = read_settings()
        fitted = None
        if fitting is not None:
            from f2l.face.landmarker import LandmarkerError
            from f2l.face.mesh import FaceMeshError

            if fitting.forked:
                _preload_estimate(model)
            try:
                fitted = fitting.result()
            except (LandmarkerError, FaceMeshError) as exc:
                _fail(str(exc))
    finally:
        if fitting is not None:
            fitting.cancel()  # a child still running (Ctrl-C, an error here) is stopped
    if fitted is not None:
        shards = [s for s in shards if not is_photo_input(s)] + fitted["shards"]
        if not shards:
            reasons = "; ".join(r["message"] for r in fitted["photos"][:5])
            _fail(f"no usable face in {len(fitted['photos'])} photo(s): {reasons}")
    from f2l.io.executor import ExecutorUnavailable
    from f2l.estimate.runner import run_estimates
    from f2l.models.registry import ModelNotFoundError

    try:
        with progress_bars(not json_out) as progress:
            settings = dict(models=model, workers=workers, threads=threads, progress=progress, executor=executor,
                            ray_address=address, settings=config_settings)
            summary = run_estimates(shards, out_dir=out, joint=joint, **settings)
            if also_single and summary["joint"] != "none":
                single = run_estimates(shards, out_dir=Path(out) / "single", joint="none", **settings)
                summary["single"] = {k: single[k] for k in ("out", "total", "ok", "failed", "elapsed_s")}
    except ModelNotFoundError as exc:
        _fail(str(exc.args[0]))
    except ExecutorUnavailable as exc:
        _fail(str(exc))
    if fitted is not None:
        summary["photos"] = {"counts": fitted["counts"],
                             "not_ok": [{k: r[k] for k in ("source_path", "status", "message")}
                                        for r in fitted["photos"] if r["status"] != "ok"]}
    typer.echo(json.dumps(summary, indent=None if json_out else 2))
    photo_errors = 0 if fitted is None else sum(r["status"] == "error" for r in fitted["photos"])
    exit_for(summary["failed"] + photo_errors, summary["ok"] + summary["skipped_done"])


def _start_fit(photos: list[Path], out: Path, min_face_px: float | None, bars: bool):
    """Fit the photos' faces (:func:`f2l.pipeline.photos.fit_photos`) in a forked child where
    :mod:`f2l.io.forked` can, else here; returns its :class:`~f2l.io.forked.Forked`. The child
    hides pandas and networkx, which pyarrow and trimesh would import for nothing
    (:mod:`f2l.io.hidden_modules`)."""
    from f2l.io import forked, hidden_modules
    from f2l.pipeline.photos import fit_photos

    def fit() -> dict:
        with progress_bars(bars) as progress:
            return fit_photos(photos, out, min_face_px=min_face_px, progress=progress)

    return forked.start(fit, child_setup=hidden_modules.hide)


ESTIMATE_MODULES = ("pandas", "pyarrow.parquet", "f2l.estimate.runner", "f2l.estimate.record",
                    "f2l.estimate.group_record", "f2l.estimate.resume", "f2l.estimate.model_prior",
                    "f2l.io.shards", "f2l.io.tables", "f2l.io.exr", "f2l.io.capture", "f2l.io.preview")
"""What ``f2l estimate`` imports to estimate, loaded while a forked child fits the photos."""


def _preload_estimate(models: list[str]) -> None:
    """Import what the estimate needs (:data:`ESTIMATE_MODULES`, the models' classes) ahead of it:
    the same modules it would import, only earlier. A model that fails to load is reported by
    the estimate itself."""
    import importlib

    from f2l.models.registry import ModelNotFoundError, model_class

    for name in ESTIMATE_MODULES:
        importlib.import_module(name)
    for name in models:
        try:
            model_class(name)
        except ModelNotFoundError:
            pass


def evaluate(
    estimates_dir: Path = typer.Argument(..., help="Directory written by `f2l estimate`."),
    shards: Optional[list[Path]] = typer.Option(None, "--shards", help="Shards with ground truth (default: recorded)."),
    json_out: JsonOut = False,
) -> None:
    """The seven §5.1 metrics and sun energy shares per face (CSV); mean ± std, medians and the
    overcast sun-share excess per model (Markdown + CSV)."""
    from f2l.metrics.evaluate import evaluate_estimates

    result = evaluate_estimates(estimates_dir, shards)
    if json_out:
        typer.echo(json.dumps(result["summary_rows"], indent=2))
    else:
        typer.echo(result["markdown"])
        typer.echo(f"\nwrote {result['per_face_csv']}, {result['summary_csv']}, {result['summary_md']}")


def demo(
    out: Path = typer.Option(Path("demo_out"), "--out", help="Output directory."),
    n: int = typer.Option(12, "--n", help="Number of synthetic faces."),
    seed: Seed = 0,
    model: Optional[list[str]] = typer.Option(None, "--model", "-m", help="Models (default: all built-in)."),
) -> None:
    """Synthesise faces, estimate with every built-in model, evaluate, and write pictures."""
    from f2l.demo import run_demo

    run_demo(out, n=n, seed=seed, models=model)


def report(
    folder: Path = typer.Argument(..., help="An evaluation folder (shards/ + estimates/, e.g. demo_out) or a build-dataset output folder."),
    out: Optional[Path] = typer.Option(None, "--out", help="The HTML file (default FOLDER/report.html); thumbnails go to report_files/ beside it."),
    work: Optional[Path] = typer.Option(None, "--work", help="build-dataset's work folder: brackets, statuses and coverage per session."),
    estimates: Optional[Path] = typer.Option(None, "--estimates", help="f2l estimate's output, evaluated (f2l evaluate) against FOLDER's shards (default FOLDER/estimates)."),
    page_size: int = typer.Option(200, "--page-size", min=1, help="Faces per page."),
    json_out: JsonOut = False,
) -> None:
    """One self-contained HTML report per build or evaluation folder (no server, nothing remote)."""
    from f2l.report.build import write_report

    if not folder.is_dir():
        _fail(f"{folder}: not a folder")
    summary = write_report(folder, out, work=work, estimates=estimates, page_size=page_size)
    typer.echo(json.dumps(summary.to_json()) if json_out else
               f"wrote {summary.pages[0]} ({len(summary.pages)} pages, {summary.faces} faces; thumbnails "
               f"{summary.thumbnails_written} written, {summary.thumbnails_reused} reused)")
