"""Faces at every scale and position (f2l.face.detector): the window plan's coverage, the merge,
and real photographs framed as people frame them.

The photos are scikit-image's (BSD-3; ``astronaut`` is a NASA portrait, public domain; ``coffee``,
``chelsea``, ``rocket``, ``stereo_motorcycle``, ``hubble_deep_field`` hold no face), composited
into wide, two-person and group framings. The astronaut's detected face box at 512 px is about
(172, 67)–(279, 175): 92–108 px wide.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from f2l.face.detector import FULL_RANGE, LEVEL_OVERLAP, SHORT_RANGE, iou, merge_detections, tile_plan

skdata = pytest.importorskip("skimage.data")

ASTRONAUT_FACE = np.array([172.0, 67.0, 279.0, 175.0])  # x0, y0, x1, y1 at 512 px


# --- the window plan ----------------------------------------------------------------------------

@pytest.mark.parametrize("spec", [FULL_RANGE, SHORT_RANGE], ids=lambda s: s.name)
@pytest.mark.parametrize("shape,min_face", [((3000, 4000), 40.0), ((512, 512), 40.0), ((886, 1280), 24.0),
                                            ((8660, 5773), 40.0), ((100, 3000), 40.0), ((64, 64), 16.0)])
def test_every_face_lies_whole_in_a_window_where_the_model_sees_it(spec, shape, min_face):
    """A square face of any width from min_face_px to the long side, anywhere in the photo, lies
    wholly inside some window of a level whose scale puts its width inside the model's band."""
    h, w = shape
    n = spec.input_size
    lo, hi = spec.band_px
    levels = tile_plan(h, w, spec, min_face)
    assert levels[0].face_px[0] == pytest.approx(min_face)
    assert levels[-1].face_px[1] >= max(h, w)
    for a, b in zip(levels, levels[1:]):  # the levels' face bands overlap by LEVEL_OVERLAP
        assert b.face_px[0] == pytest.approx(a.face_px[1] / LEVEL_OVERLAP) and b.face_px[0] < a.face_px[1]
    rng = np.random.default_rng(0)
    for _ in range(400):
        f = float(np.exp(rng.uniform(np.log(min_face), np.log(min(h, w)))))
        x, y = rng.uniform(0, w - f), rng.uniform(0, h - f)
        ok = False
        for lv in levels:
            if not lv.face_px[0] <= f <= lv.face_px[1]:
                continue
            s = lv.scale
            assert lo - 1e-6 <= f * s <= hi + 1e-6
            bx0, by0, bx1, by1 = x * s, y * s, (x + f) * s, (y + f) * s
            ok |= any(ox - 1 <= bx0 and bx1 <= ox + n + 1 and oy - 1 <= by0 and by1 <= oy + n + 1
                      for ox, oy in lv.origins)
        assert ok, (f, x, y)


def test_the_plan_costs_what_the_area_over_the_smallest_face_says():
    """12 MP at 40 px: the finest level dominates; ~140 full-range windows (measured 0.6-0.7 s)."""
    levels = tile_plan(3000, 4000, FULL_RANGE, 40.0)
    windows = sum(len(lv.origins) for lv in levels)
    assert 100 <= windows <= 200, windows
    assert len(tile_plan(3000, 4000, FULL_RANGE, 80.0)[0].origins) < len(levels[0].origins) / 3


def test_merge_joins_overlaps_and_swallows_boxes_inside_better_ones():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [2, 2, 6, 6], [50, 50, 60, 60]], float)
    kps = np.zeros((4, 6, 2))
    kps[1] += 2.0
    dets = merge_detections(boxes, kps, np.array([0.9, 0.9, 0.8, 0.7]))
    assert len(dets) == 2
    np.testing.assert_allclose(dets[0].box, [0.5, 0.5, 10.5, 10.5])  # the two overlapping, weighted by score
    assert dets[0].score == pytest.approx(0.9) and dets[1].score == pytest.approx(0.7)
    np.testing.assert_allclose(dets[1].box, [50, 50, 60, 60])


# --- real photographs -----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def landmarker():
    from f2l.face.landmarker import FaceLandmarker

    return FaceLandmarker()


@pytest.fixture(scope="module")
def astronaut():
    return skdata.astronaut()


def _paste(canvas: np.ndarray, photo: np.ndarray, face_px: float, x: int, y: int, *, flip: bool = False,
           gain: float = 1.0, face_box: np.ndarray = ASTRONAUT_FACE,
           region: tuple[int, int, int, int] = (100, 10, 350, 330)) -> np.ndarray:
    """Paste a person's head and shoulders (``region`` of ``photo``, around its face ``face_box``; by
    default the astronaut's), scaled so the face is ``face_px`` wide, with its top-left corner at
    (x, y); returns the face's box in the canvas."""
    x0, y0, x1, y1 = region
    crop = photo[y0:y1, x0:x1]
    face = face_box - [x0, y0, x0, y0]
    if flip:
        crop = crop[:, ::-1]
        face = np.array([crop.shape[1] - face[2], face[1], crop.shape[1] - face[0], face[3]])
    s = face_px / (face[2] - face[0])
    size = (round(crop.shape[1] * s), round(crop.shape[0] * s))
    im = np.asarray(Image.fromarray(np.ascontiguousarray(crop)).resize(size, Image.Resampling.LANCZOS))
    canvas[y:y + size[1], x:x + size[0]] = np.clip(im * gain, 0, 255).astype(np.uint8)
    sx, sy = size[0] / crop.shape[1], size[1] / crop.shape[0]
    return face * np.array([sx, sy, sx, sy]) + np.array([x, y, x, y])


def _found(landmarker, image, truths):
    faces = landmarker(image)
    boxes = np.array([f.detection.box for f in faces]).reshape(-1, 4)
    matched = [int(np.argmax(iou(t, boxes))) for t in truths if len(boxes) and iou(t, boxes).max() > 0.5]
    return faces, matched


@pytest.mark.parametrize("size", [(900, 900), (676, 1024), (2400, 3600)])
def test_the_astronaut_framed_wide_is_found(landmarker, astronaut, size):
    """The photo f2l used to lose: the same portrait on a wider canvas (the face 26% down to 3% of
    the long side)."""
    canvas = np.full((*size, 3), 96, np.uint8)
    canvas[60:572, 80:592] = astronaut
    faces = landmarker(canvas)
    assert len(faces) == 1
    assert iou(ASTRONAUT_FACE + [80, 60, 80, 60], faces[0].detection.box[None])[0] > 0.6


def test_two_people_side_by_side_are_two_faces(landmarker, astronaut):
    two = np.ascontiguousarray(np.concatenate([astronaut, astronaut[:, ::-1]], axis=1))
    faces = landmarker(two)
    assert len(faces) == 2
    xs = sorted(float(f.detection.box[0]) for f in faces)
    assert xs[0] < 512 <= xs[1]


@pytest.fixture(scope="module")
def group_photo(astronaut):
    """Seven people on a real background (coffee, 1800 x 1200), faces 44-200 px wide, some mirrored,
    some darker or brighter: a group photo's sizes and light."""
    canvas = np.array(Image.fromarray(skdata.coffee()).resize((1800, 1200)))
    placements = [(44, 60, 80, False, 1.0), (52, 300, 90, True, 0.7), (70, 560, 60, False, 1.2),
                  (96, 900, 120, True, 0.9), (130, 1250, 80, False, 0.6), (180, 80, 560, True, 1.0),
                  (200, 1100, 480, False, 1.1)]
    truths = [_paste(canvas, astronaut, f, x, y, flip=flip, gain=g) for f, x, y, flip, g in placements]
    return canvas, truths


def test_a_group_photo_finds_every_face(landmarker, group_photo):
    canvas, truths = group_photo
    faces, matched = _found(landmarker, canvas, truths)
    assert len(matched) == len(truths) == len(set(matched)) == len(faces), [f.detection.box for f in faces]


def fit_faces_of(canvas: np.ndarray, truths, tmp_path, name: str):
    """`f2l fit-faces` on one composite: (status row, refusals, records), after checking that every
    true face is detected once and is a record or a named refusal, and that the overlay exists."""
    import pyarrow.parquet as pq
    from typer.testing import CliRunner

    from f2l.cli import app
    from f2l.io.shards import iter_records

    Image.fromarray(canvas).save(tmp_path / f"{name}.jpg", quality=92)
    res = CliRunner().invoke(app, ["fit-faces", str(tmp_path / f"{name}.jpg"), "--out", str(tmp_path / "out"),
                                   "--grid", "8x16", "--json"])
    assert res.exit_code == 0, res.output
    row = pq.read_table(tmp_path / "out" / "status" / "fit_faces.parquet").to_pylist()[0]
    rejected = json.loads(row["rejected_json"])
    assert row["num_detected"] == len(truths)
    assert len(row["face_ids"]) + len(rejected) == len(truths)
    assert all(r["reason"] and f"{name}.jpg" in r["message"] for r in rejected), rejected
    records = list(iter_records(tmp_path / "out"))
    assert sorted(r.face_id for r in records) == sorted(row["face_ids"])
    assert len({r.face_index for r in records}) == len(records)
    assert (tmp_path / "out" / row["overlay_path"]).is_file()
    return row, rejected, records


def test_a_group_photo_gives_a_record_or_a_reason_per_face(group_photo, tmp_path):
    """`f2l fit-faces` on the group photo: every detected face is a record or a named refusal, and
    one overlay of the whole photo shows them all."""
    canvas, truths = group_photo
    row, _, _ = fit_faces_of(canvas, truths, tmp_path, "group")
    assert len(row["face_ids"]) >= len(truths) - 1


APOLLO11 = Path(__file__).parent / "data" / "real_photos" / "apollo11_crew.jpg"
# The crew's faces (Aldrin, Collins, Armstrong), boxes labelled by hand on the 600 x 471 photo.
APOLLO11_FACES = np.array([[404.0, 180.0, 456.0, 234.0], [263.0, 88.0, 315.0, 141.0], [126.0, 173.0, 178.0, 227.0]])


@pytest.fixture(scope="module")
def apollo11():
    return np.asarray(Image.open(APOLLO11).convert("RGB"))


def test_a_real_group_photo_finds_every_face(landmarker, apollo11):
    """The Apollo 11 crew's portrait (NASA, public domain): three people, faces 54 px wide."""
    faces, matched = _found(landmarker, apollo11, APOLLO11_FACES)
    assert sorted(matched) == [0, 1, 2] and len(faces) == 3, [f.detection.box for f in faces]


@pytest.mark.parametrize("scale", [0.75, 0.7])
def test_a_real_group_photo_framed_wide_and_small_finds_every_face(landmarker, apollo11, scale):
    """The same photo shrunk and placed off-centre on a 2000 x 1600 canvas: faces 37-42 px, 2% of
    the frame's long side (a group shot framed wide)."""
    h, w = apollo11.shape[:2]
    small = np.asarray(Image.fromarray(apollo11).resize((round(w * scale), round(h * scale)),
                                                        Image.Resampling.LANCZOS))
    canvas = np.full((1600, 2000, 3), 40, np.uint8)
    canvas[900:900 + small.shape[0], 1300:1300 + small.shape[1]] = small
    truths = APOLLO11_FACES * scale * small.shape[1] / (w * scale) + [1300, 900, 1300, 900]
    faces, matched = _found(landmarker, canvas, truths)
    assert sorted(matched) == [0, 1, 2] and len(faces) == 3, [f.detection.box for f in faces]


def test_a_real_group_photo_gives_a_record_or_a_reason_per_face(apollo11, tmp_path):
    row, rejected, records = fit_faces_of(apollo11, APOLLO11_FACES, tmp_path, "apollo11_crew")
    assert len(records) == 3 and not rejected


def test_a_real_group_photo_gives_a_light_per_face(tmp_path):
    """`f2l estimate photo.jpg -m sunsky`: the photo's faces share one light, and each face has a row."""
    import pyarrow.parquet as pq
    from typer.testing import CliRunner

    from f2l.cli import app

    res = CliRunner().invoke(app, ["estimate", str(APOLLO11), "-m", "sunsky", "--out", str(tmp_path / "est"),
                                   "--json"])
    assert res.exit_code == 0, res.output
    rows = pq.read_table(tmp_path / "est" / "estimates.parquet").to_pylist()
    assert sorted(r["face_id"].rsplit("-", 1)[1] for r in rows) == ["f0", "f1", "f2"], rows
    assert all(r["status"] == "ok" and np.all(np.isfinite(r["sun_direction"])) for r in rows), rows
    assert all((tmp_path / "est" / r["probe_path"]).is_file() for r in rows)


@pytest.mark.parametrize("name", ["coffee", "chelsea", "rocket", "stereo_motorcycle", "hubble_deep_field"])
@pytest.mark.parametrize("upscale", [1, 3])
def test_photos_without_faces_give_none(landmarker, name, upscale):
    image = getattr(skdata, name)()
    image = image[0] if isinstance(image, tuple) else image
    if upscale != 1:
        image = np.asarray(Image.fromarray(image).resize((image.shape[1] * upscale, image.shape[0] * upscale),
                                                         Image.Resampling.BICUBIC))
    assert landmarker(np.ascontiguousarray(image)) == []


def test_bench_detect_runs_the_real_code_small():
    """`f2l bench-detect` at a tiny size: the recall table, the face-free count and a timing row."""
    from f2l.dev.bench_detect import format_table, run_detect_bench

    r = run_detect_bench(photos=3, negatives=3, sizes_mp=(0.5,), repeats=1, seed=1)
    assert r["true_faces"] >= 3 and r["recall"] == 1.0 and r["extra_detections"] == 0
    assert r["negative_faces"] == 0
    (t,) = r["timing"]
    assert t["windows"] >= 1 and t["detect_s"] > 0 and t["faces"] == t["true_faces"] >= 3
    table = format_table(r)
    assert "| all |" in table and "face-free photos" in table
    assert r["negative_confirmed"] == 0 and "kept by confirmation" in table
