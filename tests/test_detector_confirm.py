"""Faces the detector scores just under its threshold, or the landmark model doubts, are kept when
they are confirmed (f2l.face.detector.TiledDetector.support, f2l.face.landmarker.FaceLandmarker.confirmed).

Real photographs: scikit-image's astronaut (a NASA portrait, public domain) pasted on ``coffee``
(BSD-3, no face). At 44 px and 0.35x brightness the full-range model scores her 0.57, under its
0.6 threshold: a candidate, confirmed by its support and two crops of landmark presence >= 0.99.
"""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from f2l.face.detector import FULL_RANGE, LOW_SCORE, SUPPORT_WINDOWS, Detection, TiledDetector, iou
from tests.test_face_detection import _paste

skdata = pytest.importorskip("skimage.data")


@pytest.fixture(scope="module")
def landmarker():
    from f2l.face.landmarker import FaceLandmarker

    return FaceLandmarker()


@pytest.fixture(scope="module")
def dim_and_clear():
    """640 x 480 on coffee: a dim 44 px face (a candidate) and a clear 90 px one (a detection)."""
    canvas = np.array(Image.fromarray(skdata.coffee()).resize((640, 480)))
    astronaut = skdata.astronaut()
    dim = _paste(canvas, astronaut, 44, 200, 150, gain=0.35)
    clear = _paste(canvas, astronaut, 90, 420, 200, flip=True)
    return canvas, dim, clear


def test_a_dim_face_under_the_threshold_is_a_candidate_and_is_confirmed(landmarker, dim_and_clear):
    canvas, dim, clear = dim_and_clear
    detections, candidates = landmarker.tiled.find(canvas)
    assert [iou(clear, d.box[None])[0] > 0.5 for d in detections] == [True]
    (cand,) = [c for c in candidates if iou(dim, c.box[None])[0] > 0.3]
    assert LOW_SCORE <= cand.score < FULL_RANGE.min_score
    assert cand.scale > 0  # the scale of the level that found it: where support looks again
    from f2l.face.landmarker import CONFIRM_PRESENCE, SUPPORT_STRONG, SUPPORT_WEAK

    assert SUPPORT_WEAK <= landmarker.tiled.support(canvas, cand) < SUPPORT_STRONG
    lms = landmarker.confirmed(canvas, cand)
    assert lms is not None and lms.presence >= CONFIRM_PRESENCE
    faces = landmarker(canvas)
    assert len(faces) == 2
    assert iou(clear, faces[0].detection.box[None])[0] > 0.5  # the detection first, as before
    assert iou(dim, faces[1].detection.box[None])[0] > 0.3
    assert faces[0].support is None and SUPPORT_WEAK <= faces[1].support < SUPPORT_STRONG
    # the landmarks lie on the dim face: their box overlaps its true box
    pts = faces[1].points[:, :2]
    assert iou(dim, np.concatenate([pts.min(0), pts.max(0)])[None])[0] > 0.4


def test_candidates_leave_the_detections_as_they_were(landmarker, dim_and_clear):
    """With candidates the detections are those of a search at the threshold alone, bit for bit."""
    canvas, _, _ = dim_and_clear
    without = TiledDetector(landmarker.detector, FULL_RANGE, low_score=FULL_RANGE.min_score)
    before, none = without.find(canvas)
    after, candidates = landmarker.tiled.find(canvas)
    assert none == [] and len(candidates) >= 1
    assert len(before) == len(after) >= 1
    for a, b in zip(before, after):
        assert np.array_equal(a.box, b.box) and np.array_equal(a.keypoints, b.keypoints) and a.score == b.score


def test_a_mirrored_window_maps_its_hits_back(landmarker, dim_and_clear):
    """The mirrored support window finds the clear face where the plain one does, with the subject's
    right eye (keypoint 0) still the right eye."""
    canvas, _, clear = dim_and_clear
    tiled = landmarker.tiled
    (det,) = [d for d in tiled(canvas) if iou(clear, d.box[None])[0] > 0.5]
    cx, cy = (det.box[0] + det.box[2]) / 2, (det.box[1] + det.box[3]) / 2
    found = []
    for mirrored in (False, True):
        boxes, kps, scores = tiled._window_at(canvas, cx, cy, det.scale, mirrored)
        j = int(np.argmax(iou(det.box, boxes)))
        assert iou(det.box, boxes[j:j + 1])[0] > 0.7 and scores[j] > 0.6
        found.append(kps[j])
    plain, mirror = found
    assert np.abs(plain - mirror).max() < 0.12 * det.width
    assert mirror[0, 0] < mirror[1, 0]  # the subject's right eye is on the photo's left


def test_support_is_high_on_a_face_and_nil_off_it(landmarker, dim_and_clear):
    canvas, _, clear = dim_and_clear
    tiled = landmarker.tiled
    (det,) = [d for d in tiled(canvas) if iou(clear, d.box[None])[0] > 0.5]
    assert 0.75 * len(SUPPORT_WINDOWS) <= tiled.support(canvas, det) <= len(SUPPORT_WINDOWS)
    bare = Detection(box=np.array([20.0, 380.0, 70.0, 430.0]), keypoints=np.zeros((6, 2)), score=0.5)
    assert tiled.support(canvas, bare) == 0.0


def test_a_doubted_detection_needs_one_crop_a_candidate_two(landmarker, dim_and_clear):
    """With strong support a detection (score >= the threshold) is kept on its first crop at
    min_presence; the same hit scored as a candidate needs two crops at CONFIRM_PRESENCE."""
    import dataclasses

    from f2l.face.landmarker import CONFIRM_CROPS, CONFIRM_PRESENCE, SUPPORT_STRONG

    canvas, _, clear = dim_and_clear
    (det,) = [d for d in landmarker.tiled(canvas) if iou(clear, d.box[None])[0] > 0.5]
    assert landmarker.tiled.support(canvas, det) >= SUPPORT_STRONG
    presences = [landmarker._crop_landmarks(canvas, det, *crop)[1] for crop in CONFIRM_CROPS[:3]]
    assert presences[0] >= landmarker.min_presence and presences[1] >= CONFIRM_PRESENCE
    first = landmarker._crop_landmarks(canvas, det, *CONFIRM_CROPS[0])[0]
    np.testing.assert_array_equal(landmarker.confirmed(canvas, det).points, first)
    candidate = dataclasses.replace(det, score=0.5)
    np.testing.assert_array_equal(landmarker.confirmed(canvas, candidate).points, first)
    bare = dataclasses.replace(det, box=np.array([20.0, 380.0, 70.0, 430.0]))
    assert landmarker.confirmed(canvas, bare) is None  # no support off the face
