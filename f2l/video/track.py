"""Faces followed through a clip: detect on keyframes, track the landmarks in between.

:class:`FaceTracker` keeps one track per person and, per frame (:meth:`FaceTracker.update`):

1. **follows** each visible face from its previous landmarks, as MediaPipe's face-mesh tracking
   does: one landmark inference (:meth:`FaceLandmarker._run_landmarks`) on the ROI made from the
   last frame's landmarks (:func:`f2l.face.landmarker._roi_from_landmarks`: eyes level, the
   landmark box ×1.5), its centre moved on by the face's last step (constant velocity). The
   face is kept while the model's face presence stays ≥ ``min_presence``;
2. **detects** (the tiled BlazeFace detector over the whole frame) on keyframes: the first
   frame, every ``keyframe_every`` frames, the frame a track is lost on, and every
   ``search_every`` frames while a person is missing (up to ``max_gap_s``). A detection that
   overlaps a followed face is that face; any other gets the still-image landmarks
   (:meth:`FaceLandmarker.landmarks`, which must pass the landmarker's stricter
   ``min_presence``) and is matched to a missing person that left from where it is (centre within
   ``reid_radius`` face widths of where it was last seen, width within ×``reid_scale``, gone no
   longer than ``max_gap_s``), or becomes a new person;
3. **looks again** where each missing person was last seen (one landmark inference on its last
   ROI): a face uncovered in place comes back before the next keyframe.

Every known person (every person seen so far) has one :class:`TrackedFace` row per frame, with
``status`` and a human ``reason``:

* ``"ok"`` — landmarks, usable;
* ``"too_small"`` — landmarks, narrower than ``min_face_px`` (:func:`f2l.face.fit.face_width_px`);
* ``"cut_off"`` — landmarks, more than ``max_outside_fraction`` of them outside the frame;
* ``"turned"`` — landmarks, |yaw| > ``max_yaw_deg``;
* ``"covered"`` — no face where it was last seen well inside the frame (presence low), for up
  to ``max_gap_s``;
* ``"lost"`` — not found: it left the frame (its last landmarks touched the edge), or it has
  been missing longer than ``max_gap_s``.

Rows without landmarks carry ``landmarks=None`` and the last box seen. Pose: ``yaw_deg`` and
``pitch_deg`` of the head relative to its line of sight, from a similarity (Umeyama) fit of the
landmarks (x, −y, −z) to MediaPipe's canonical mesh (:func:`f2l.face.geometry.similarity_fit`,
:func:`~f2l.face.geometry.pose_angles_deg`; yaw > 0: the head turned toward the camera's
right). It costs ~0.1 ms; ``geometry.reconstruct_vertices``' perspective fit ("rigid") costs
~25 ms and needs the focal length, so it is left to the head fit. Relative to the line of
sight is what decides self-occlusion; the perspective pose differs from it by the direction of
the face from the optical axis (a few degrees).

:func:`track_clip` decodes a clip (:func:`f2l.video.decode.read_frames`) and yields a
:class:`TrackedFrame` (index, time, the RGB frame, its rows) per frame.

Coordinates: photo pixels of the upright frame (x right, y down, pixel centres at +0.5);
landmarks (478, 3) as the landmarker's (z in the same pixel scale, smaller = nearer).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from f2l.face.detector import iou
from f2l.face import fit
from f2l.face.geometry import NUM_MESH_LANDMARKS, pose_angles_deg, similarity_fit
from f2l.face.landmarker import _roi_from_landmarks

STATUSES = ("ok", "lost", "covered", "turned", "cut_off", "too_small")
# a detection whose box overlaps a followed face's landmark box this much is that face
SAME_FACE_IOU = 0.3


@dataclass(frozen=True)
class TrackedFace:
    """One person in one frame. ``landmarks`` (478, 3) photo px or None when not found;
    ``presence`` the landmark model's face presence (0 when nothing was looked at); ``box``
    (x0, y0, x1, y1) of the landmarks, or of the last ones seen; ``yaw_deg``/``pitch_deg`` NaN
    without landmarks; ``keyframe`` whether the detector ran on this frame."""

    frame_index: int
    time_s: float
    person: int
    landmarks: np.ndarray | None
    presence: float
    box: tuple[float, float, float, float]
    yaw_deg: float
    pitch_deg: float
    status: str
    reason: str
    keyframe: bool = False

    @property
    def usable(self) -> bool:
        return self.status == "ok"


@dataclass(frozen=True)
class TrackedFrame:
    """One decoded frame (``image`` (H, W, 3) uint8 RGB, upright) and its rows, person order."""

    index: int
    time_s: float
    image: np.ndarray
    faces: list[TrackedFace]


@dataclass
class _Track:
    person: int
    points: np.ndarray | None  # the last landmarks seen (photo px)
    box: np.ndarray  # the last landmark box seen
    roi: tuple | None  # the ROI the next frame is looked at through
    last_seen: int  # frame index
    last_seen_s: float
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))
    visible: bool = True
    left_frame: bool = False  # its last landmarks touched the frame's edge


def landmark_box(points: np.ndarray) -> np.ndarray:
    """(x0, y0, x1, y1) of the 468 mesh landmarks, an array."""
    return np.array(fit.landmark_box(points))


def head_pose_deg(points: np.ndarray, canonical_cm: np.ndarray) -> tuple[float, float]:
    """(yaw, pitch) in degrees of landmarks (478, 3) relative to their line of sight: the
    rotation of the similarity fit of (x, −y, −z) to the canonical mesh (R = R_y(yaw)
    R_x(pitch) R_z(roll), :func:`f2l.face.geometry.pose_angles_deg`)."""
    lm = np.asarray(points, np.float64)[:NUM_MESH_LANDMARKS]
    shape = np.stack([lm[:, 0], -lm[:, 1], -lm[:, 2]], axis=1)
    _, rot, _ = similarity_fit(np.asarray(canonical_cm, np.float64), shape)
    yaw, pitch, _ = pose_angles_deg(rot)
    return yaw, pitch


def _outside_fraction(points: np.ndarray, hw: tuple[int, int]) -> float:
    return fit._outside_fraction(points[:NUM_MESH_LANDMARKS, :2], hw)


def _centre(box: np.ndarray) -> np.ndarray:
    return np.array([(box[0] + box[2]) / 2, (box[1] + box[3]) / 2])


def _width(box: np.ndarray) -> float:
    return float(max(box[2] - box[0], box[3] - box[1]))


class FaceTracker:
    """Follow the faces of successive frames of one clip (see the module docstring).

    ``landmarker``: a :class:`f2l.face.landmarker.FaceLandmarker`. ``keyframe_every``: frames
    between regular detections; ``search_every``: frames between detections while a person is
    missing; ``min_presence``: the face presence a followed face must keep; ``max_gap_s``: how
    long a missing person may be re-identified where it was last seen; ``max_faces``: the most
    people followed at once (0: no limit); ``predict_motion``: move each ROI on by the face's
    last step (off: MediaPipe's ROI from the last landmarks as it is).
    """

    def __init__(self, landmarker, *, min_face_px: float = 40.0, keyframe_every: int = 30,
                 search_every: int = 5, max_yaw_deg: float = 50.0, min_presence: float = 0.5,
                 max_outside_fraction: float = 0.02, max_gap_s: float = 2.0, reid_radius: float = 1.0,
                 reid_scale: float = 2.0, max_faces: int = 0, predict_motion: bool = True) -> None:
        from f2l.face.mesh import canonical_face_mesh

        if keyframe_every < 1 or search_every < 1:
            raise ValueError(f"keyframe_every and search_every must be >= 1, got {keyframe_every}, {search_every}")
        self.landmarker = landmarker
        self.min_face_px = float(min_face_px)
        self.keyframe_every = int(keyframe_every)
        self.search_every = int(search_every)
        self.max_yaw_deg = float(max_yaw_deg)
        self.min_presence = float(min_presence)
        self.max_outside_fraction = float(max_outside_fraction)
        self.max_gap_s = float(max_gap_s)
        self.reid_radius = float(reid_radius)
        self.reid_scale = float(reid_scale)
        self.max_faces = int(max_faces)
        self.predict_motion = bool(predict_motion)
        self._canonical = np.asarray(canonical_face_mesh()[0], np.float64)
        self._tracks: list[_Track] = []
        self._next_person = 0
        self._last_keyframe: int | None = None
        self.keyframes = 0  # frames the detector ran on
        self.inferences = 0  # landmark model runs while following (keyframes not counted)

    # -- one frame ---------------------------------------------------------------------------
    def update(self, rgb: np.ndarray, index: int, time_s: float) -> list[TrackedFace]:
        """Rows for every known person in this frame (person order)."""
        from f2l.face.landmarker import _check_image

        image = _check_image(rgb)
        hw = image.shape[:2]
        presence: dict[int, float] = {}
        lost_now = False
        for track in self._tracks:
            if track.visible:
                points, p = self._follow(image, track.roi, track.velocity if self.predict_motion else np.zeros(2))
                presence[track.person] = p
                if p >= self.min_presence:
                    self._see(track, points, index, time_s, hw)
                else:
                    track.visible = False
                    lost_now = True
            elif track.roi is not None and time_s - track.last_seen_s <= self.max_gap_s:
                # where it was last seen: a face uncovered in place comes back at once
                points, p = self._follow(image, track.roi, np.zeros(2))
                presence[track.person] = p
                if p >= self.landmarker.min_presence and not self._overlaps_visible(landmark_box(points)):
                    self._see(track, points, index, time_s, hw)
        self._merge_duplicates()
        keyframe = self._is_keyframe(index, time_s, lost_now)
        if keyframe:
            self._detect(image, index, time_s, hw, presence)
        return [self._row(track, index, time_s, hw, presence.get(track.person, 0.0), keyframe)
                for track in self._tracks]

    def _follow(self, image: np.ndarray, roi, velocity: np.ndarray):
        cx, cy, size, rotation = roi
        self.inferences += 1
        return self.landmarker._run_landmarks(image, (cx + velocity[0], cy + velocity[1], size, rotation))

    def _see(self, track: _Track, points: np.ndarray, index: int, time_s: float, hw) -> None:
        box = landmark_box(points)
        if track.visible and track.points is not None and index > track.last_seen:
            step = (_centre(box) - _centre(track.box)) / (index - track.last_seen)
            track.velocity = step
        else:
            track.velocity = np.zeros(2)
        track.points, track.box, track.roi = points, box, _roi_from_landmarks(points)
        track.last_seen, track.last_seen_s, track.visible = index, time_s, True
        track.left_frame = _outside_fraction(points, hw) > 0 or not _inside(box, hw)

    def _overlaps_visible(self, box: np.ndarray) -> bool:
        boxes = [t.box for t in self._tracks if t.visible]
        return bool(boxes) and bool((iou(box, np.array(boxes)) > SAME_FACE_IOU).any())

    def _merge_duplicates(self) -> None:
        """Two followed faces that converged on one face: the older person keeps it."""
        visible = [t for t in self._tracks if t.visible]
        for i, a in enumerate(visible):
            for b in visible[i + 1:]:
                if a.visible and b.visible and iou(a.box, b.box[None])[0] > 0.5:
                    b.visible, b.roi = False, None

    def _is_keyframe(self, index: int, time_s: float, lost_now: bool) -> bool:
        if self._last_keyframe is None or lost_now or index - self._last_keyframe >= self.keyframe_every:
            return True
        # searched for more often only while a missing person can still be re-identified
        missing = any(not t.visible and time_s - t.last_seen_s <= self.max_gap_s for t in self._tracks)
        return missing and index - self._last_keyframe >= self.search_every

    def _detect(self, image: np.ndarray, index: int, time_s: float, hw, presence: dict) -> None:
        self._last_keyframe = index
        self.keyframes += 1
        for det in self.landmarker.detect(image, min_face_px=self.min_face_px):
            if self._overlaps_visible(np.asarray(det.box, np.float64)):
                continue
            if self.max_faces and sum(t.visible for t in self._tracks) >= self.max_faces:
                break
            found = self.landmarker.landmarks(image, det)
            if found.presence < self.landmarker.min_presence:
                continue
            box = landmark_box(found.points)
            if self._overlaps_visible(box):
                continue
            track = self._reidentify(box, time_s)
            if track is None:
                track = _Track(person=self._next_person, points=None, box=box, roi=None,
                               last_seen=index, last_seen_s=time_s, visible=False)
                self._next_person += 1
                self._tracks.append(track)
            self._see(track, found.points, index, time_s, hw)
            presence[track.person] = found.presence

    def _reidentify(self, box: np.ndarray, time_s: float) -> _Track | None:
        """The missing person last seen where ``box`` is (nearest centre), or None."""
        best, best_d = None, math.inf
        for track in self._tracks:
            if track.visible or time_s - track.last_seen_s > self.max_gap_s:
                continue
            w = _width(track.box)
            d = float(np.hypot(*(_centre(box) - _centre(track.box))))
            ratio = _width(box) / max(w, 1e-9)
            if d <= self.reid_radius * w and 1 / self.reid_scale <= ratio <= self.reid_scale and d < best_d:
                best, best_d = track, d
        return best

    # -- rows --------------------------------------------------------------------------------
    def _row(self, track: _Track, index: int, time_s: float, hw, presence: float,
             keyframe: bool) -> TrackedFace:
        box = tuple(float(v) for v in track.box)
        common = dict(frame_index=int(index), time_s=float(time_s), person=track.person,
                      presence=float(presence), box=box, keyframe=keyframe)
        if not track.visible or track.last_seen != index:
            gap_s = time_s - track.last_seen_s
            if track.left_frame:
                status, reason = "lost", "left the frame"
            elif gap_s > self.max_gap_s:
                status, reason = "lost", f"not seen for {gap_s:.1f} s"
            else:
                status, reason = "covered", (f"no face where it was last seen (presence {presence:.2f} "
                                             f"< {self.min_presence:.2f})")
            return TrackedFace(landmarks=None, yaw_deg=math.nan, pitch_deg=math.nan, status=status,
                               reason=reason, **common)
        points = track.points
        yaw, pitch = head_pose_deg(points, self._canonical)
        width = fit.face_width_px(points)
        outside = _outside_fraction(points, hw)
        if width < self.min_face_px:
            status, reason = "too_small", f"{width:.0f} px wide < {self.min_face_px:.0f} px"
        elif outside > self.max_outside_fraction:
            status, reason = "cut_off", f"{outside:.0%} of its landmarks lie outside the frame"
        elif abs(yaw) > self.max_yaw_deg:
            status, reason = "turned", f"head yaw {yaw:+.0f}° exceeds ±{self.max_yaw_deg:.0f}°"
        else:
            status, reason = "ok", ""
        return TrackedFace(landmarks=points, yaw_deg=yaw, pitch_deg=pitch, status=status, reason=reason,
                           **common)


def _inside(box: np.ndarray, hw, margin_px: float = 1.0) -> bool:
    h, w = hw
    return bool(box[0] >= margin_px and box[1] >= margin_px and box[2] <= w - margin_px
                and box[3] <= h - margin_px)


def track_clip(path: str | os.PathLike, landmarker=None, *, start: int = 0, stop: int | None = None,
               every: int = 1, on_issue=None, **options) -> Iterator[TrackedFrame]:
    """Decode ``path`` (:func:`f2l.video.decode.read_frames`: ``start``, ``stop``, ``every``,
    ``on_issue``) and follow its faces (:class:`FaceTracker` with ``options``; ``landmarker``
    defaults to a one-thread :class:`~f2l.face.landmarker.FaceLandmarker`). Yields one
    :class:`TrackedFrame` per decoded frame; with ``every`` > 1 the tracker sees only those
    frames (faces move further between them). Raises :class:`f2l.video.decode.VideoError`
    when the clip cannot be read."""
    from f2l.face.landmarker import FaceLandmarker
    from f2l.video.decode import read_frames

    tracker = FaceTracker(landmarker if landmarker is not None else FaceLandmarker(threads=1), **options)
    for index, time_s, rgb in read_frames(path, start=start, stop=stop, every=every, on_issue=on_issue):
        yield TrackedFrame(index=index, time_s=time_s, image=rgb, faces=tracker.update(rgb, index, time_s))
