"""Research and developer commands without a stage module of their own: ``f2l eval synth``,
``f2l eval fit-probe``, ``f2l prior sky-corpus|build``, ``f2l dev bench|scale-report``.
Registered by :mod:`f2l.cli.app`."""

from __future__ import annotations

import json
from contextlib import contextmanager
from pathlib import Path
from typing import Optional

import typer

from f2l.cli.common import Grid, JsonOut, OvercastFraction, Seed, exit_for, fail as _fail, parse_grid as _grid
from f2l.cli.progress import progress_bars
from f2l.io.progress import Progress


def synth(
    out: Path = typer.Option(..., "--out", help="Output shard directory."),
    n: int = typer.Option(12, "--n", help="Number of synthetic faces."),
    seed: Seed = 0,
    grid: Grid = "64x128",
    image_size: int = typer.Option(128, help="Photo size in pixels (square)."),
    overcast_fraction: OvercastFraction = 0.25,
    sun_elevation_deg: str = typer.Option(
        "5:80", "--sun-elevation-deg", metavar="MIN:MAX",
        help="Range of clear-sky sun elevations in degrees (uniform; azimuths cover the full circle). "
             "Only the elevation draw is rescaled: pose, albedo and noise of a seed stay the same.",
    ),
    noise: float = typer.Option(
        0.002, help="Sensor noise sigma (linear units), added before the photo is quantised to 8 bits; "
                    "observed pixels are the decoded 8-bit codes.",
    ),
    lambertian: bool = typer.Option(
        False, "--lambertian",
        help="Lambertian skin (the estimator's own forward model, for regression checks). Default: glossy skin, "
             "the GGX highlight of the whole probe with roughness 0.3-0.7 and F0 0.028-0.048 drawn per face "
             "(meta 'gloss'); sky, pose, albedo and noise of a seed are the same either way."),
    specular: float = typer.Option(0.0, help="Strength of an extra Blinn-Phong highlight of the sun alone "
                                             "(0 = none), on top of the gloss."),
    visibility: str = typer.Option("adaptive", help="Visibility method: adaptive or exact."),
    capture: bool = typer.Option(
        False, "--capture/--no-capture",
        help="Give clear-sky records a capture time and place at which the real sun had the synthetic "
             "sun's elevation (meta 'capture'), as a photo's EXIF would; `f2l estimate` uses it as a sun prior."),
    features: bool = typer.Option(
        False, "--features/--no-features",
        help="Paint eyes, brows, lips and nostrils so a face detector finds the photos (for `f2l fit-faces` "
             "checks); the records' masks then keep skin only."),
    json_out: JsonOut = False,
) -> None:
    """Render synthetic faces under known probes into shards (ground truth included); glossy skin
    unless --lambertian."""
    from f2l.synth.dataset import write_synthetic_shards
    from f2l.synth.skies import parse_elevation_range

    try:
        elevation_range = parse_elevation_range(sun_elevation_deg)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--sun-elevation-deg") from exc
    with progress_bars(not json_out) as progress:
        summary = write_synthetic_shards(
            out, n=n, seed=seed, grid=_grid(grid), image_size=image_size, overcast_fraction=overcast_fraction,
            noise_sigma=noise, specular=specular, visibility_method=visibility, progress=progress,
            sun_elevation_range_deg=elevation_range, capture_meta=capture, features=features, gloss=not lambertian,
        )
    typer.echo(json.dumps(summary, indent=None if json_out else 2))


def bench(
    faces: int = typer.Option(1, help="Number of synthetic faces."),
    model: Optional[list[str]] = typer.Option(None, "--model", "-m", help="Models (default: all installed)."),
    out: Path = typer.Option(Path("bench_out"), "--out", help="Output directory (table, plot)."),
    image_size: int = typer.Option(128, help="Synthetic photo size (128 gives ~10k face pixels)."),
    grid: Grid = "64x128",
    threads: int = typer.Option(2, help="Threads."),
    seed: Seed = 1,
    sun_skip_faces: int = typer.Option(2, help="Overcast faces on which each compact-sun model (sunsky, plugins) runs with and without its exact sun core (0: none)."),
) -> None:
    """Error versus run time of the installed models on synthetic faces (table + PNG plot)."""
    from f2l.dev.bench import run_bench

    result = run_bench(faces=faces, models=model, out_dir=out, image_size=image_size, grid=_grid(grid), threads=threads,
                       seed=seed, sun_skip_faces=sun_skip_faces)
    typer.echo(result["markdown"])
    typer.echo(f"\nwrote {result['table_md']}, {result['plot_png']}")


@contextmanager
def _counted(total: int, stage: str, enabled: bool):
    """A ``step(n)`` callback (n more probes done) drawn as the CLI's bar, or None when not ``enabled``."""
    with progress_bars(enabled) as bars:
        yield None if bars is None else Progress(bars, stage, "probe", total).advance


def _load_model_or_fail(name: str, grid):
    from f2l.models.registry import ModelNotFoundError, load_model

    try:
        return load_model(name, grid)
    except ModelNotFoundError as exc:
        _fail(str(exc.args[0]))


def _fit_probe_inputs(probes: list[Path], model: str, grid: str, json_out: bool, what: str,
                      out_dir: Optional[Path] = None):
    """(model, fit records, skipped) for the HDR probes found in ``probes``
    (:func:`f2l.prior.probe_fit.list_probe_files`; the other files of its folders are named
    as skipped on stderr), with a progress bar. Each probe is fitted by
    :func:`f2l.prior.probe_fit.fit_probe_files`: a bad one is a record with status "error"."""
    from f2l.prior.probe_fit import fit_probe_files, list_probe_files

    paths, skipped = list_probe_files(probes)
    for message in skipped:
        typer.echo(f"f2l: {message}", err=True)
    if not paths:
        _fail("no .exr probes found (nor .hdr, .rgbe, .tif, .tiff, .pfm) in " + ", ".join(map(str, probes)))
    m = _load_model_or_fail(model, _grid(grid))
    with _counted(len(paths), f"{what} {model}", not json_out) as step:
        records = fit_probe_files(paths, m, progress=step, out_dir=out_dir)
    return m, records, skipped


def fit_probe_cmd(
    probes: list[Path] = typer.Argument(..., help="Lat-long HDR probes (.exr, .hdr, .pfm, float .tif) or folders of them."),
    model: str = typer.Option(..., "--model", "-m", help="Lighting model name."),
    out: Optional[Path] = typer.Option(None, "--out", help="Write fit_probe.csv and fitted probes here."),
    grid: Grid = "64x128",
    json_out: JsonOut = False,
) -> None:
    """Fit a lighting model directly to HDR probes (paper Table 1); report the sun angle where known.

    A probe that cannot be fitted (unreadable, malformed side file, black, implausible) is a row
    with status "error" and its reason; the others are fitted and the table is written. Exit code
    4 when some probes failed, 1 when every probe failed."""
    from f2l.prior.fit_report import write_fit_report

    m, records, skipped = _fit_probe_inputs(probes, model, grid, json_out, "fit-probe", out)
    summary = write_fit_report(records, m, out)
    summary["skipped"] = skipped
    if json_out:
        typer.echo(json.dumps(summary))
    else:
        typer.echo(summary["markdown"])
    exit_for(summary["errors"], len(records) - summary["errors"])


def sky_corpus(
    out: Path = typer.Option(..., "--out", help="Output folder for the sky EXRs (+ JSON side files)."),
    n: int = typer.Option(400, "--n", help="Number of skies."),
    seed: Seed = 0,
    grid: Grid = "64x128",
    overcast_fraction: OvercastFraction = 0.25,
    json_out: JsonOut = False,
) -> None:
    """Write the project's default sky corpus (CIE clear + overcast skies) for `f2l prior build`."""
    from f2l.prior.corpus import write_sky_corpus

    with _counted(n, "sky-corpus", not json_out) as step:
        paths = write_sky_corpus(out, n, seed=seed, grid=_grid(grid), overcast_fraction=overcast_fraction,
                                 progress=step)
    typer.echo(json.dumps({"written": len(paths), "out": str(out)}))


def build_prior_cmd(
    probes: list[Path] = typer.Argument(..., help="Folders of lat-long sky probes (.exr, .hdr, .pfm, float .tif), or files."),
    model: str = typer.Option(..., "--model", "-m", help="Lighting model name."),
    out: Path = typer.Option(..., "--out", help="Prior JSON to write."),
    components: int = typer.Option(6, help="GMM components."),
    seed: int = typer.Option(0, help="Seed of the GMM fit."),
    grid: Grid = "64x128",
    json_out: JsonOut = False,
) -> None:
    """Fit the model to every probe, then a GMM over its prior features: the model's prior.

    A probe that cannot be fitted (unreadable, malformed side file, black, implausible, a fit that
    overflows) is skipped with its reason on stderr and the prior is built from the others. Exit
    code 4 when some probes were skipped (the prior is written), 1 when none could be fitted."""
    from f2l.cli.common import EXIT_NOTHING_DONE
    from f2l.estimate.model_prior import save_prior
    from f2l.prior.build import build_prior

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


def scale_report_cmd(
    faces: list[int] = typer.Option([10, 200], "--faces", help="Dataset sizes (repeatable)."),
    model: str = typer.Option("sh9", "--model", "-m", help="Lighting model to estimate with."),
    image_size: int = typer.Option(96, help="Synthetic photo size in pixels."),
    grid: Grid = "32x64",
    build: bool = typer.Option(False, "--build", help="Instead: build-dataset on a tree of face photos, local against --executor ray (f2l.pipeline.scale)."),
    workers: int = typer.Option(2, "--workers", min=1, help="--build: CPUs of the local Ray."),
    json_out: JsonOut = False,
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
