"""``f2l eval groups`` on a render-faces-like folder: one photo of two people (the astronaut twice,
mirrored) under a known clear sky; fit-faces, then the table of error against the number of faces
with the real estimator, single and joint, on both."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image


def test_eval_groups_scores_single_and_joint_estimates(tmp_path):
    skdata = pytest.importorskip("skimage.data")
    from typer.testing import CliRunner

    from f2l.cli import app
    from f2l.dev.bench_detect import ASTRONAUT_FACE
    from f2l.io.exr import write_exr
    from f2l.lighting.grid import LatLongGrid, direction_from_angles
    from f2l.synth.skies import clear_sky

    render = tmp_path / "render"
    for sub in ("photos", "meta", "probes"):
        (render / sub).mkdir(parents=True)
    a = skdata.astronaut()
    Image.fromarray(np.ascontiguousarray(np.concatenate([a, a[:, ::-1]], axis=1))).save(
        render / "photos" / "pbr-group-s0-00001.jpg", quality=95)
    grid = LatLongGrid(32, 64)
    sun = direction_from_angles(np.radians(40.0), np.radians(30.0))
    write_exr(render / "probes" / "pbr-group-s0-00001.exr",
              clear_sky(grid, np.radians(40.0), np.radians(30.0)).astype(np.float32))
    boxes = [ASTRONAUT_FACE.tolist(), [1024 - ASTRONAUT_FACE[2], ASTRONAUT_FACE[1], 1024 - ASTRONAUT_FACE[0],
                                       ASTRONAUT_FACE[3]]]
    faces = [{"box": [float(v) for v in b], "width_px": float(b[2] - b[0]), "in_frame": True,
              "pose": {"yaw_deg": 0.0}} for b in boxes]
    (render / "meta" / "pbr-group-s0-00001.json").write_text(json.dumps({
        "face_id": "pbr-group-s0-00001", "framing": "group", "faces": faces,
        "sky": {"kind": "clear", "sun_direction": [float(v) for v in sun]}}))
    runner = CliRunner()
    res = runner.invoke(app, ["fit-faces", str(render / "photos"), "--out", str(tmp_path / "fitted"), "--grid", "32x64",
                              "--json"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["eval", "groups", str(render), "--fitted", str(tmp_path / "fitted"), "--faces", "1",
                              "--faces", "2", "--out", str(tmp_path / "report")])
    assert res.exit_code == 0, res.output
    rows = json.loads((tmp_path / "report" / "groups.json").read_text())
    assert sorted(r["n"] for r in rows) == [1, 2] and {r["part"] for r in rows} == {"report"}
    for r in rows:
        assert all(np.isfinite(r["single"])) and all(np.isfinite(r["joint"])) and r["joint_s"] > 0
    one = next(r for r in rows if r["n"] == 1)
    assert one["joint"] == one["single"]  # a group of one is the single estimate
    table = (tmp_path / "report" / "groups.md").read_text()
    assert "| 2 | 1 (1) |" in table and "Reporting part" in table
