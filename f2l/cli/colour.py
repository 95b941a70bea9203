"""CLI layer of colour calibration (registered by :mod:`f2l.cli.app`)."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from f2l.cli.common import JsonOut, exit_for
from f2l.cli.progress import progress_bars


def calibrate_cmd(
    chart_photos: list[Path] = typer.Argument(..., help="Photos of a ColorChecker Classic (JPEG/PNG/TIFF or camera RAW) or folders of them."),
    out: Path = typer.Option(..., "--out", help="Output directory (colour.parquet, reports/)."),
    chart: str = typer.Option("ColorChecker24 - After November 2014", "--chart", help="Reference chart edition (a colour-science name), e.g. 'ColorChecker24 - Before November 2014'."),
    method: str = typer.Option("3x3", "--method", help="Colour correction: 3x3 (Cheung 2004 matrix) or root-polynomial (Finlayson 2015, degree 2)."),
    reports: bool = typer.Option(True, "--reports/--no-reports", help="Write a swatch PNG and a ΔE2000 table per photo under OUT/reports/."),
    json_out: JsonOut = False,
) -> None:
    """Fit a colour correction (camera RGB → linear Rec.709) to each ColorChecker photo; ΔE2000 reports."""
    from f2l.colour.calibrate import calibrate, format_summary, summarise
    from f2l.colour.chart import editions
    from f2l.colour.fit import METHODS
    from f2l.face.run import expand_photos

    if method not in METHODS:
        raise typer.BadParameter(f"must be one of {', '.join(METHODS)}", param_hint="--method")
    if chart not in editions():
        raise typer.BadParameter(f"must be one of: {'; '.join(editions())}", param_hint="--chart")
    if not expand_photos(chart_photos):
        typer.echo("f2l: error: no photos found in " + ", ".join(map(str, chart_photos)), err=True)
        raise typer.Exit(code=2)
    with progress_bars(not json_out) as progress:
        results = calibrate(chart_photos, out, edition=chart, method=method, reports=reports,
                            progress=progress)
    summary = summarise(results, out)
    typer.echo(json.dumps(summary) if json_out else format_summary(summary))
    if all(r.status in ("no_chart", "error") for r in results):
        raise typer.Exit(code=1)
    exit_for(sum(r.status == "error" for r in results), sum(r.status != "error" for r in results))
