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


def require_render_dirs(render_dirs) -> None:
    """Fail (usage) unless every folder is an ``f2l eval render-faces`` output (it has ``meta/``)."""
    from pathlib import Path

    missing = [str(d) for d in render_dirs if not (Path(d) / "meta").is_dir()]
    if missing:
        fail(f"not a render-faces folder (no meta/): {', '.join(missing)}")


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



def config_settings() -> dict:
    """EstimatorConfig's public fields: ``{name: (type, default, group, help)}``, from the fields'
    metadata (:mod:`f2l.estimate.config`): the one place the CLI turns them into options."""
    import dataclasses
    import typing

    from f2l.estimate.config import EstimatorConfig

    hints = typing.get_type_hints(EstimatorConfig)
    return {f.name: (hints[f.name], f.default, f.metadata["group"], f.metadata["help"])
            for f in dataclasses.fields(EstimatorConfig) if f.metadata.get("public", True)}


def _parse_value(text: str, kind):
    """``text`` as a value of type ``kind`` (int, float, bool, ``X | None``, ``tuple[X, ...]``,
    ``tuple[X, Y]``; a tuple's items comma-separated); ValueError saying what was expected."""
    import types
    import typing

    args = typing.get_args(kind)
    if typing.get_origin(kind) in (typing.Union, types.UnionType):
        if text.strip().lower() == "none":
            return None
        (kind,) = [a for a in args if a is not type(None)]
        return _parse_value(text, kind)
    if typing.get_origin(kind) is tuple:
        items = [t for t in (s.strip() for s in text.split(",")) if t]
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_parse_value(t, args[0]) for t in items)
        if len(items) != len(args):
            raise ValueError(f"expected {len(args)} comma-separated values, got {len(items)}")
        return tuple(_parse_value(t, a) for t, a in zip(items, args))
    if kind is bool:
        low = text.strip().lower()
        if low in ("1", "true", "yes", "on"):
            return True
        if low in ("0", "false", "no", "off"):
            return False
        raise ValueError("expected true or false")
    return kind(text)


def _type_name(kind) -> str:
    return getattr(kind, "__name__", None) if isinstance(kind, type) else str(kind).replace("typing.", "")


def parse_settings(pairs: list[str] | None) -> dict:
    """``--set NAME=VALUE`` (repeatable) -> ``{name: value}``, each checked against EstimatorConfig's
    public fields and their types; a bad one is a usage error naming the field (and, for an
    unknown name, the names allowed)."""
    fields = config_settings()
    out = {}
    for pair in pairs or []:
        name, sep, text = pair.partition("=")
        name = name.strip().replace("-", "_")
        if not sep:
            raise typer.BadParameter(f"{pair!r}: expected NAME=VALUE", param_hint="--set")
        if name not in fields:
            raise typer.BadParameter(f"unknown setting {name!r}; the settings are: {', '.join(sorted(fields))} "
                                     f"(f2l estimate --settings lists them)", param_hint="--set")
        kind = fields[name][0]
        try:
            out[name] = _parse_value(text, kind)
        except (TypeError, ValueError) as exc:
            raise typer.BadParameter(f"{name}={text!r}: not a {_type_name(kind)} ({exc})", param_hint="--set") from exc
    return out


OPTION_OF = {"threads": "--threads", "max_iter": "--max-iter", "max_pixels": "--max-pixels",
             "sun_prior_from_capture": "--sun-prior/--no-sun-prior", "skin_gloss": "--skin-gloss",
             "skin_reflection": "--skin-reflection"}
"""EstimatorConfig fields that ``f2l estimate`` sets through options of their own."""


def estimate_settings(pairs: list[str] | None, **options) -> dict:
    """The estimator settings of ``f2l estimate``: ``--set NAME=VALUE`` (:func:`parse_settings`) and
    the options of their own (``options``: field -> value, None when not given). A ``--set`` of a
    field with its own option is a usage error naming the option."""
    settings = parse_settings(pairs)
    for name in settings:
        if name in OPTION_OF:
            raise typer.BadParameter(f"{name} has an option of its own: use {OPTION_OF[name]}", param_hint="--set")
    settings.update({k: v for k, v in options.items() if v is not None})
    return settings


def print_settings(value: bool) -> None:
    """``--settings`` (an eager flag): print :func:`settings_text` and exit."""
    if value:
        typer.echo(settings_text())
        raise typer.Exit()


def settings_text() -> str:
    """EstimatorConfig's public fields by group, each with its type, default and help (``--settings``)."""
    from f2l.estimate.config import GROUPS

    fields = config_settings()
    lines = []
    for group in GROUPS:
        names = [n for n, f in fields.items() if f[2] == group]
        if names:
            lines.append(f"[{group}]")
            lines += [f"  {n} = {_format(fields[n][1])}  ({_type_name(fields[n][0])}) {fields[n][3]}" for n in names]
    return "\n".join(lines)


def _format(value) -> str:
    return ",".join(str(v) for v in value) if isinstance(value, tuple) else str(value)
