"""`f2l scale-report --build`: build-dataset on a tree of face photos, local against Ray, timed in
fresh processes with the whole process tree's peak memory (a tiny tree here; README: 10 and 200)."""

from __future__ import annotations

import pytest

from f2l.pipeline.scale import format_build_table, run_build_scale


def test_build_scale_runs_both_executors():
    pytest.importorskip("ray")
    rows = run_build_scale((3,), executors=("local", "ray"), workers=2)
    assert [r["executor"] for r in rows] == ["local", "ray"]
    assert rows[0]["records"] == rows[1]["records"] >= 3  # the same dataset either way
    assert all(r["seconds"] > 0 and r["faces_per_min"] > 0 and r["peak_mib"] > 100 for r in rows)
    assert rows[1]["peak_mib"] > rows[0]["peak_mib"]  # Ray's raylet, object store and workers count
    assert "| 3 | ray |" in format_build_table(rows)
