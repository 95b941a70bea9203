"""``f2l eval groups`` on a render-faces-like folder: one photo of two people (the astronaut twice,
mirrored) under a known clear sky; fit-faces, then the table of error against the number of faces
with the real estimator, single and joint, on both."""

from __future__ import annotations

import json

import numpy as np

from tests.render_helpers import astronaut_pair_render


def test_eval_groups_scores_single_and_joint_estimates(tmp_path):
    from typer.testing import CliRunner

    from f2l.cli import app

    render, fitted = astronaut_pair_render(tmp_path)
    runner = CliRunner()
    res = runner.invoke(app, ["eval", "groups", str(render), "--fitted", str(fitted), "--faces", "1",
                              "--faces", "2", "--out", str(tmp_path / "report")])
    assert res.exit_code == 0, res.output
    rows = json.loads((tmp_path / "report" / "groups.json").read_text())
    assert sorted(r["n"] for r in rows) == [1, 2] and {r["part"] for r in rows} == {"report"}
    for r in rows:
        assert all(np.isfinite(r["single"])) and all(np.isfinite(r["joint"])) and r["joint_s"] > 0
    for r in rows:  # the sun's cones of the joint and of each face alone (clear sky: they exist)
        assert len(r["single_cones"]) == r["n"] and all(c is not None and 0 < c[0] < c[1] for c in r["single_cones"])
        assert r["joint_cones"] is not None and 0 < r["joint_cones"][0] < r["joint_cones"][1]
    one = next(r for r in rows if r["n"] == 1)
    assert one["joint"] == one["single"]  # a group of one is the single estimate
    table = (tmp_path / "report" / "groups.md").read_text()
    assert "| 2 | 1 (1) |" in table and "Reporting part" in table
    assert "in 68% / 90% cone" in table and "of 2 (" in table  # the two faces alone, in the cone table
