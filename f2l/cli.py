"""The ``f2l`` command line (typer). Thin: parsing, progress and exit codes; no algorithms here."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional

import typer

from f2l import __version__
from f2l.cli_support import exit_for, fail as _fail, parse_grid as _grid  # shared with the stages' cli.py

app = typer.Typer(
    name="f2l",
    help="f2l — faces to light: HDR outdoor light probes from photographs of faces.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"f2l {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version_callback, is_eager=True, help="Show the version and exit."),
    debug_log: Optional[Path] = typer.Option(
        None, "--debug-log", envvar="F2L_DEBUG_LOG",
        help="Append debug messages (e.g. third-party libraries' own log lines) to this file."),
) -> None:
    """f2l — faces to light."""
    if debug_log is not None:
        import logging

        handler = logging.FileHandler(debug_log, encoding="utf-8")
        handler.setFormatter(logging.Formatter("%(asctime)s %(process)d %(name)s %(levelname)s %(message)s"))
        root = logging.getLogger("f2l")
        root.addHandler(handler)
        root.setLevel(logging.DEBUG)


@app.command()
def models(json_out: bool = typer.Option(False, "--json", help="Machine-readable output.")) -> None:
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


@app.command()
def synth(
    out: Path = typer.Option(..., "--out", help="Output shard directory."),
    n: int = typer.Option(12, "--n", help="Number of synthetic faces."),
    seed: int = typer.Option(0, help="Random seed (everything is deterministic from it)."),
    grid: str = typer.Option("64x128", help="Lighting grid HxW."),
    image_size: int = typer.Option(128, help="Photo size in pixels (square)."),
    overcast_fraction: float = typer.Option(0.25, help="Fraction of overcast skies."),
    sun_elevation_deg: str = typer.Option(
        "5:80", "--sun-elevation-deg", metavar="MIN:MAX",
        help="Range of clear-sky sun elevations in degrees (uniform; azimuths cover the full circle). "
             "Only the elevation draw is rescaled: pose, albedo and noise of a seed stay the same.",
    ),
    noise: float = typer.Option(
        0.002, help="Sensor noise sigma (linear units), added before the photo is quantised to 8 bits; "
                    "observed pixels are the decoded 8-bit codes.",
    ),
    specular: float = typer.Option(0.0, help="Strength of an optional specular highlight."),
    visibility: str = typer.Option("adaptive", help="Visibility method: adaptive or exact."),
    capture: bool = typer.Option(
        False, "--capture/--no-capture",
        help="Give clear-sky records a capture time and place at which the real sun had the synthetic "
             "sun's elevation (meta 'capture'), as a photo's EXIF would; `f2l estimate` uses it as a sun prior."),
    features: bool = typer.Option(
        False, "--features/--no-features",
        help="Paint eyes, brows, lips and nostrils so a face detector finds the photos (for `f2l fit-faces` "
             "checks); the records' masks then keep skin only."),
    json_out: bool = typer.Option(False, "--json", help="Print a JSON summary only."),
) -> None:
    """Render synthetic faces under known probes into shards (ground truth included)."""
    from f2l.synth.dataset import write_synthetic_shards
    from f2l.synth.skies import parse_elevation_range

    try:
        elevation_range = parse_elevation_range(sun_elevation_deg)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--sun-elevation-deg") from exc
    summary = write_synthetic_shards(
        out, n=n, seed=seed, grid=_grid(grid), image_size=image_size, overcast_fraction=overcast_fraction,
        noise_sigma=noise, specular=specular, visibility_method=visibility, progress=not json_out,
        sun_elevation_range_deg=elevation_range, capture_meta=capture, features=features,
    )
    typer.echo(json.dumps(summary, indent=None if json_out else 2))


@app.command()
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
    max_iter: int = typer.Option(18, help="L-BFGS iterations of non-linear models (sunsky: all phases together)."),
    sun_prior: bool = typer.Option(
        True, "--sun-prior/--no-sun-prior",
        help="Constrain the sun's elevation from the photo's capture time and GPS position (EXIF or "
             "the record's meta 'capture'); sun models only. The heading is unknown: azimuth stays free."),
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
    json_out: bool = typer.Option(False, "--json", help="Print a JSON summary only."),
) -> None:
    """Estimate an HDR probe for every face record with the given lighting model(s); reruns skip
    faces already estimated with the same model, version and settings.

    A record that cannot be read or estimated is a row with its status and reason; the others are
    written. Exit code 4 when some failed, 1 when none succeeded."""
    from f2l.pipeline.photos import fit_photos, is_photo_input

    missing = [str(s) for s in shards if not Path(s).exists()]
    if missing:
        _fail(f"no such photo or shard path: {', '.join(missing)}")
    if executor not in ("local", "ray"):
        raise typer.BadParameter("must be local or ray", param_hint="--executor")
    photos = [s for s in shards if is_photo_input(s)]
    fitted = None
    if photos:
        from f2l.face.landmarker import LandmarkerError
        from f2l.synth.facemesh import FaceMeshError

        try:
            fitted = fit_photos(photos, out, min_face_px=min_face_px, progress=not json_out)
        except (LandmarkerError, FaceMeshError) as exc:
            _fail(str(exc))
        shards = [s for s in shards if not is_photo_input(s)] + fitted["shards"]
        if not shards:
            reasons = "; ".join(r["message"] for r in fitted["photos"][:5])
            _fail(f"no usable face in {len(fitted['photos'])} photo(s): {reasons}")
    from f2l.estimate.ray_executor import ExecutorUnavailable
    from f2l.estimate.runner import run_estimates
    from f2l.models.registry import ModelNotFoundError

    try:
        summary = run_estimates(
            shards, models=model, out_dir=out, workers=workers, threads=threads, max_pixels=max_pixels,
            max_iter=max_iter, progress=not json_out, sun_prior=sun_prior, executor=executor,
            ray_address=address, skin_gloss=skin_gloss, skin_reflection=skin_reflection,
        )
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


@app.command()
def evaluate(
    estimates_dir: Path = typer.Argument(..., help="Directory written by `f2l estimate`."),
    shards: Optional[list[Path]] = typer.Option(None, "--shards", help="Shards with ground truth (default: recorded)."),
    json_out: bool = typer.Option(False, "--json", help="Print JSON instead of a table."),
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


@app.command()
def bench(
    faces: int = typer.Option(1, help="Number of synthetic faces."),
    model: Optional[list[str]] = typer.Option(None, "--model", "-m", help="Models (default: all installed)."),
    out: Path = typer.Option(Path("bench_out"), "--out", help="Output directory (table, plot)."),
    image_size: int = typer.Option(128, help="Synthetic photo size (128 gives ~10k face pixels)."),
    grid: str = typer.Option("64x128", help="Lighting grid HxW."),
    threads: int = typer.Option(2, help="Threads."),
    seed: int = typer.Option(1, help="Seed of the synthetic set."),
    sun_skip_faces: int = typer.Option(2, help="Overcast faces on which each compact-sun model (sunsky, plugins) runs with and without its exact sun core (0: none)."),
) -> None:
    """Error versus run time of the installed models on synthetic faces (table + PNG plot)."""
    from f2l.bench import run_bench

    result = run_bench(faces=faces, models=model, out_dir=out, image_size=image_size, grid=_grid(grid), threads=threads,
                       seed=seed, sun_skip_faces=sun_skip_faces)
    typer.echo(result["markdown"])
    typer.echo(f"\nwrote {result['table_md']}, {result['plot_png']}")


@app.command()
def demo(
    out: Path = typer.Option(Path("demo_out"), "--out", help="Output directory."),
    n: int = typer.Option(12, "--n", help="Number of synthetic faces."),
    seed: int = typer.Option(0, help="Seed."),
    model: Optional[list[str]] = typer.Option(None, "--model", "-m", help="Models (default: all built-in)."),
) -> None:
    """Synthesise faces, estimate with every built-in model, evaluate, and write pictures."""
    from f2l.demo import run_demo

    run_demo(out, n=n, seed=seed, models=model)


@app.command()
def report(
    folder: Path = typer.Argument(..., help="An evaluation folder (shards/ + estimates/, e.g. demo_out) or a build-dataset output folder."),
    out: Optional[Path] = typer.Option(None, "--out", help="The HTML file (default FOLDER/report.html); thumbnails go to report_files/ beside it."),
    work: Optional[Path] = typer.Option(None, "--work", help="build-dataset's work folder: brackets, statuses and coverage per session."),
    estimates: Optional[Path] = typer.Option(None, "--estimates", help="f2l estimate's output, evaluated (f2l evaluate) against FOLDER's shards (default FOLDER/estimates)."),
    page_size: int = typer.Option(200, "--page-size", min=1, help="Faces per page."),
    json_out: bool = typer.Option(False, "--json", help="Print a JSON summary only."),
) -> None:
    """One self-contained HTML report per build or evaluation folder (no server, nothing remote)."""
    from f2l.report.build import write_report

    if not folder.is_dir():
        _fail(f"{folder}: not a folder")
    summary = write_report(folder, out, work=work, estimates=estimates, page_size=page_size)
    typer.echo(json.dumps(summary.to_json()) if json_out else
               f"wrote {summary.pages[0]} ({len(summary.pages)} pages, {summary.faces} faces; thumbnails "
               f"{summary.thumbnails_written} written, {summary.thumbnails_reused} reused)")


def _progress(total: int, desc: str, enabled: bool):
    """(callback(n), close()) over a tqdm bar on stderr, or no-ops when disabled."""
    if not enabled:
        return (lambda n=1: None), (lambda: None)
    from tqdm import tqdm

    bar = tqdm(total=total, desc=desc, unit="probe", file=sys.stderr)
    return bar.update, bar.close


def _load_model_or_fail(name: str, grid):
    from f2l.models.registry import ModelNotFoundError, load_model

    try:
        return load_model(name, grid)
    except ModelNotFoundError as exc:
        _fail(str(exc.args[0]))


def _fit_probe_inputs(probes: list[Path], model: str, grid: str, json_out: bool, what: str,
                      out_dir: Optional[Path] = None):
    """(model, fit records, skipped) for the HDR probes found in ``probes``
    (:func:`f2l.estimate.probe_fit.list_probe_files`; the other files of its folders are named
    as skipped on stderr), with a progress bar. Each probe is fitted by
    :func:`f2l.estimate.probe_fit.fit_probe_files`: a bad one is a record with status "error"."""
    from f2l.estimate.probe_fit import fit_probe_files, list_probe_files

    paths, skipped = list_probe_files(probes)
    for message in skipped:
        typer.echo(f"f2l: {message}", err=True)
    if not paths:
        _fail("no .exr probes found (nor .hdr, .rgbe, .tif, .tiff, .pfm) in " + ", ".join(map(str, probes)))
    m = _load_model_or_fail(model, _grid(grid))
    step, close = _progress(len(paths), f"{what} {model}", not json_out)
    records = fit_probe_files(paths, m, progress=step, out_dir=out_dir)
    close()
    return m, records, skipped


@app.command("fit-probe")
def fit_probe_cmd(
    probes: list[Path] = typer.Argument(..., help="Lat-long HDR probes (.exr, .hdr, .pfm, float .tif) or folders of them."),
    model: str = typer.Option(..., "--model", "-m", help="Lighting model name."),
    out: Optional[Path] = typer.Option(None, "--out", help="Write fit_probe.csv and fitted probes here."),
    grid: str = typer.Option("64x128", help="Model grid HxW (probes are resampled to it)."),
    json_out: bool = typer.Option(False, "--json", help="Print a JSON summary only."),
) -> None:
    """Fit a lighting model directly to HDR probes (paper Table 1); report the sun angle where known.

    A probe that cannot be fitted (unreadable, malformed side file, black, implausible) is a row
    with status "error" and its reason; the others are fitted and the table is written. Exit code
    4 when some probes failed, 1 when every probe failed."""
    from f2l.estimate.prior_build import write_fit_report

    m, records, skipped = _fit_probe_inputs(probes, model, grid, json_out, "fit-probe", out)
    summary = write_fit_report(records, m, out)
    summary["skipped"] = skipped
    if json_out:
        typer.echo(json.dumps(summary))
    else:
        typer.echo(summary["markdown"])
    exit_for(summary["errors"], len(records) - summary["errors"])


@app.command("sky-corpus")
def sky_corpus(
    out: Path = typer.Option(..., "--out", help="Output folder for the sky EXRs (+ JSON side files)."),
    n: int = typer.Option(400, "--n", help="Number of skies."),
    seed: int = typer.Option(0, help="Seed."),
    grid: str = typer.Option("64x128", help="Probe grid HxW."),
    overcast_fraction: float = typer.Option(0.25, help="Fraction of overcast skies."),
    json_out: bool = typer.Option(False, "--json", help="Print a JSON summary only."),
) -> None:
    """Write the project's default sky corpus (CIE clear + overcast skies) for `f2l build-prior`."""
    from f2l.estimate.prior_build import write_sky_corpus

    step, close = _progress(n, "sky-corpus", not json_out)
    paths = write_sky_corpus(out, n, seed=seed, grid=_grid(grid), overcast_fraction=overcast_fraction, progress=step)
    close()
    typer.echo(json.dumps({"written": len(paths), "out": str(out)}))


@app.command("build-prior")
def build_prior_cmd(
    probes: list[Path] = typer.Argument(..., help="Folders of lat-long sky probes (.exr, .hdr, .pfm, float .tif), or files."),
    model: str = typer.Option(..., "--model", "-m", help="Lighting model name."),
    out: Path = typer.Option(..., "--out", help="Prior JSON to write."),
    components: int = typer.Option(6, help="GMM components."),
    seed: int = typer.Option(0, help="Seed of the GMM fit."),
    grid: str = typer.Option("64x128", help="Model grid HxW."),
    json_out: bool = typer.Option(False, "--json", help="Print a JSON summary only."),
) -> None:
    """Fit the model to every probe, then a GMM over its prior features: the model's prior.

    A probe that cannot be fitted (unreadable, malformed side file, black, implausible, a fit that
    overflows) is skipped with its reason on stderr and the prior is built from the others. Exit
    code 4 when some probes were skipped (the prior is written), 1 when none could be fitted."""
    from f2l.cli_support import EXIT_NOTHING_DONE
    from f2l.estimate.model_prior import save_prior
    from f2l.estimate.prior_build import build_prior

    m, records, _ = _fit_probe_inputs(probes, model, grid, json_out, "build-prior")
    bad = [r for r in records if r.status != "ok"]
    for r in bad[:10]:
        typer.echo(f"f2l: skipped {r.message}", err=True)
    if len(bad) > 10:
        typer.echo(f"f2l: ... and {len(bad) - 10} more probes skipped", err=True)
    try:
        prior = build_prior(m, records, n_components=components, seed=seed,
                            corpus={"sources": [str(p) for p in probes]})
    except ValueError as exc:
        nothing_fitted = records and len(bad) == len(records) and m.prior_feature_names is not None
        _fail(str(exc), EXIT_NOTHING_DONE if nothing_fitted else 2)
    save_prior(prior, out)
    typer.echo(json.dumps({"out": str(out), "fitted": len(records) - len(bad), "skipped": len(bad),
                           "components": prior.num_components, "features": prior.features}))
    exit_for(len(bad), len(records) - len(bad))


# stages with a CLI module of their own (f2l/<stage>/cli.py)
from f2l.capture.cli import bench_capture_cmd, ingest_cmd, make_probes_cmd  # noqa: E402
from f2l.colour.cli import calibrate_cmd  # noqa: E402
from f2l.pipeline.cli import build_dataset_cmd  # noqa: E402
from f2l.face.cli import bench_detect_cmd, bench_faces_cmd, compare_geometry_cmd, fit_faces_cmd  # noqa: E402
from f2l.render.cli import (eval_framings_cmd, eval_real_ablations_cmd, eval_real_cmd,  # noqa: E402
                            eval_real_geometry_cmd, eval_real_search_cmd, render_faces_cmd, render_skies_cmd,
                            twin_geometry_cmd)

STAGE_COMMANDS = {
    "ingest": ingest_cmd, "make-probes": make_probes_cmd, "bench-capture": bench_capture_cmd,
    "calibrate": calibrate_cmd, "build-dataset": build_dataset_cmd,
    "fit-faces": fit_faces_cmd, "compare-geometry": compare_geometry_cmd, "bench-faces": bench_faces_cmd,
    "bench-detect": bench_detect_cmd,
    "render-faces": render_faces_cmd, "render-skies": render_skies_cmd, "twin-geometry": twin_geometry_cmd, "eval-real": eval_real_cmd,
    "eval-real-geometry": eval_real_geometry_cmd, "eval-real-search": eval_real_search_cmd,
    "eval-real-ablations": eval_real_ablations_cmd, "eval-framings": eval_framings_cmd,
}
for _name, _command in STAGE_COMMANDS.items():
    app.command(_name)(_command)


def _add_plugin_commands() -> None:
    """Commands plugins add through the entry-point group ``f2l.commands`` (entry-point name = the
    command, value = a typer command function), e.g. the built-in autoencoder's ``ae-corpus`` and
    ``train-ae``. A command that fails to load still exists and says why when run."""
    from importlib.metadata import entry_points

    taken = {c.name for c in app.registered_commands}
    for ep in entry_points(group="f2l.commands"):
        if ep.name in taken:
            continue
        taken.add(ep.name)
        try:
            fn = ep.load()
        except Exception as exc:  # noqa: BLE001 - a broken plugin must not break the CLI
            fn = _broken_command(ep.name, ep.value, exc)
        app.command(ep.name)(fn)


def _broken_command(name: str, target: str, exc: Exception):
    def broken() -> None:
        _fail(f"command {name!r} ({target}) failed to load: {type(exc).__name__}: {exc}")

    broken.__doc__ = f"(failed to load: {target})"
    return broken


_add_plugin_commands()


@app.command("scale-report")
def scale_report_cmd(
    faces: list[int] = typer.Option([10, 200], "--faces", help="Dataset sizes (repeatable)."),
    model: str = typer.Option("sh9", "--model", "-m", help="Lighting model to estimate with."),
    image_size: int = typer.Option(96, help="Synthetic photo size in pixels."),
    grid: str = typer.Option("32x64", help="Lighting grid HxW."),
    build: bool = typer.Option(False, "--build", help="Instead: build-dataset on a tree of face photos, local against --executor ray (f2l.pipeline.scale)."),
    workers: int = typer.Option(2, "--workers", min=1, help="--build: CPUs of the local Ray."),
    json_out: bool = typer.Option(False, "--json", help="Print JSON only."),
) -> None:
    """Build and estimate synthetic datasets of several sizes: faces/minute, per-stage time, peak memory."""
    if build:
        from f2l.pipeline.scale import format_build_table, run_build_scale

        try:
            rows = run_build_scale(tuple(faces), workers=workers)
        except RuntimeError as exc:
            _fail(str(exc))
        typer.echo(json.dumps(rows) if json_out else format_build_table(rows))
        return
    from f2l.estimate.scale import format_table, run_scale_report

    g = _grid(grid)
    rows = run_scale_report(tuple(faces), model=model, image_size=image_size, grid=(g.height, g.width))
    typer.echo(json.dumps(rows) if json_out else format_table(rows))


def main() -> None:
    try:
        app()
    except KeyboardInterrupt:
        sys.exit(130)


if __name__ == "__main__":
    main()
