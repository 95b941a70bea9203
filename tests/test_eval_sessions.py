"""Path-traced sessions (``f2l eval render-faces --session-size``) and ``f2l eval sessions``."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from f2l.estimate.frames import roll_probe, yaw_matrix
from f2l.lighting.grid import LatLongGrid, direction_from_angles, rotate_y
from f2l.render.dataset import RenderOptions, draw_case, draw_session_case, session_yaws, turn_lighting


def test_without_sessions_every_draw_is_the_default_one():
    for options in (RenderOptions(), RenderOptions(sunsky_fraction=1.0)):
        for index in range(6):
            assert draw_session_case(4, index, options) == draw_case(4, index, options)
            assert draw_session_case(4, index, options, 1) == draw_case(4, index, options)


def test_a_session_shares_the_first_photos_light_and_keeps_each_photos_own_draws():
    for index in range(9):
        spec, own = draw_session_case(2, index, RenderOptions(), 3), draw_case(2, index)
        first = index - index % 3
        assert {k: v for k, v in spec.items() if k not in ("lighting", "session", "camera_yaw_deg", "session_lighting")} \
            == {k: v for k, v in own.items() if k != "lighting"}
        assert spec["session"] == f"pbr-s2-session{first:05d}"
        assert spec["session_lighting"] == draw_case(2, first)["lighting"]
        assert spec["camera_yaw_deg"] == session_yaws(2, first, 3)[index - first]
        assert abs(spec["camera_yaw_deg"]) <= 90.0
        if index == first:
            assert spec["camera_yaw_deg"] == 0.0 and spec["lighting"] == own["lighting"]
    assert len({draw_session_case(2, i, RenderOptions(), 3)["camera_yaw_deg"] for i in range(9)}) == 7


def test_a_turned_camera_sees_the_sessions_sun_and_map_turned_back_by_its_heading():
    """The frames' convention (f2l.estimate.frames): turned by yaw_matrix(yaw), the sun a camera
    turned ``yaw`` right sees is the reference one; its probe rolled by ``yaw`` is the reference's."""
    sky = {"source": "sunsky", "sun_elevation_deg": 30.0, "sun_azimuth_deg": 150.0, "turbidity": 3.0,
           "ground_albedo": 0.2}
    for yaw in (-80.0, 45.0, 70.0):
        seen = turn_lighting(sky, yaw)
        sun = direction_from_angles(math.radians(seen["sun_elevation_deg"]), math.radians(seen["sun_azimuth_deg"]))
        reference = direction_from_angles(math.radians(30.0), math.radians(150.0))
        assert np.allclose(yaw_matrix(math.radians(yaw)) @ sun, reference, atol=1e-6)
    grid = LatLongGrid(8, 16)
    radiance = np.random.default_rng(0).uniform(size=grid.shape + (3,))
    ref = {"source": "bridge", "rotation_deg": 45.0}
    for yaw in (-90.0, 22.5, 67.5):  # whole columns: exact
        turned = rotate_y(radiance, math.radians(turn_lighting(ref, yaw)["rotation_deg"]))
        assert np.allclose(roll_probe(turned, grid, yaw), rotate_y(radiance, math.radians(45.0)))


def test_session_table_and_report(tmp_path):
    from f2l.evaluation.sessions import session_table, write_session_report

    rows = [{"session": "a", "faces": 3, "overcast": False, "single": [20.0, 0.2, 0.1], "joint": [10.0, 0.1, 0.05],
             "single_s": 3.0, "joint_s": 2.0, "left_out": 0},
            {"session": "b", "faces": 2, "overcast": True, "single": [float("nan"), 0.4, 0.3],
             "joint": [float("nan"), 0.2, 0.1], "single_s": 1.0, "joint_s": 1.0, "left_out": 1}]
    table = session_table(rows)
    assert "| 2 (1) | 5 | 20.0 → 10.0 (0.50) | 0.300 → 0.150 (0.50) | 0.2000 → 0.0750 | 1 | 4 → 3 |" in table
    write_session_report(rows, tmp_path)
    assert (tmp_path / "sessions.md").read_text().strip() == table
    assert len(json.loads((tmp_path / "sessions.json").read_text())) == 2


def test_tiny_session_render_writes_each_photos_truth_in_its_own_frame(tmp_path):
    pytest.importorskip("mitsuba")
    pytest.importorskip("anny")
    from f2l.io.exr import read_exr
    from f2l.render.dataset import PROBE_GRID, render_faces

    options = RenderOptions(image_px=48, spp=2, max_depth=2, sunsky_fraction=1.0)
    summary = render_faces(tmp_path, 2, seed=7, options=options, session_size=2)
    assert summary["ok"] == 2 and summary["session_size"] == 2
    metas = [json.loads((tmp_path / "meta" / f"pbr-s7-{i:05d}.json").read_text()) for i in range(2)]
    assert metas[0]["session"] == metas[1]["session"] and metas[0]["camera_yaw_deg"] == 0.0
    probes = [read_exr(tmp_path / "probes" / f"pbr-s7-{i:05d}.exr") / m["exposure"] for i, m in enumerate(metas)]
    sky = np.clip(probes[0], None, np.percentile(probes[0], 99))  # the sun's disk moves by up to half a column
    back = np.clip(roll_probe(probes[1], PROBE_GRID, metas[1]["camera_yaw_deg"]), None, sky.max())
    assert np.abs(back - sky).mean() < 0.02 * sky.mean()
    assert np.abs(np.clip(probes[1], None, sky.max()) - sky).mean() > 0.05 * sky.mean()


def test_eval_sessions_cli_scores_singles_and_the_turned_session_and_tags_the_records(tmp_path):
    """A render-faces-like session of three photos (the astronaut's fitted face under a clear sky as
    cameras turned 0°, 45° and −30° see it): one row, finite metrics, records tagged for --joint session."""
    import dataclasses

    skdata = pytest.importorskip("skimage.data")
    from PIL import Image
    from typer.testing import CliRunner

    from f2l.cli import app
    from f2l.io.exr import write_exr
    from f2l.io.shards import ShardWriter, iter_records
    from f2l.synth.skies import clear_sky

    render, grid = tmp_path / "render", LatLongGrid(32, 64)
    for sub in ("photos", "meta", "probes"):
        (render / sub).mkdir(parents=True)
    Image.fromarray(skdata.astronaut()).save(render / "photos" / "pbr-s0-00000.jpg", quality=95)
    runner = CliRunner()
    res = runner.invoke(app, ["fit-faces", str(render / "photos"), "--out", str(tmp_path / "fit1"), "--grid", "32x64",
                              "--json"])
    assert res.exit_code == 0, res.output
    (record,) = list(iter_records(tmp_path / "fit1"))
    sky = clear_sky(grid, np.radians(40.0), np.radians(30.0)).astype(np.float32)
    with ShardWriter(tmp_path / "fitted") as writer:
        for i, yaw in enumerate((0.0, 45.0, -30.0)):
            fid = f"pbr-s0-{i:05d}"
            writer.write(dataclasses.replace(record, face_id=f"{fid}-f0",
                                             source_path=str(render / "photos" / f"{fid}.jpg"), meta={}))
            write_exr(render / "probes" / f"{fid}.exr", roll_probe(sky, grid, -yaw))
            sun = direction_from_angles(np.radians(40.0), np.radians(30.0 - yaw))
            (render / "meta" / f"{fid}.json").write_text(json.dumps({
                "face_id": fid, "index": i, "session": "pbr-s0-session00000", "camera_yaw_deg": yaw,
                "lighting": {"source": "sunsky"}, "sky": {"kind": "clear", "sun_direction": sun.tolist()}}))
    res = runner.invoke(app, ["eval", "sessions", str(render), "--fitted", str(tmp_path / "fitted"), "--out",
                              str(tmp_path / "report"), "--tag", str(tmp_path / "tagged")])
    assert res.exit_code == 0, res.output
    (row,) = json.loads((tmp_path / "report" / "sessions.json").read_text())
    assert row["faces"] == 3 and row["yaws_deg"] == [0.0, 45.0, -30.0] and len(row["singles"]) == 3
    assert all(np.isfinite(row["single"])) and all(np.isfinite(row["joint"])) and row["joint_s"] > 0
    assert "| 1 (1) | 3 |" in (tmp_path / "report" / "sessions.md").read_text()
    tagged = list(iter_records(tmp_path / "tagged"))
    assert [(r.meta["session"], r.meta["camera_yaw_deg"]) for r in tagged] == \
        [("pbr-s0-session00000", y) for y in (0.0, 45.0, -30.0)]
