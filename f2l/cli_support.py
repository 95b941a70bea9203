"""Helpers shared by the ``f2l`` CLI modules (:mod:`f2l.cli` and the stages' ``cli.py``)."""

from __future__ import annotations

import typer


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
