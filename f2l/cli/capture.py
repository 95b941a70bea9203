"""CLI layer of the capture stages (registered by :mod:`f2l.cli.app`)."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from f2l.cli.common import JsonOut, exit_for
from f2l.cli.progress import progress_bars


def ingest_cmd(
    root: Path = typer.Argument(..., help="Capture tree: one folder per session (site), or a flat folder."),
    work: Path = typer.Option(Path("work"), "--work", help="Work folder: captures.parquet goes here."),
    session_gap_min: float = typer.Option(30.0, help="Flat folders: a gap longer than this (minutes) starts a new session."),
    bracket_gap_s: float = typer.Option(15.0, help="Frames further apart than this (s) are not one bracket."),
    detect_roles: bool = typer.Option(True, "--detect-roles/--no-detect-roles", help="Run the face/chart detectors on files no folder name or session.toml gives a role."),
    allow_outside: bool = typer.Option(False, "--allow-outside", help="Let a session.toml name files (a flat field) outside its session folder (absolute paths, '..', symlinks out), and read capture files that are symlinks out of ROOT. Refused by default."),
    json_out: JsonOut = False,
) -> None:
    """Scan camera RAW, JPEG/PNG/TIFF and EXR/HDR files into WORK/captures.parquet (incremental).

    Every file is a row; one that cannot be read, or whose session.toml names something invalid,
    is a row with status "error" and the reason. Exit code 4 when some files failed, 1 when all did."""
    from f2l.capture.manifest import run_ingest

    try:
        with progress_bars(not json_out) as progress:
            summary = run_ingest(root, work, session_gap_min=session_gap_min,
                                 bracket_gap_s=bracket_gap_s, detect_roles=detect_roles,
                                 progress=progress, allow_outside=allow_outside)
    except FileNotFoundError as exc:
        typer.echo(f"f2l: error: {exc}", err=True)
        raise typer.Exit(code=2)
    if json_out:
        typer.echo(json.dumps(summary.to_json()))
    else:
        _print_summary(summary)
    errors = summary.by_status.get("error", 0)
    exit_for(errors, summary.files - errors)


def _print_summary(summary) -> None:
    import pyarrow.parquet as pq

    typer.echo(f"{summary.files} files in {summary.sessions} sessions, {summary.brackets} brackets "
               f"-> {summary.table}")
    typer.echo(f"read {summary.read}, unchanged {summary.reused}"
               + (" (nothing to do)" if summary.read == 0 else ""))
    typer.echo("status: " + ", ".join(f"{k} {v}" for k, v in summary.by_status.items()))
    typer.echo("roles:  " + ", ".join(f"{k} {v}" for k, v in summary.by_role.items()))
    for problem in summary.session_problems + summary.warnings:
        typer.echo(f"f2l: warning: {problem}", err=True)
    _print_brackets(summary.bracket_list)
    rows = pq.read_table(summary.table, columns=["status", "message"]).to_pylist()
    problems = [r["message"] for r in rows if r["status"] != "ok"]
    for message in problems[:20]:
        typer.echo(f"  {message}")
    if len(problems) > 20:
        typer.echo(f"  ... and {len(problems) - 20} more (see the status column)")


def _print_brackets(brackets: list[dict], limit: int = 40) -> None:
    """One line per bracket: frames, EV100 range and the view it was split by."""
    if not brackets:
        return
    typer.echo("brackets:")
    for b in brackets[:limit]:
        view = ", ".join(f"{k[:-4]} {v:g}°" for k, v in b["view"].items()) or "no orientation given"
        ev = "" if b["ev100_min"] is None else f", EV100 {b['ev100_min']:.1f}..{b['ev100_max']:.1f}"
        typer.echo(f"  {b['bracket_id']}: {b['frames']} frames{ev}; {view}")
    if len(brackets) > limit:
        typer.echo(f"  ... and {len(brackets) - limit} more")


def session_problems(work: Path) -> list[str]:
    """Distinct "session: why its session.toml was not used" lines of WORK/captures.parquet."""
    import pyarrow.parquet as pq

    table = work / "captures.parquet"
    if not table.is_file():
        return []
    names = pq.read_schema(table).names
    if "session_problem" not in names:
        return []
    rows = pq.read_table(table, columns=["session", "session_problem"]).to_pylist()
    return sorted({f"session {r['session']}: {r['session_problem']}" for r in rows if r["session_problem"]})


def make_probes_cmd(
    root: Path = typer.Argument(..., help="The capture tree given to `f2l ingest`."),
    work: Path = typer.Option(Path("work"), "--work", help="Work folder holding captures.parquet; views/, probes/ and probes.parquet go here."),
    probe_height: int = typer.Option(128, "--probe-height", min=8, help="Probe rows (lat-long, width 2x): 128 is 1.4° per texel."),
    view_max_side: int = typer.Option(1024, help="Merged views are box-averaged to at most this many px per side before they are written and assembled."),
    colour: str = typer.Option("rec709", "--colour", help="rec709: linear Rec.709 through the camera's colour matrix (DNG ColorMatrix, else LibRaw's table); camera: camera RGB."),
    restore_sun: bool = typer.Option(False, "--restore-sun", help="Where the sun clips in every frame, restore its energy from the sky (matched to Hosek-Wilkie clear skies; flagged in probes.parquet)."),
    full_probe: bool = typer.Option(False, "--full-probe", help="Also write probes/<session>.full.exr at the views' own resolution (up to 512 rows; slow: ~13 s per view): a ground truth finer than the probe grid."),
    json_out: JsonOut = False,
) -> None:
    """Merge every bracket in the RAW domain and assemble each session's views into a lat-long probe.

    A bracket, view or probe that fails (or a probe refused as black or uncovered) is a row with
    status "error"; the others are written. Exit code 4 when some failed, 1 when all did."""
    from f2l.capture.probe_rows import COLOUR_SPACES
    from f2l.capture.probes import make_probes

    if colour not in COLOUR_SPACES:
        raise typer.BadParameter(f"expected one of {', '.join(COLOUR_SPACES)}", param_hint="--colour")
    for problem in session_problems(work):
        typer.echo(f"f2l: warning: {problem} (session ingested without it)", err=True)
    try:
        with progress_bars(not json_out) as progress:
            summary = make_probes(root, work, grid_height=probe_height, view_max_side=view_max_side,
                                  colour_space=colour, restore_sun=restore_sun, full_probe=full_probe,
                                  progress=progress)
    except FileNotFoundError as exc:
        typer.echo(f"f2l: error: {exc}", err=True)
        raise typer.Exit(code=2)
    out = summary.to_json()
    if json_out:
        typer.echo(json.dumps(out))
        exit_for(summary.errors, sum(r["status"] != "error" for r in summary.rows))
        return
    typer.echo(f"{summary.brackets} brackets -> {summary.views} placed views -> {summary.probes} "
               f"probes in {summary.seconds:.1f} s ({work}/probes.parquet)")
    for r in summary.rows:
        extra = "" if r["coverage_fraction"] is None else (
            f" coverage {r['coverage_fraction']:.0%}, saturated {r['saturated_fraction']:.2%}")
        typer.echo(f"  {r['kind']:5} {r['name']}: {r['status']}{extra} {r['message']}".rstrip())
    exit_for(summary.errors, sum(r["status"] != "error" for r in summary.rows))


def bench_capture_cmd(
    brackets: list[int] = typer.Option([2, 8], "--brackets", help="Tree sizes to time (brackets; repeatable)."),
    frames: int = typer.Option(5, help="Frames per bracket."),
    megapixels: float = typer.Option(2.0, help="Megapixels per synthetic DNG."),
    repeat: int = typer.Option(2, help="Best of this many runs."),
    compression: list[str] = typer.Option(["ljpeg"], "--compression",
                                          help="DNG compression: ljpeg (as cameras write RAWs) or none; repeatable."),
    json_out: JsonOut = False,
) -> None:
    """Ingest + merge time against a bare LibRaw decode of the same DNGs, and peak memory per tree size."""
    from f2l.dev.bench_capture import format_table, run_capture_bench

    from f2l.capture.dng import COMPRESSIONS

    bad = [c for c in compression if c not in COMPRESSIONS]
    if bad:
        raise typer.BadParameter(f"{bad[0]!r}: expected one of {', '.join(COMPRESSIONS)}", param_hint="--compression")
    rows = [row for c in compression for row in run_capture_bench(tuple(brackets), frames=frames, megapixels=megapixels,
                                                                  repeat=repeat, compression=c)]
    typer.echo(json.dumps(rows) if json_out else format_table(rows))
