"""EstimatorConfig's fields are grouped and documented in their metadata, and become `f2l estimate`
options in one place (f2l.cli.common): `--set NAME=VALUE`, checked against the fields and their
types, and `--settings`. Explicit settings apply with or without a config."""

from __future__ import annotations

import dataclasses
import hashlib
import json

import pytest
import typer
from typer.testing import CliRunner

from f2l.cli.app import app
from f2l.cli.common import estimate_settings, parse_settings, settings_text
from f2l.estimate.config import GROUPS, EstimatorConfig


def test_metadata_leaves_the_settings_hash_unchanged():
    cfg = dataclasses.asdict(EstimatorConfig())
    cfg.pop("sun_spread")  # a field added after the metadata (f2l.estimate.sun_spread)
    cfg.pop("neighbour_shadows")  # likewise (f2l.estimate.neighbours)
    cfg.update(skin_gloss=0.05, skin_reflection=0.0)  # the defaults when the metadata was added (issue 44 changed them)
    digest = hashlib.sha256(json.dumps(cfg, sort_keys=True).encode()).hexdigest()
    assert digest == "fe31b63e0a8a7cc45185dce8a9e8b28a19d5ec1076139402beadac9102fdac37"  # before the metadata


def test_every_field_has_a_group_and_help():
    for f in dataclasses.fields(EstimatorConfig):
        assert f.metadata["group"] in GROUPS and f.metadata["help"], f.name
    text = settings_text()
    assert [line for line in text.splitlines() if line.startswith("[")] == [f"[{g}]" for g in GROUPS]
    assert "skin_gloss = 0.1" in text and "sun_elevation_prior " not in text  # filled per record, not a setting


def test_set_values_are_parsed_by_the_fields_types():
    got = parse_settings(["sun_starts=5", "fixed_albedo=0.5,0.4,0.3", "sun_elevation_profile_deg=", "max_pixels=None",
                          "clipped_bounds=off", "irls_iters=3,4", "skin-gloss=0"])
    assert got == {"sun_starts": 5, "fixed_albedo": (0.5, 0.4, 0.3), "sun_elevation_profile_deg": (),
                   "max_pixels": None, "clipped_bounds": False, "irls_iters": (3, 4), "skin_gloss": 0.0}


@pytest.mark.parametrize("pair, says", [("nope=1", "unknown setting 'nope'; the settings are: albedo_prior_weight"),
                                        ("sun_starts=many", "sun_starts='many': not a int"),
                                        ("fixed_albedo=1,2", "expected 3 comma-separated values"),
                                        ("clipped_bounds=maybe", "expected true or false"),
                                        ("sun_starts", "expected NAME=VALUE")])
def test_a_bad_setting_names_the_field(pair, says):
    with pytest.raises(typer.BadParameter, match=says.replace("(", r"\(")):
        parse_settings([pair])


def test_fields_with_options_of_their_own_are_set_through_them():
    with pytest.raises(typer.BadParameter, match="use --skin-gloss"):
        estimate_settings(["skin_gloss=0.1"])
    assert estimate_settings(["sun_starts=4"], skin_gloss=0.0, max_iter=None) == {"sun_starts": 4, "skin_gloss": 0.0}


def test_cli_lists_settings_and_refuses_unknown_ones(tmp_path):
    res = CliRunner().invoke(app, ["estimate", "--settings"])
    assert res.exit_code == 0 and "[optimiser]" in res.stdout and "max_iter = 18" in res.stdout
    res = CliRunner().invoke(app, ["estimate", str(tmp_path), "-m", "sh9", "--out", str(tmp_path / "o"),
                                   "--set", "nope=1"])
    assert res.exit_code == 2 and "unknown setting 'nope'" in res.output


def test_explicit_settings_apply_with_a_config(small_shards, tmp_path):
    from f2l.estimate.runner import RUN_FILE, run_estimates

    run_estimates([small_shards], ["sh9"], tmp_path, workers=1, threads=1, progress=None, joint="none",
                  config=EstimatorConfig(max_iter=2, threads=1), skin_gloss=0.0, settings={"sun_starts": 1})
    cfg = json.loads((tmp_path / RUN_FILE).read_text())["config"]
    assert (cfg["skin_gloss"], cfg["sun_starts"], cfg["max_iter"]) == (0.0, 1, 2)
    with pytest.raises(ValueError, match="unknown estimator setting"):
        run_estimates([small_shards], ["sh9"], tmp_path / "b", settings={"nope": 1})
