"""The ``f2l`` command line: the user's commands at the top level, research and developer tools in
groups, plugins' commands in their own groups.

- **Your photos and captures** (top level): ``ingest``, ``make-probes``, ``calibrate``,
  ``build-dataset``, ``fit-faces``, ``estimate``, ``evaluate``, ``report``, ``models``, ``demo``.
- ``f2l eval …``: evaluation sets, renders and the paper's tables (``real``, ``framings``,
  ``render-faces``, ``synth``, ``fit-probe``, ...).
- ``f2l prior …``: the Sun+Sky prior (``sky-corpus``, ``build``).
- ``f2l dev …``: benchmarks (``bench``, ``bench-capture``, ``bench-faces``, ``bench-detect``,
  ``scale-report``).
- A plugin's group: entry-point group ``f2l.command_groups`` (name = the group, value = a
  ``typer.Typer``), e.g. the built-in autoencoder's ``f2l ae corpus|train``. Single commands in
  ``f2l.commands`` are still added at the top level.

The names before the grouping (``eval-real``, ``render-faces``, ``build-prior``, ``bench``,
``ae-corpus``, ...) still work for one release: hidden from ``--help``, they print where the
command went and run it (:data:`DEPRECATED`).
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path
from typing import Optional

import typer

from f2l import __version__
from f2l.cli import build, capture, colour, evaluation, face, research, user, video
from f2l.cli.common import fail

USER_PANEL = "Your photos and captures"
GROUP_PANEL = "Research, evaluation and development"

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


USER_COMMANDS = {
    "estimate": user.estimate, "video": video.video_cmd, "fit-faces": face.fit_faces_cmd, "ingest": capture.ingest_cmd,
    "make-probes": capture.make_probes_cmd, "calibrate": colour.calibrate_cmd,
    "build-dataset": build.build_dataset_cmd, "evaluate": user.evaluate, "report": user.report,
    "models": user.models, "demo": user.demo,
}
"""The user's path, in the order ``--help`` lists it."""

GROUPS = {
    "eval": ("Evaluation sets, renders and the paper's tables.", {
        "real": evaluation.eval_real_cmd, "ablations": evaluation.eval_real_ablations_cmd,
        "geometry": evaluation.eval_real_geometry_cmd, "search": evaluation.eval_real_search_cmd,
        "framings": evaluation.eval_framings_cmd, "groups": evaluation.eval_groups_cmd,
        "sessions": evaluation.eval_sessions_cmd, "video": video.eval_video_cmd,
        "shade": evaluation.eval_shade_cmd, "render-faces": evaluation.render_faces_cmd,
        "render-skies": evaluation.render_skies_cmd, "twin-geometry": evaluation.twin_geometry_cmd,
        "compare-geometry": face.compare_geometry_cmd, "synth": research.synth,
        "fit-probe": research.fit_probe_cmd,
    }),
    "prior": ("The Sun+Sky model's prior: its sky corpus and the GMM built from it.", {
        "sky-corpus": research.sky_corpus, "build": research.build_prior_cmd,
    }),
    "dev": ("Benchmarks: error against run time, capture, face fitting, detection, scale.", {
        "bench": research.bench, "bench-capture": capture.bench_capture_cmd,
        "bench-faces": face.bench_faces_cmd, "bench-detect": face.bench_detect_cmd, "bench-video": video.bench_video_cmd,
        "scale-report": research.scale_report_cmd,
    }),
}
"""Groups of research and developer commands: name -> (help, {command: function})."""

DEPRECATED = {
    "synth": "eval synth", "fit-probe": "eval fit-probe", "eval-real": "eval real",
    "eval-real-ablations": "eval ablations", "eval-real-geometry": "eval geometry",
    "eval-real-search": "eval search", "eval-framings": "eval framings",
    "render-faces": "eval render-faces", "render-skies": "eval render-skies",
    "twin-geometry": "eval twin-geometry", "compare-geometry": "eval compare-geometry",
    "sky-corpus": "prior sky-corpus", "build-prior": "prior build", "bench": "dev bench",
    "bench-capture": "dev bench-capture", "bench-faces": "dev bench-faces", "bench-detect": "dev bench-detect",
    "scale-report": "dev scale-report", "ae-corpus": "ae corpus", "train-ae": "ae train",
}
"""Command names before the grouping (2026-11-27) -> where they are now; kept for one release."""


def _deprecated(function, old: str, new: str):
    """``function`` under its old name: says where it went (stderr), then runs it."""
    @functools.wraps(function)
    def alias(*args, **kwargs):
        typer.echo(f"f2l: '{old}' is now 'f2l {new}'; the old name goes in the next release", err=True)
        return function(*args, **kwargs)

    return alias


def _broken_command(name: str, target: str, exc: Exception):
    def broken() -> None:
        fail(f"command {name!r} ({target}) failed to load: {type(exc).__name__}: {exc}")

    broken.__doc__ = f"(failed to load: {target})"
    return broken


def _plugin_groups() -> dict[str, typer.Typer]:
    """Groups plugins add (entry-point group ``f2l.command_groups``); a group that fails to load
    is a command that says why when run."""
    from importlib.metadata import entry_points

    out = {}
    for ep in entry_points(group="f2l.command_groups"):
        if ep.name in out or ep.name in GROUPS or ep.name in USER_COMMANDS:
            continue
        try:
            group = ep.load()
            if not isinstance(group, typer.Typer):
                raise TypeError(f"{ep.value} is a {type(group).__name__}, not a typer.Typer")
        except Exception as exc:  # noqa: BLE001 - a broken plugin must not break the CLI
            app.command(ep.name, rich_help_panel=GROUP_PANEL)(_broken_command(ep.name, ep.value, exc))
            continue
        out[ep.name] = group
    return out


def _register() -> None:
    for name, function in USER_COMMANDS.items():
        app.command(name, rich_help_panel=USER_PANEL)(function)
    targets = {}
    for group_name, (help_text, commands) in GROUPS.items():
        group = typer.Typer(help=help_text, no_args_is_help=True, add_completion=False)
        for name, function in commands.items():
            group.command(name)(function)
            targets[f"{group_name} {name}"] = function
        app.add_typer(group, name=group_name, rich_help_panel=GROUP_PANEL)
    for group_name, group in _plugin_groups().items():
        app.add_typer(group, name=group_name, rich_help_panel=GROUP_PANEL)
        for info in group.registered_commands:
            targets[f"{group_name} {info.name or info.callback.__name__.replace('_', '-')}"] = info.callback
    taken = set(USER_COMMANDS) | set(GROUPS)
    for old, new in DEPRECATED.items():
        if new in targets and old not in taken:
            app.command(old, hidden=True, help=f"Now `f2l {new}`.")(_deprecated(targets[new], old, new))
            taken.add(old)
    _add_plugin_commands(taken)


def _add_plugin_commands(taken: set) -> None:
    """Single commands plugins add at the top level (entry-point group ``f2l.commands``: name =
    the command, value = a typer command function)."""
    from importlib.metadata import entry_points

    for ep in entry_points(group="f2l.commands"):
        if ep.name in taken:
            continue
        taken.add(ep.name)
        try:
            function = ep.load()
        except Exception as exc:  # noqa: BLE001 - a broken plugin must not break the CLI
            function = _broken_command(ep.name, ep.value, exc)
        app.command(ep.name, rich_help_panel=GROUP_PANEL)(function)


_register()


def main() -> None:
    try:
        app()
    except KeyboardInterrupt:
        sys.exit(130)
