"""A face in an occluder's shadow (issue 42): the board of ``render-faces --shade-one``
(f2l.render.occluder, f2l.render.framing) and ``f2l eval shade`` (f2l.evaluation.shade)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from f2l.render.dataset import RenderOptions
from tests.render_helpers import astronaut_pair_render


def test_the_board_has_its_own_stream_and_leaves_the_case_unchanged():
    from f2l.render.framing import draw_framed_case

    for index in range(10):
        plain = draw_framed_case("group", 11, index)
        shaded = draw_framed_case("group", 11, index, RenderOptions(shade_one=True))
        board = shaded.pop("shade")
        assert shaded == plain and "shade" not in plain
        assert 0 <= board["pick"] < 1 and 50 <= board["distance_cm"] <= 100 and 40 <= board["diameter_cm"] <= 60


def _project(points):
    """A camera 300 cm away on +Z, focal 1000 px, 1200 x 800 px."""
    z = 300.0 - points[:, 2]
    return 600 + 1000 * points[:, 0] / z, 400 - 1000 * points[:, 1] / z, z > 1.0


def test_the_board_goes_toward_the_sun_off_the_others_and_off_the_faces():
    from f2l.render.occluder import place_occluder

    shade = {"pick": 0.0, "distance_cm": 70.0, "diameter_cm": 50.0}
    centres = np.array([[-25.0, 0, 0], [25.0, 0, 0]])
    forwards = np.array([[0, 0, 1.0], [0, 0, 1.0]])
    boxes = []
    for x in (-25.0, 25.0):
        cols, rows, _ = _project(np.array([[x - 7, 6, 0], [x + 7, -12, 0]]))
        boxes.append([cols.min(), rows.min(), cols.max(), rows.max()])
    # sun high on the right, in front: the board above person 1's face; person 0 is clear of its shadow
    sun = np.array([0.3, 0.8, 0.5])
    sun /= np.linalg.norm(sun)
    placed = place_occluder({**shade, "pick": 0.99}, sun, centres, forwards, boxes, _project, (1200, 800))
    assert placed["shaded_person"] == 1
    assert np.allclose(placed["occluder"]["center_cm"], centres[1] + 70.0 * sun, atol=1e-3)
    # the sun straight from the side: each one's board would shade the other
    side = place_occluder(shade, np.array([1.0, 0.1, 0.3]) / np.linalg.norm([1.0, 0.1, 0.3]), centres, forwards,
                          boxes, _project, (1200, 800))
    assert side["shaded_person"] is None and "would be in its shadow" in side["shade_note"]
    # the sun behind the camera: the board would hide the face in the photo
    front = place_occluder(shade, np.array([0.05, 0.3, 1.0]) / np.linalg.norm([0.05, 0.3, 1.0]), centres, forwards,
                           boxes, _project, (1200, 800))
    assert front["shaded_person"] is None and "cover face" in front["shade_note"]
    # the sun behind the people: no face to shade
    back = place_occluder(shade, np.array([0.2, 0.5, -0.8]) / np.linalg.norm([0.2, 0.5, -0.8]), centres, forwards,
                          boxes, _project, (1200, 800))
    assert back["shaded_person"] is None and "does not light" in back["shade_note"]


def _face_means(folder, fid):
    meta = json.loads((folder / "meta" / f"{fid}.json").read_text())
    photo = np.asarray(Image.open(folder / "png" / f"{fid}.png"), np.float64)
    means = []
    for face in meta["faces"]:
        x0, y0, x1, y1 = (int(round(v)) for v in face["box"])
        means.append(photo[max(y0, 0):y1, max(x0, 0):x1].mean())
    return meta, np.array(means)


def test_a_shaded_render_darkens_one_face_and_a_case_without_a_board_is_the_plain_render(tmp_path):
    pytest.importorskip("mitsuba")
    pytest.importorskip("anny")
    from f2l.render.framing import render_framed

    plain, shaded = RenderOptions(image_px=160, spp=2), RenderOptions(image_px=160, spp=2, shade_one=True)
    for index in (96, 0):  # seed 11: case 96 (2 people, sky model) gets a board; case 0's sun lights no face
        for name, options in (("plain", plain), ("shaded", shaded)):
            summary = render_framed(tmp_path / name, "group", 1, seed=11, options=options, start=index, progress=False)
            assert summary["ok"] == 1, summary
    fid = "pbr-group-s11-00096"
    meta, dark = _face_means(tmp_path / "shaded", fid)
    _, lit = _face_means(tmp_path / "plain", fid)
    k = meta["shaded_person"]
    assert k is not None and meta["occluder"]["radius_cm"] > 0 and meta["sky"]["kind"] == "clear"
    other = 1 - k
    assert dark[k] / dark[other] < 0.8 * lit[k] / lit[other]  # the shaded face darker against the other
    fid = "pbr-group-s11-00000"
    meta = json.loads((tmp_path / "shaded" / "meta" / f"{fid}.json").read_text())
    assert meta["shaded_person"] is None and "does not light" in meta["shade_note"]
    assert (tmp_path / "shaded" / "png" / f"{fid}.png").read_bytes() == (tmp_path / "plain" / "png" / f"{fid}.png").read_bytes()
    assert "shaded_person" not in json.loads((tmp_path / "plain" / "meta" / f"{fid}.json").read_text())


def test_eval_shade_scores_the_three_joint_estimates(tmp_path):
    """A render-faces-like folder: the astronaut twice (mirrored), the second face marked shaded;
    fit-faces, then ``f2l eval shade``: each variant scored, the flag read, the tables written."""
    from typer.testing import CliRunner

    from f2l.cli import app

    render, fitted = astronaut_pair_render(tmp_path, shaded_person=1)
    runner = CliRunner()
    res = runner.invoke(app, ["eval", "shade", str(render), "--fitted", str(fitted),
                              "--out", str(tmp_path / "report")])
    assert res.exit_code == 0, res.output
    (row,) = json.loads((tmp_path / "report" / "shade.json").read_text())
    assert row["shaded_fitted"] and sorted(row["persons"]) == [0, 1] and isinstance(row["flagged"], bool)
    assert row["check on"]["used"][row["shaded_index"]] is not row["flagged"]
    assert len(row["without"]["used"]) == 1 and row["check off"]["used"] == [True, True]
    for variant in ("check on", "without", "check off"):
        assert all(np.isfinite(row[variant]["metrics"])) and row[variant]["s"] > 0
    table = (tmp_path / "report" / "shade.md").read_text()
    assert "| 1 | 1 |" in table and "(b) without the shaded face" in table and "pbr-group-s0-00001" in table
