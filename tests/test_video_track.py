"""Faces tracked through clips (f2l.video.track): identity, landmarks, and each frame's status.

Clips are composited here from real photographs: scikit-image's ``astronaut`` (a NASA portrait,
public domain) and matplotlib's ``grace_hopper.jpg`` (public domain), cropped around the face and
pasted, moving and scaling, onto scikit-image's ``coffee`` (no face) at 480×270, then written
with OpenCV's ``VideoWriter`` (MPEG-4 part 2). The astronaut's face is ~90 px wide at scale 1,
Grace Hopper's ~180 px.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from f2l.video.decode import VideoError
from f2l.video.track import STATUSES, FaceTracker, head_pose_deg, track_clip
from tests.test_video_decode import write_video

skdata = pytest.importorskip("skimage.data")

SIZE = (480, 270)  # w, h


@pytest.fixture(scope="module")
def sprites():
    import matplotlib
    from PIL import Image

    hopper = Path(matplotlib.get_data_path()) / "sample_data" / "grace_hopper.jpg"
    return {"astronaut": skdata.astronaut()[20:240, 130:330],
            "hopper": np.asarray(Image.open(hopper).convert("RGB"))[80:400, 110:420]}


@pytest.fixture(scope="module")
def landmarker():
    from f2l.face.landmarker import FaceLandmarker

    return FaceLandmarker(threads=1)


def compose(frames, size=SIZE):
    """RGB frames from per-frame lists of (sprite, x, y, scale) pastes (top-left corner at x, y,
    clipped by the frame) and ("cover", x0, y0, x1, y1) grey boxes, over ``coffee``."""
    w, h = size
    background = cv2.resize(skdata.coffee(), (w, h), interpolation=cv2.INTER_AREA)
    out = []
    for items in frames:
        img = background.copy()
        for item in items:
            if isinstance(item[0], str):
                _, x0, y0, x1, y1 = item
                img[y0:y1, x0:x1] = 128
                continue
            sprite, x, y, scale = item
            sp = cv2.resize(sprite, (round(sprite.shape[1] * scale), round(sprite.shape[0] * scale)),
                            interpolation=cv2.INTER_AREA)
            x, y = int(round(x)), int(round(y))
            sx0, sy0 = max(0, -x), max(0, -y)
            sx1, sy1 = min(sp.shape[1], w - x), min(sp.shape[0], h - y)
            if sx1 > sx0 and sy1 > sy0:
                img[y + sy0:y + sy1, x + sx0:x + sx1] = sp[sy0:sy1, sx0:sx1]
        out.append(img)
    return out


def rows_by_frame(path, landmarker, **options):
    frames = list(track_clip(path, landmarker, **options))
    return frames, [{f.person: f for f in fr.faces} for fr in frames]


def test_one_face_keeps_one_id_and_the_still_image_landmarks(tmp_path, sprites, landmarker):
    """40 frames of the astronaut moving 6 px/frame right, 1.5 px down and growing 30%: one
    person, "ok" on every frame, landmarks within ~2 px of the still-image landmarker's on the
    same decoded frame, detection on keyframes only."""
    a = sprites["astronaut"]
    clip = write_video(tmp_path / "one.mp4",
                       compose([[(a, 20 + 6 * i, 20 + 1.5 * i, 0.8 + 0.0075 * i)] for i in range(40)]))
    tracker_frames = list(track_clip(clip, landmarker, keyframe_every=30))
    assert len(tracker_frames) == 40
    assert all(len(fr.faces) == 1 and fr.faces[0].person == 0 for fr in tracker_frames)
    assert all(fr.faces[0].status == "ok" and fr.faces[0].landmarks.shape == (478, 3) for fr in tracker_frames)
    assert [fr.index for fr in tracker_frames if fr.faces[0].keyframe] == [0, 30]
    errors = []
    for fr in tracker_frames[::3]:
        still = landmarker(fr.image)
        assert len(still) == 1
        errors.append(np.linalg.norm(fr.faces[0].landmarks[:468, :2] - still[0].points[:468, :2], axis=1))
    errors = np.array(errors)
    assert np.median(errors) < 1.5 and np.percentile(errors, 95) < 4.0, (np.median(errors), errors.max())
    # the face moved with the paste: its nose tip 6 px/frame right (times the growing scale)
    nose = np.array([fr.faces[0].landmarks[4, 0] for fr in tracker_frames])
    assert np.median(np.diff(nose)) == pytest.approx(6 + 0.0075 * 100, abs=1.0)
    assert all(abs(fr.faces[0].yaw_deg) < 15 for fr in tracker_frames)
    # every other frame: the tracker sees only those, the face moves twice as far between them
    halves = list(track_clip(clip, landmarker, every=2))
    assert [fr.index for fr in halves] == list(range(0, 40, 2))
    assert all(fr.faces[0].person == 0 and fr.faces[0].status == "ok" for fr in halves)
    np.testing.assert_allclose(halves[-1].faces[0].landmarks, tracker_frames[38].faces[0].landmarks, atol=1.5)


def test_two_people_keep_distinct_ids_while_they_move(tmp_path, sprites, landmarker):
    a, g = sprites["astronaut"], sprites["hopper"]
    frames = [[(a, 10 + 4 * i, 30 + 2 * i, 0.8), (g, 330 - 4 * i, 60 - i, 0.45 + 0.003 * i)] for i in range(30)]
    clip = write_video(tmp_path / "two.mp4", compose(frames))
    _, rows = rows_by_frame(clip, landmarker)
    assert all(len(r) == 2 and all(f.status == "ok" for f in r.values()) for r in rows)
    # the person on the left (the astronaut) is the same id in every frame, and moves right
    left = {min(r.values(), key=lambda f: f.box[0]).person for r in rows}
    right = {max(r.values(), key=lambda f: f.box[0]).person for r in rows}
    assert len(left) == 1 and len(right) == 1 and left != right
    (pa,), (pg,) = left, right
    xs = [rows[i][pa].box[0] for i in range(30)]
    assert xs[-1] - xs[0] == pytest.approx(4 * 29, abs=8)
    xs = [rows[i][pg].box[0] for i in range(30)]
    assert xs[-1] - xs[0] < -80


@pytest.mark.parametrize("comes_back", ["where_it_left", "elsewhere"])
def test_a_face_that_leaves_the_frame_is_lost_then_found(tmp_path, sprites, landmarker, comes_back):
    """The astronaut walks out at the right edge (frames 0-11), stays out (12-21), and comes back:
    at the right edge (the same person) or at the far left (a new person; the first stays lost)."""
    a = sprites["astronaut"]
    xs = [300 + 20 * i for i in range(12)] + [600] * 10 + [440 - 12 * i for i in range(14)]
    if comes_back == "elsewhere":
        xs = xs[:22] + [10 + 2 * i for i in range(14)]
    clip = write_video(tmp_path / "leave.mp4", compose([[(a, x, 40, 0.8)] for x in xs]))
    _, rows = rows_by_frame(clip, landmarker, search_every=3)
    assert rows[0][0].status == "ok"
    statuses = [r[0].status for r in rows]
    assert "cut_off" in statuses[:12]  # half out of the frame before it is gone
    out = [i for i, x in enumerate(xs) if x >= 480]
    assert all(statuses[i] == "lost" and rows[i][0].landmarks is None for i in out)
    assert rows[out[0]][0].reason == "left the frame"
    if comes_back == "where_it_left":
        assert all(len(r) == 1 for r in rows)
        assert statuses[-1] == "ok" and statuses[-4:] == ["ok"] * 4
    else:
        assert all(len(r) == 1 for r in rows[:22])
        assert set(rows[-1]) == {0, 1} and rows[-1][1].status == "ok" and rows[-1][0].status == "lost"
        assert all(r[1].status == "ok" for r in rows if 1 in r)
    # every row's status is one of the documented ones, and landmarks go with the found ones
    assert all(f.status in STATUSES and (f.landmarks is None) == (f.status in ("lost", "covered"))
               for r in rows for f in r.values())


def test_a_covered_face_is_covered_and_the_other_face_is_unaffected(tmp_path, sprites, landmarker):
    """A grey box hides the astronaut over frames 10-19; Grace Hopper, beside her, stays "ok"
    with the same landmarks as in the same clip without the box."""
    a, g = sprites["astronaut"], sprites["hopper"]
    base = [[(a, 40 + 2 * i, 30, 0.8), (g, 290, 60 + i, 0.45)] for i in range(30)]
    covered = [items + ([("cover", 20, 10, 230, 240)] if 10 <= i < 20 else []) for i, items in enumerate(base)]
    _, plain = rows_by_frame(write_video(tmp_path / "plain.mp4", compose(base)), landmarker)
    covered_clip = write_video(tmp_path / "covered.mp4", compose(covered))
    _, rows = rows_by_frame(covered_clip, landmarker, search_every=3)
    pa = min(rows[0].values(), key=lambda f: f.box[0]).person
    pg = 1 - pa
    assert all(set(r) == {0, 1} for r in rows)
    for i, r in enumerate(rows):
        if 10 <= i < 20:
            assert r[pa].status in ("covered", "lost") and r[pa].landmarks is None, (i, r[pa])
        else:
            assert r[pa].status == "ok", (i, r[pa])
        assert r[pg].status == "ok"
        np.testing.assert_allclose(r[pg].landmarks[:, :2], plain[i][pg].landmarks[:, :2], atol=1.5)
    assert rows[12][pa].status == "covered" and "last seen" in rows[12][pa].reason
    # it comes back where it was, as the same person
    assert rows[20][pa].status == "ok"
    # hidden longer than max_gap_s (0.2 s = 5 frames): lost after that, and a new person when
    # the next regular keyframe (every 5 frames here) finds the face again
    _, short = rows_by_frame(covered_clip, landmarker, search_every=3, max_gap_s=0.2, keyframe_every=5)
    assert [short[i][pa].status for i in (12, 13, 15, 19)] == ["covered", "covered", "lost", "lost"]
    assert "not seen for" in short[15][pa].reason
    assert set(short[-1]) == {0, 1, 2} and short[-1][2].status == "ok" and short[-1][pa].status == "lost"
    assert 20 <= [i for i, r in enumerate(short) if 2 in r][0] < 25  # the first keyframe after
    assert all(r[pg].status == "ok" for r in short)


def test_head_pose_of_the_canonical_mesh_turned_and_nodded():
    """Yaw and pitch from landmarks: the canonical mesh rotated by known angles and projected
    orthographically (x, −y, −z in px) gives those angles back."""
    from f2l.face.mesh import canonical_face_mesh
    from scipy.spatial.transform import Rotation

    canon = np.asarray(canonical_face_mesh()[0], np.float64)
    for yaw, pitch in [(0, 0), (30, 0), (-55, 10), (20, -25)]:
        rot = Rotation.from_euler("YXZ", [yaw, pitch, 0], degrees=True).as_matrix()
        posed = 8.0 * canon @ rot.T  # 8 px per cm
        points = np.zeros((478, 3))
        points[:468] = np.stack([200 + posed[:, 0], 150 - posed[:, 1], -posed[:, 2]], axis=1)
        got = head_pose_deg(points, canon)
        assert got == pytest.approx((yaw, pitch), abs=1e-6)


def test_status_rules_turned_small_and_cut_off(landmarker):
    """The status of a found face: a turned head, a small face, landmarks outside the frame."""
    from f2l.face.mesh import canonical_face_mesh
    from scipy.spatial.transform import Rotation

    from f2l.video.track import _Track

    canon = np.asarray(canonical_face_mesh()[0], np.float64)
    tracker = FaceTracker(landmarker, min_face_px=40, max_yaw_deg=50)

    def row(yaw, px_per_cm, x):
        posed = px_per_cm * canon @ Rotation.from_euler("Y", yaw, degrees=True).as_matrix().T
        points = np.zeros((478, 3))
        points[:468] = np.stack([x + posed[:, 0], 135 - posed[:, 1], -posed[:, 2]], axis=1)
        points[468:] = points[:10]
        track = _Track(person=0, points=points, box=np.zeros(4), roi=None, last_seen=3, last_seen_s=0.1)
        return tracker._row(track, 3, 0.1, (270, 480), 0.99, False)

    assert row(10, 8, 240).status == "ok"
    turned = row(60, 8, 240)
    assert turned.status == "turned" and turned.yaw_deg == pytest.approx(60) and "yaw" in turned.reason
    assert row(0, 2.5, 240).status == "too_small"  # ~35 px wide
    assert row(0, 8, 470).status == "cut_off"


def test_a_missing_or_non_video_clip_gives_a_clear_error(tmp_path, landmarker):
    with pytest.raises(VideoError, match="no such file") as exc:
        next(track_clip(tmp_path / "nowhere.mp4", landmarker))
    assert "nowhere.mp4" in str(exc.value)
    text = tmp_path / "notes.mp4"
    text.write_text("hello")
    with pytest.raises(VideoError, match="not a readable video") as exc:
        next(track_clip(text, landmarker))
    assert str(text) in str(exc.value)


def test_the_benchmark_runs_on_a_small_clip():
    """``python -m f2l.dev.bench_track`` at 480×270, 20 frames (the face moves 16 px/frame, a
    third of its width): every stage timed, one person found on every frame and followed without
    detection after the first, tracked landmarks on the still-image ones."""
    from f2l.dev.bench_track import run_bench

    r = run_bench(frames=20, size=(480, 270), keyframe_every=30, check_every=5)
    assert (r["ok_rows"], r["rows"], r["people"], r["keyframes"]) == (20, 20, 1, 1)
    assert r["fps"] > 0 and all(r[k]["median"] > 0 for k in ("decode_ms", "follow_ms", "keyframe_ms"))
    assert r["landmark_err_px"]["median"] < 1.5 and 40 < r["face_width_px"] < 80
