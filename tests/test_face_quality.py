"""The blur index (f2l.face.quality; Crete et al. 2007) and the ``blurred`` refusal."""

from __future__ import annotations

import json

import numpy as np
import pytest

from f2l.face.quality import MAX_BLUR_INDEX, blur_index, central_box


def test_a_sharp_step_keeps_one_ninth():
    """A vertical step edge: the 9-tap box spreads the jump over 9 columns, so 1/9 of the
    neighbour variation survives; rows have no variation and are skipped."""
    step = np.zeros((20, 40))
    step[:, 20:] = 1.0
    assert blur_index(step) == pytest.approx(1 / 9, abs=1e-12)
    assert blur_index(step.T) == pytest.approx(1 / 9, abs=1e-12)


def test_blur_raises_the_index_and_flat_images_are_fully_blurred():
    import cv2

    rng = np.random.default_rng(0)
    texture = rng.random((96, 96))
    sharp = blur_index(texture)
    soft = [blur_index(cv2.GaussianBlur(texture, (0, 0), s)) for s in (1.0, 2.0, 4.0)]
    assert sharp < 0.2 and sharp < soft[0] < soft[1] < soft[2] <= 1.0
    assert blur_index(np.full((16, 16), 0.3)) == 1.0
    with pytest.raises(ValueError, match="2-D"):
        blur_index(np.zeros(5))


def test_central_box_is_clipped_to_the_photo():
    xy = np.array([[-10.0, -10.0], [90.0, 190.0]])
    assert central_box(xy, (100, 50)) == (20, 100, 5, 50)  # centre (40, 90), half-size (35, 70)


@pytest.fixture(scope="module")
def astronaut_faces(tmp_path_factory):
    import cv2
    import skimage.data
    from PIL import Image

    from f2l.face.landmarker import FaceLandmarker

    folder = tmp_path_factory.mktemp("blur")
    img = skimage.data.astronaut()
    landmarker = FaceLandmarker()
    points = landmarker(img)[0].points
    paths = {}
    for name, sigma in (("sharp", 0.0), ("soft", 4.0)):
        im = img if sigma == 0 else cv2.GaussianBlur(img, (0, 0), sigma)
        paths[name] = folder / f"{name}.png"
        Image.fromarray(im).save(paths[name])
    return paths, points


def test_a_blurred_face_scores_above_the_threshold_and_a_sharp_one_below(astronaut_faces):
    from f2l.face.fit import face_width_px
    from f2l.io.photo import load_photo
    from f2l.face.quality import face_blur_index

    paths, points = astronaut_faces
    width = face_width_px(points)
    sharp = face_blur_index(load_photo(paths["sharp"]), points, width)
    soft = face_blur_index(load_photo(paths["soft"]), points, width)
    assert sharp < MAX_BLUR_INDEX - 0.1 < MAX_BLUR_INDEX + 0.1 < soft


def test_fit_faces_refuses_the_blurred_face_and_records_the_sharp_ones_index(astronaut_faces, tmp_path):
    """Through `f2l fit-faces`: the blurred photo's face is refused as ``blurred`` with its index in
    the message; the sharp one is a record whose meta carries its blur index."""
    import pyarrow.parquet as pq
    from typer.testing import CliRunner

    from f2l.cli import app
    from f2l.io.shards import iter_records

    paths, _ = astronaut_faces
    res = CliRunner().invoke(app, ["fit-faces", str(paths["sharp"]), str(paths["soft"]), "--out", str(tmp_path),
                                   "--grid", "8x16", "--json"])
    assert res.exit_code == 0, res.output
    rows = {r["source_path"].split("/")[-1]: r
            for r in pq.read_table(tmp_path / "status" / "fit_faces.parquet").to_pylist()}
    refused = json.loads(rows["soft.png"]["rejected_json"])
    assert [r["reason"] for r in refused] == ["blurred"] and "blur index" in refused[0]["message"]
    assert rows["soft.png"]["face_ids"] == []
    (record,) = list(iter_records(tmp_path))
    assert record.source_path.endswith("sharp.png")
    assert 0.1 < record.meta["blur_index"] < MAX_BLUR_INDEX
