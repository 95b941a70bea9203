"""What the ``f2l`` CLI modules share: the ``--json`` option, ``--grid`` parsing, errors and exit codes."""

from __future__ import annotations

from typing import Annotated

import typer

JsonOut = Annotated[bool, typer.Option("--json", help="Print one JSON summary on stdout, nothing else (no progress, no table).")]
"""The ``--json`` option every command takes: ``json_out: JsonOut = False``."""
Grid = Annotated[str, typer.Option("--grid", help="Lighting grid HxW, e.g. 64x128 (probes and transport are on it).")]
"""``--grid``: ``grid: Grid = "64x128"`` (parsed by :func:`parse_grid`)."""
Seed = Annotated[int, typer.Option("--seed", help="Random seed: everything the command draws is deterministic from it.")]
"""``--seed``: ``seed: Seed = 0``."""
OvercastFraction = Annotated[float, typer.Option("--overcast-fraction", help="Fraction of overcast skies.")]
"""``--overcast-fraction``: ``overcast_fraction: OvercastFraction = 0.25``."""


def parse_grid(grid: str):
    """``"64x128"`` -> ``LatLongGrid(64, 128)``; a bad value is a usage error naming ``--grid``."""
    from f2l.lighting.grid import LatLongGrid

    try:
        h, w = (int(v) for v in grid.lower().split("x"))
        return LatLongGrid(h, w)
    except Exception as exc:  # noqa: BLE001
        raise typer.BadParameter(f"--grid must look like 64x128: {exc}") from exc


def fail(message: str, code: int = 2) -> None:
    """Print ``f2l: error: MESSAGE`` on stderr and exit with ``code``."""
    typer.echo(f"f2l: error: {message}", err=True)
    raise typer.Exit(code=code)


EXIT_NOTHING_DONE = 1
"""Some inputs failed and none succeeded (the tables and statuses are written all the same)."""
EXIT_USAGE = 2
"""A usage error, a missing input, or a machine the command cannot run on."""
EXIT_LOCKED = 3
"""``build-dataset``: another build holds the work folder's lock."""
EXIT_PARTIAL = 4
"""Some inputs failed, the others succeeded: everything that could be done is written."""


def exit_for(failed: int, succeeded: int) -> None:
    """The batch commands' exit code (docs/guide/reliability.md): 0 when nothing failed,
    :data:`EXIT_PARTIAL` when some inputs failed and others succeeded, :data:`EXIT_NOTHING_DONE`
    when inputs failed and none succeeded. A refusal for what an input shows (no face, a face too
    small, a probe without a sun) is a result, not a failure; an input that cannot be read or
    holds invalid values is a failure."""
    if failed and not succeeded:
        raise typer.Exit(code=EXIT_NOTHING_DONE)
    if failed:
        raise typer.Exit(code=EXIT_PARTIAL)

