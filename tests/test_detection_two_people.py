"""A group photo of two different real people: every face found, and `fit-faces` gives each one a
record or a reason.

The people are scikit-image's ``astronaut`` (Eileen Collins, a NASA portrait, public domain) and
matplotlib's ``grace_hopper.jpg`` (a US Navy portrait, public domain; matplotlib is a dependency),
composited at five sizes (50-200 px faces), mirrored or not, darker or brighter, on a wide
2000 x 900 frame of scikit-image's ``coffee`` (BSD-3, no face).
"""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from f2l.face.detector import iou
from tests.test_face_detection import _paste, fit_faces_of

skdata = pytest.importorskip("skimage.data")

# (photo, face box (x0, y0, x1, y1) as the shipped detector finds it, head-and-shoulders region)
ASTRONAUT = ("astronaut", np.array([172.0, 67.0, 279.0, 175.0]), (100, 10, 350, 330))
HOPPER = ("grace_hopper", np.array([159.0, 120.0, 365.0, 326.0]), (40, 40, 480, 560))
# (person, face width px, top-left x, y, mirrored, brightness)
PLACEMENTS = ((ASTRONAUT, 200, 60, 180, False, 1.0), (HOPPER, 150, 520, 300, True, 0.8),
              (ASTRONAUT, 90, 900, 120, True, 1.2), (HOPPER, 64, 1250, 380, False, 0.7),
              (ASTRONAUT, 50, 1650, 300, False, 0.9))


def _photo(name: str) -> np.ndarray:
    if name == "astronaut":
        return skdata.astronaut()
    import matplotlib.cbook

    return np.asarray(Image.open(matplotlib.cbook.get_sample_data("grace_hopper.jpg")).convert("RGB"))


@pytest.fixture(scope="module")
def two_people_group():
    canvas = np.array(Image.fromarray(skdata.coffee()).resize((2000, 900)))
    truths = [_paste(canvas, _photo(name), f, x, y, flip=flip, gain=g, face_box=face, region=region)
              for (name, face, region), f, x, y, flip, g in PLACEMENTS]
    return canvas, truths


def test_the_pasted_people_do_not_overlap(two_people_group):
    _, truths = two_people_group
    boxes = np.array(truths)
    for i, t in enumerate(boxes):
        assert iou(t, np.delete(boxes, i, axis=0)).max() == 0.0
    widths = boxes[:, 2] - boxes[:, 0]
    np.testing.assert_allclose(widths, [p[1] for p in PLACEMENTS], rtol=0.02)


def test_every_face_of_two_people_is_found(two_people_group):
    from f2l.face.landmarker import FaceLandmarker

    canvas, truths = two_people_group
    faces = FaceLandmarker()(canvas)
    boxes = np.array([f.detection.box for f in faces]).reshape(-1, 4)
    assert len(faces) == len(truths), boxes
    best = [int(np.argmax(iou(t, boxes))) for t in truths]
    assert sorted(best) == list(range(len(truths)))  # one detection per face, none left over
    assert min(iou(t, boxes).max() for t in truths) > 0.5


def test_fit_faces_gives_each_of_two_people_a_record_or_a_reason(two_people_group, tmp_path):
    canvas, truths = two_people_group
    _, rejected, records = fit_faces_of(canvas, truths, tmp_path, "two_people")
    # the astronaut brightened 1.2x loses half her skin to clipping: refused as such; the others fit
    assert [r["reason"] for r in rejected] == ["clipped"]
    (box,) = [np.array(r["box"]) for r in rejected]
    assert iou(box, np.array(truths)).argmax() == 2
    assert len(records) == 4
