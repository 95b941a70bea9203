"""`f2l render-faces --framing`: several people, framed wide, under one light (f2l.render.framing),
and the detection recall read from such a set (f2l bench-detect --rendered)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from f2l.render.dataset import RenderOptions


def test_framed_draws_are_deterministic_and_within_their_ranges():
    from f2l.render.framing import FRAMING_DRAWS, draw_framed_case

    for framing, ((lo_n, hi_n), (lo_f, hi_f)) in FRAMING_DRAWS.items():
        for index in range(20):
            spec = draw_framed_case(framing, 3, index)
            assert spec == draw_framed_case(framing, 3, index)
            assert lo_n <= len(spec["persons"]) <= hi_n and lo_f <= spec["camera"]["head_width_fraction"] <= hi_f
            assert all(abs(p["yaw_deg"]) <= 50 for p in spec["persons"])
            xs = [p["x_cm"] for p in spec["persons"]]
            assert all(b - a >= 34.0 - 1e-6 for a, b in zip(xs, xs[1:]))  # shoulder to shoulder, no overlap
    # the same case index shares the portrait set's light (its lighting stream)
    from f2l.render.dataset import draw_case

    assert draw_framed_case("group", 3, 5)["lighting"] == draw_case(3, 5)["lighting"]
    with pytest.raises(ValueError, match="framing must be one of"):
        draw_framed_case("panorama", 0, 0)


def test_a_group_photo_renders_with_every_face_box_and_one_light(tmp_path):
    pytest.importorskip("mitsuba")
    pytest.importorskip("anny")
    from f2l.render.framing import render_framed

    options = RenderOptions(image_px=192, spp=2)
    summary = render_framed(tmp_path, "group", 1, seed=4, options=options, progress=False)
    assert summary["ok"] == 1, summary
    fid = "pbr-group-s4-00000"
    meta = json.loads((tmp_path / "meta" / f"{fid}.json").read_text())
    w, h = meta["image_size"]
    assert max(w, h) == 192 and len(meta["faces"]) == len(meta["persons"]) >= 2
    photo = np.asarray(Image.open(tmp_path / "photos" / f"{fid}.jpg"))
    assert photo.shape == (h, w, 3)
    centres = []
    for face in meta["faces"]:
        x0, y0, x1, y1 = face["box"]
        assert x1 > x0 and y1 > y0 and face["width_px"] == pytest.approx(x1 - x0, abs=0.02)
        centres.append((x0 + x1) / 2)
    assert centres == sorted(centres)  # people left to right as drawn
    truth = np.load(tmp_path / "truth" / f"{fid}.npz")
    assert sorted(set(truth["person"].tolist())) == list(range(len(meta["persons"])))
    assert (tmp_path / "probes" / f"{fid}.exr").is_file()
    again = render_framed(tmp_path, "group", 1, seed=4, options=options, progress=False)
    assert again["skipped_existing"] == 1 and again["ok"] == 0


def test_rendered_recall_reads_the_true_boxes(tmp_path):
    """bench-detect --rendered on a folder laid out as render-faces writes it: two astronauts, one
    too narrow to count."""
    skdata = pytest.importorskip("skimage.data")
    from f2l.dev.bench_detect import ASTRONAUT_FACE, format_rendered, rendered_recall

    a = skdata.astronaut()
    canvas = np.full((600, 1400, 3), 90, np.uint8)
    canvas[40:552, 60:572] = a
    small = np.asarray(Image.fromarray(a).resize((128, 128)))
    canvas[300:428, 900:1028] = small
    (tmp_path / "photos").mkdir()
    (tmp_path / "meta").mkdir()
    Image.fromarray(canvas).save(tmp_path / "photos" / "case.jpg", quality=95)
    big = (ASTRONAUT_FACE + [60, 40, 60, 40]).tolist()
    tiny = (ASTRONAUT_FACE / 4 + [900, 300, 900, 300]).tolist()
    faces = [{"box": big, "width_px": big[2] - big[0], "in_frame": True, "pose": {"yaw_deg": 0.0}},
             {"box": tiny, "width_px": tiny[2] - tiny[0], "in_frame": True, "pose": {"yaw_deg": 0.0}}]
    (tmp_path / "meta" / "case.json").write_text(json.dumps({"framing": "group", "faces": faces}))
    r = rendered_recall([tmp_path])
    assert r["true_faces"] == 1 and r["found"] == 1 and r["not_counted"] == 1 and r["recall"] == 1.0
    assert r["framings"] == {"group": {"found": 1, "faces": 1}}
    assert "| all | 1 / 1 |" in format_rendered(r)


def test_accuracy_by_face_width_joins_truth_records_and_estimates(tmp_path):
    """A render-faces-like folder (two astronauts, one 107 px and one 27 px wide, a true probe with a
    sun): fit-faces, estimate (sh9), then the per-band table: the wide face found, fitted, scored;
    the narrow one below the table's 40 px and not counted."""
    skdata = pytest.importorskip("skimage.data")
    from typer.testing import CliRunner

    from f2l.cli import app
    from f2l.dev.bench_detect import ASTRONAUT_FACE
    from f2l.io.exr import write_exr
    from f2l.lighting.grid import LatLongGrid, direction_from_angles
    from f2l.evaluation.face_width import accuracy_by_face_width
    from f2l.synth.skies import clear_sky

    render = tmp_path / "render"
    for sub in ("photos", "meta", "probes"):
        (render / sub).mkdir(parents=True)
    a = skdata.astronaut()
    canvas = np.full((600, 1400, 3), 90, np.uint8)
    canvas[40:552, 60:572] = a
    canvas[300:428, 900:1028] = np.asarray(Image.fromarray(a).resize((128, 128)))
    Image.fromarray(canvas).save(render / "photos" / "case.jpg", quality=95)
    grid = LatLongGrid(16, 32)
    sun = direction_from_angles(np.radians(40.0), np.radians(30.0))
    write_exr(render / "probes" / "case.exr", clear_sky(grid, np.radians(40.0), np.radians(30.0)).astype(np.float32))
    big = (ASTRONAUT_FACE + [60, 40, 60, 40]).tolist()
    tiny = (ASTRONAUT_FACE / 4 + [900, 300, 900, 300]).tolist()
    faces = [{"box": b, "width_px": b[2] - b[0], "in_frame": True, "pose": {"yaw_deg": 0.0}} for b in (big, tiny)]
    (render / "meta" / "case.json").write_text(json.dumps({
        "face_id": "case", "framing": "group", "faces": faces,
        "sky": {"kind": "clear", "sun_direction": [float(v) for v in sun]}}))
    runner = CliRunner()
    res = runner.invoke(app, ["fit-faces", str(render / "photos"), "--out", str(tmp_path / "fitted"), "--grid", "16x32",
                              "--json"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["estimate", str(tmp_path / "fitted"), "-m", "sh9", "--out", str(tmp_path / "est"), "--json"])
    assert res.exit_code == 0, res.output
    result = accuracy_by_face_width([render], tmp_path / "fitted", tmp_path / "est")
    (row,) = result["rows"]
    assert row["band"] == "80-160" and row["found"] and row["fitted"] and row["case"] == "case"
    metrics = row["estimates"]["sh9"]
    assert np.isfinite(metrics["MAE (s)"]) and 0 <= metrics["Sun-ang (°)"] <= 180
    assert "| 80-160 | 1 | 1 | 1 | 1 |" in result["table"] and "| all | 1 |" in result["table"]
    res = runner.invoke(app, ["eval", "framings", str(render), "--fitted", str(tmp_path / "fitted"), "--est",
                              str(tmp_path / "est"), "--out", str(tmp_path / "report")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "report" / "accuracy_by_face_width.md").read_text().strip() == result["table"]
