"""The ``f2l`` command line (typer): :data:`app` and :func:`main` (:mod:`f2l.cli.app` says how the
commands are grouped). Thin: parsing, progress and exit codes; the work is in the stage packages,
which hold no CLI code."""

from f2l.cli.app import app, main

__all__ = ["app", "main"]
