"""The command line grouped by task (f2l.cli.app): the user's commands first, research and
developer tools in groups, plugins' groups from entry points, the old names for one release."""

from __future__ import annotations

import json

import pytest
import typer
from typer.testing import CliRunner

from f2l.cli import app
from f2l.cli.app import DEPRECATED, GROUPS, USER_COMMANDS


@pytest.fixture(scope="module")
def command():
    return typer.main.get_command(app)


def test_help_lists_the_users_commands_first_then_the_groups():
    out = CliRunner().invoke(app, ["--help"], terminal_width=120).stdout
    user_at = out.index("Your photos and captures")
    groups_at = out.index("Research, evaluation and development")
    assert user_at < groups_at
    positions = [out.index(f" {name} ", user_at) for name in USER_COMMANDS]
    assert positions == sorted(positions) and positions[-1] < groups_at
    for group in ("eval", "prior", "dev", "ae"):
        assert f" {group} " in out[groups_at:]
    for old in DEPRECATED:  # hidden, though they still run
        assert f" {old} " not in out


def test_the_top_level_is_the_users_path_and_groups(command):
    visible = {name for name, c in command.commands.items() if not c.hidden}
    assert visible == set(USER_COMMANDS) | set(GROUPS) | {"ae"}
    assert len(USER_COMMANDS) <= 11  # estimate, video, fit-faces, ingest, make-probes, calibrate, build-dataset, ...


def test_every_old_name_leads_to_its_new_command(command):
    for old, new in DEPRECATED.items():
        group, name = new.split()
        assert old in command.commands and command.commands[old].hidden, old
        target = command.commands[group]
        assert name in getattr(target, "commands", {}), new


def test_an_old_name_runs_the_command_and_says_where_it_went(tmp_path):
    res = CliRunner().invoke(app, ["sky-corpus", "--out", str(tmp_path / "a"), "--n", "1", "--grid", "8x16", "--json"])
    assert res.exit_code == 0, res.output
    assert "'sky-corpus' is now 'f2l prior sky-corpus'" in res.stderr
    assert json.loads(res.stdout)["written"] == 1
    res = CliRunner().invoke(app, ["prior", "sky-corpus", "--out", str(tmp_path / "b"), "--n", "1", "--grid", "8x16", "--json"])
    assert res.exit_code == 0 and res.stderr == "" and json.loads(res.stdout)["written"] == 1
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == sorted(p.name for p in (tmp_path / "b").iterdir())


def test_json_is_one_option_everywhere(command):
    """--json is defined once (f2l.cli.common.JsonOut): the same help on every command."""
    helps = set()

    def walk(c):
        if hasattr(c, "commands"):  # a group
            for sub in c.commands.values():
                walk(sub)
            return
        helps.update(p.help for p in c.params if "--json" in getattr(p, "opts", ()))

    walk(command)
    assert len(helps) == 1 and "one JSON summary" in helps.pop()


def test_a_plugin_group_is_a_group(command):
    ae = command.commands["ae"]
    assert set(ae.commands) == {"corpus", "train"}


def test_stage_packages_hold_no_cli_code():
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "f2l"
    stray = [p.relative_to(root).as_posix() for p in root.rglob("cli*.py") if p.parent.name != "cli"]
    assert stray == []
