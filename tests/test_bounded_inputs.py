"""Bounded TOML/JSON reading (f2l.io.bounded) and probe plausibility (f2l.lighting.plausibility)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from f2l.io.bounded import MAX_DEPTH, InputError, json_depth, load_json, load_toml
from f2l.lighting.plausibility import MIN_SKY_COVERAGE, probe_problem


# -- bounded JSON / TOML ---------------------------------------------------------------------------
def test_json_depth_counts_brackets_outside_strings():
    assert json_depth('{"a": [1, {"b": [2]}]}') == 4
    assert json_depth('{"a": "[[[[[[", "b": "\\"[[["}') == 1
    assert json_depth("3") == 0


@pytest.mark.parametrize("depth", [MAX_DEPTH + 1, 1000, 100_000])
def test_deep_json_is_refused_without_recursion(depth):
    text = "[" * depth + "]" * depth
    with pytest.raises(InputError, match=r"meta\.json: nested 10*\d* levels deep|meta\.json: nested \d+ levels"):
        load_json(text, "meta.json")


def test_json_at_the_depth_limit_is_read():
    text = "[" * MAX_DEPTH + "]" * MAX_DEPTH
    value = load_json(text, "x")
    for _ in range(MAX_DEPTH - 1):
        value = value[0]
    assert value == []


@pytest.mark.parametrize("text, key", [('{"a": NaN}', "NaN"), ('{"a": {"b": Infinity}}', "Infinity"),
                                       ('{"a": [1, -Infinity]}', "Infinity"), ('{"a": 1e999}', "a: inf")])
def test_non_finite_json_numbers_are_refused(text, key):
    with pytest.raises(InputError, match=key):
        load_json(text, "side.json")


def test_long_strings_and_big_texts_are_refused():
    with pytest.raises(InputError, match=r"s\.json: name: a string of 70000 characters"):
        load_json(json.dumps({"name": "x" * 70_000}), "s.json")
    with pytest.raises(InputError, match="more than the 100 accepted"):
        load_json(" " * 101, "s.json", max_bytes=100)
    with pytest.raises(InputError, match="not UTF-8"):
        load_json(b'{"a": "\xff"}', "s.json")


def test_toml_bounds_name_the_key():
    with pytest.raises(InputError, match=r"session\.toml: shots/0/pitch_deg: nan is not a finite number"):
        load_toml('[[shots]]\nfiles = "a"\npitch_deg = nan\n', "session.toml")
    with pytest.raises(InputError, match="nested deeper than 32"):
        load_toml("a = " + "{b = " * 1000 + "1" + "}" * 1000, "session.toml")
    with pytest.raises(InputError, match="nested deeper than 32"):
        load_toml("a = " + "[" * 40 + "]" * 40, "session.toml")
    with pytest.raises(InputError, match="not valid TOML"):
        load_toml("a = = 1", "session.toml")
    assert load_toml('a.b.c = 1\n[[s]]\nx = 2.5\n', "ok.toml") == {"a": {"b": {"c": 1}}, "s": [{"x": 2.5}]}


# -- probe plausibility -------------------------------------------------------------------------------
def test_probe_problem_accepts_a_sky_and_names_every_fault():
    from f2l.lighting.grid import LatLongGrid
    from f2l.synth.skies import clear_sky

    sky = clear_sky(LatLongGrid(16, 32), 0.6, 0.3, turbidity=3.0, sun_kappa=64.0)
    assert probe_problem(sky) is None
    assert "black" in probe_problem(np.zeros_like(sky))
    assert "full-sphere lat-long" in probe_problem(sky[:, :30])
    assert "full-sphere lat-long" in probe_problem(np.ones((15, 30, 3)))
    bad = sky.copy()
    bad[3, 4, 1] = np.nan
    assert probe_problem(bad) == "1 texels are NaN or infinite"
    assert "negative" in probe_problem(sky - 1.0)
    # light only in the top two rows: 1.9% of the upper hemisphere
    few = np.zeros_like(sky)
    few[:2] = 1.0
    assert "covers" in probe_problem(few)
    # the ground may be black: a sky-only probe is fine
    ground_black = sky.copy()
    ground_black[8:] = 0.0
    assert probe_problem(ground_black) is None


def test_probe_problem_uses_the_coverage_mask():
    sky = np.ones((16, 32, 3))
    seen = np.zeros((16, 32), bool)
    assert "covers 0.0%" in probe_problem(sky, coverage=seen)
    seen[:8] = True
    assert probe_problem(sky, coverage=seen) is None
    seen[:] = False
    seen[:8, :int(32 * MIN_SKY_COVERAGE) + 1] = True
    assert probe_problem(sky, coverage=seen) is None
