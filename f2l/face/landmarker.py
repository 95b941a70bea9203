"""Offline face detection and 478-point 3D landmarks: MediaPipe's models on LiteRT.

``ai-edge-litert`` runs MediaPipe's TFLite models directly, without the ``mediapipe`` package
(which declares the GUI ``opencv-contrib-python`` and so fights ``opencv-contrib-python-headless``
for ``cv2``):

* detection — BlazeFace *full range* (``f2l/data/face_detection_full_range.tflite``, pinned by
  SHA-256, Apache-2.0): a 192×192 RGB input in [-1, 1], 2,304 anchors, 16 regressors per anchor
  (box centre/size + 6 keypoints: right eye, left eye, nose tip, mouth, right and left tragion,
  "right" meaning the subject's right) in input pixels, and a logit score. It is run over a
  pyramid of windows (:mod:`f2l.face.detector`), so faces from ``min_face_px`` wide to the whole
  frame are found anywhere in the photo, as many as there are. (Until 2026-11-27 the whole photo
  was letterboxed into the bundle's short-range 128×128 detector, which lost every face under
  about a fifth of the long side; ``docs/experiments/face_detection.md`` compares the two.)
* ``face_landmarks_detector.tflite`` of the pinned ``face_landmarker.task`` bundle (see
  :mod:`f2l.face.mesh`) — a 256×256 RGB crop in [0, 1] → 478 (x, y, z) in crop
  pixels (468 face-mesh points + 10 iris points) and a face-presence logit. The crop is the
  square around the detection box scaled ×1.5 and rotated so that the eyes are level; a second
  pass re-crops around the first pass's landmarks (MediaPipe's tracking ROI, rotation from
  landmarks 33 → 263), which tightens the fit. The presence score also vets the detector's hits.
  A hit the landmark model doubts, or one scoring just under the detector's threshold (a
  candidate), is kept only when the detector finds it again around it (its *support*) and more
  crops give a high presence (:meth:`FaceLandmarker.confirmed`).

Landmarks are returned in photo pixels (x right, y down, pixel centres at +0.5) with z in the
same pixel scale, smaller = nearer the camera (MediaPipe's convention).
"""

from __future__ import annotations

import logging
import math
import os
import sys
import zipfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from f2l.face.detector import FULL_RANGE, Detection, TiledDetector, iou

_log = logging.getLogger(__name__)

LANDMARKS_MEMBER = "face_landmarks_detector.tflite"
DETECTOR_FILE = "face_detection_full_range.tflite"
DETECTOR_SHA256 = "99bf9494d84f50acc6617d89873f71bf6635a841ea699c17cb3377f9507cfec3"
DETECTOR_ENV_VAR = "F2L_FACE_DETECTOR"
MIN_FACE_PX = 40.0
# The landmark model's face presence a detection must reach to count as a face. Measured with
# `f2l dev bench-detect`: true faces on real-photo composites >= 0.99999998; on face-free photos the
# detector's hits reach up to 0.87 on the first crop and more with the retried crops, and 0.95
# keeps 200 of them at 0 false faces (docs/experiments/face_detection.md).
MIN_PRESENCE = 0.95
# two detections whose landmark boxes overlap this much are one face (the higher presence kept)
DUPLICATE_IOU = 0.5
LANDMARKS_SIZE = 256
NUM_LANDMARKS = 478
ROI_SCALE = 1.5
# crops tried, in order, while the presence stays under min_presence: (centre, box scale); "nose"
# centres the crop on the detector's nose keypoint, which suits a turned face better than its box
ROI_CROPS = (("box", ROI_SCALE), ("nose", 1.5), ("nose", 1.8), ("box", 1.8))
# A detection whose presence stays under min_presence on ROI_CROPS (doubted), or a candidate (a hit
# scoring under the detector's threshold), is kept when the detector's support for it (0-6, the sum
# of its scores in 6 windows around it; f2l.face.detector.TiledDetector.support) reaches SUPPORT_WEAK
# and two of CONFIRM_CROPS reach CONFIRM_PRESENCE; a doubted detection also when its support reaches
# SUPPORT_STRONG and one crop reaches min_presence. Measured on path-traced groups (seed 0) and 200
# face-free photos: true faces doubted by the landmark model have support 4.2-4.7, face-like
# textures doubted at most 2.9; true candidates 2.4-3.9 with 2-24 crops at 0.99, textures with two
# such crops at most 1.7 (a rocket's gantry: 3.7 with one crop at 0.998, so one crop is not enough).
SUPPORT_STRONG = 3.5
SUPPORT_WEAK = 2.0
CONFIRM_PRESENCE = 0.99
# (centre, box scale, rotation) of the confirming crops: centre "mid" is halfway from the box's centre
# to the nose; rotation "eyes" levels the detector's eye keypoints, "photo" keeps the photo's axes
CONFIRM_CROPS = tuple((centre, scale, rotation) for centre in ("box", "nose", "mid")
                      for scale in (1.3, 1.5, 1.8, 2.2) for rotation in ("eyes", "photo"))
# Eye-corner landmarks that define the tracking ROI's rotation (subject's right -> left).
ROI_ROTATION_LANDMARKS = (33, 263)


class LandmarkerError(RuntimeError):
    """The LiteRT runtime or the landmarker models are unavailable or unreadable."""


@dataclass(frozen=True)
class FaceLandmarks:
    """478 landmarks (478, 3) in photo pixels (z in the same scale, smaller = nearer).

    ``presence`` is the landmark model's face-presence probability on the final crop,
    ``detection`` the detector hit it started from, ``support`` the detector's support (0-6) where
    the face had to be confirmed (:meth:`FaceLandmarker.confirmed`), else None.
    """

    points: np.ndarray
    presence: float
    detection: Detection
    support: float | None = None


# ---------------------------------------------------------------------------------------------
# Model loading
# ---------------------------------------------------------------------------------------------
def _interpreter_class():
    try:
        from ai_edge_litert.interpreter import Interpreter
    except ImportError as exc:  # pragma: no cover - the dependency is declared
        raise LandmarkerError(
            "the LiteRT runtime is missing: install ai-edge-litert (a dependency of f2l)"
        ) from exc
    return Interpreter


def _native_stderr_to_debug_log():
    """Route what native code writes to file descriptor 2 while the block runs (LiteRT prints
    "INFO: Created TensorFlow Lite XNNPACK delegate for CPU." from C++, ignoring
    TF_CPP_MIN_LOG_LEVEL) to this module's logger at DEBUG level (``f2l --debug-log``) instead of
    the terminal. Lines that are not "INFO:" (warnings, errors) and everything written when the
    block raises are also passed on to the terminal."""
    from f2l.io.native_stderr import native_stderr_lines

    def handle(line: str, failed: bool) -> None:
        _log.debug("LiteRT: %s", line.strip())
        if failed or not line.startswith("INFO:"):
            print(line, file=sys.stderr)

    return native_stderr_lines(handle)


def default_detector_path() -> Path:
    """The detector model: ``$F2L_FACE_DETECTOR`` or f2l's packaged copy."""
    from importlib import resources

    env = os.environ.get(DETECTOR_ENV_VAR)
    if env:
        return Path(env)
    return Path(str(resources.files("f2l.data").joinpath(DETECTOR_FILE)))


def _model_bytes(path: Path, check_sha256: bool) -> bytes:
    import hashlib

    try:
        data = path.read_bytes()
    except OSError as exc:
        raise LandmarkerError(f"{path}: cannot read the face detector model: {exc.strerror or exc}") from exc
    if check_sha256:
        digest = hashlib.sha256(data).hexdigest()
        if digest != DETECTOR_SHA256:
            raise LandmarkerError(f"{path}: SHA-256 mismatch (got {digest}, expected {DETECTOR_SHA256}); "
                                  "this is not the pinned BlazeFace full-range model")
    return data


@lru_cache(maxsize=4)
def _interpreters(task_path: str, detector_path: str, check_sha256: bool, threads: int):
    from f2l.face.mesh import canonical_face_mesh

    canonical_face_mesh(task_path, check_sha256=check_sha256)  # verifies the pin
    detector_bytes = _model_bytes(Path(detector_path), check_sha256)
    Interpreter = _interpreter_class()
    out = []
    try:
        with zipfile.ZipFile(task_path) as zf, _native_stderr_to_debug_log():
            for content in (detector_bytes, zf.read(LANDMARKS_MEMBER)):
                it = Interpreter(model_content=content, num_threads=int(threads))
                it.allocate_tensors()
                out.append(it)
    except (zipfile.BadZipFile, KeyError, ValueError, RuntimeError) as exc:
        raise LandmarkerError(f"{task_path}: cannot load the landmarker models: {exc}") from exc
    return tuple(out)


class FaceLandmarker:
    """Detect faces and their 478 landmarks in an 8-bit RGB photo (H, W, 3) uint8.

    ``task_path`` overrides the landmark bundle (default: ``$F2L_FACE_LANDMARKER`` or f2l's
    packaged copy), ``detector_path`` the detector (``$F2L_FACE_DETECTOR`` or the packaged copy);
    their SHA-256 must match the pins unless ``check_sha256=False``.
    """

    def __init__(self, task_path: str | os.PathLike | None = None, *, check_sha256: bool = True,
                 threads: int = 1, min_score: float | None = None, min_presence: float = MIN_PRESENCE,
                 refine_passes: int = 1, detector_path: str | os.PathLike | None = None) -> None:
        from f2l.face.mesh import default_task_path

        path = Path(task_path) if task_path is not None else default_task_path()
        self.task_path = path.resolve()
        det_path = Path(detector_path) if detector_path is not None else default_detector_path()
        self.detector_path = det_path.resolve()
        self.detector, self.landmarks_model = _interpreters(str(self.task_path), str(self.detector_path),
                                                            check_sha256, int(threads))
        self.tiled = TiledDetector(self.detector, FULL_RANGE, min_score=min_score)
        self.min_score = self.tiled.min_score
        self.min_presence = float(min_presence)
        self.refine_passes = int(refine_passes)

    # -- detection ---------------------------------------------------------------------------
    def detect(self, image: np.ndarray, min_face_px: float = MIN_FACE_PX) -> list[Detection]:
        """Detections of faces at least ``min_face_px`` wide (about: the band's slack lets a few
        narrower ones through), anywhere in the photo, highest score first, in photo pixels."""
        return self.tiled(_check_image(image), min_face_px=min_face_px)

    # -- landmarks ---------------------------------------------------------------------------
    def landmarks(self, image: np.ndarray, detection: Detection) -> FaceLandmarks:
        """The 478 landmarks of one detected face: a crop from the detection (its box ×
        ``ROI_SCALE``, eyes level), refined from the landmarks. Where the refined presence stays
        under ``min_presence``, the other ``ROI_CROPS`` are tried (a turned or noisy face's first
        crop can miss it: measured on path-traced group photos, presence 0.003 on the box's crop,
        0.99 on the nose's), and the crop with the highest presence is kept."""
        image = _check_image(image)
        best = None
        for centre, scale in ROI_CROPS:
            points, presence = self._crop_landmarks(image, detection, centre, scale, "eyes")
            if best is None or presence > best[1]:
                best = (points, presence)
            if best[1] >= self.min_presence:
                break
        return FaceLandmarks(points=best[0], presence=best[1], detection=detection)

    def confirmed(self, image: np.ndarray, detection: Detection) -> FaceLandmarks | None:
        """The landmarks of a doubted detection or a candidate if they are confirmed (the detector's
        support and the presence on ``CONFIRM_CROPS``, see ``SUPPORT_STRONG``), else None: the first
        crop at ``min_presence`` for a detection with strong support, else the first of two crops at
        ``CONFIRM_PRESENCE``."""
        image = _check_image(image)
        support = self.tiled.support(image, detection)
        if support < SUPPORT_WEAK:
            return None
        sure = max(CONFIRM_PRESENCE, self.min_presence)
        strong = detection.score >= self.min_score and support >= SUPPORT_STRONG
        first = None
        for crop in CONFIRM_CROPS:
            points, presence = self._crop_landmarks(image, detection, *crop)
            if strong and presence >= self.min_presence:
                return FaceLandmarks(points=points, presence=presence, detection=detection, support=support)
            if presence >= sure:
                if first is not None:
                    return first
                first = FaceLandmarks(points=points, presence=presence, detection=detection, support=support)
        return None

    def _crop_landmarks(self, image: np.ndarray, detection: Detection, centre: str, scale: float,
                        rotation: str) -> tuple[np.ndarray, float]:
        """Landmarks and presence from one crop around a detection (see ``CONFIRM_CROPS``),
        refined ``refine_passes`` times from the landmarks."""
        x0, y0, x1, y1 = detection.box
        box_centre = ((x0 + x1) / 2, (y0 + y1) / 2)
        if centre == "box":
            cx, cy = box_centre
        elif centre == "nose":
            cx, cy = tuple(detection.keypoints[2])
        else:
            cx, cy = tuple((detection.keypoints[2] + box_centre) / 2)
        angle = 0.0
        if rotation == "eyes":
            eye_r, eye_l = detection.keypoints[0], detection.keypoints[1]
            angle = -math.atan2(-(eye_l[1] - eye_r[1]), eye_l[0] - eye_r[0])
        points, presence = self._run_landmarks(image, (cx, cy, max(x1 - x0, y1 - y0) * scale, angle))
        for _ in range(self.refine_passes):
            points, presence = self._run_landmarks(image, _roi_from_landmarks(points))
        return points, presence

    def _run_landmarks(self, image: np.ndarray, roi) -> tuple[np.ndarray, float]:
        cx, cy, size, rotation = roi
        c, s = math.cos(rotation), math.sin(rotation)
        k = size / LANDMARKS_SIZE
        # crop pixel (u, v) -> photo: centre + R(rotation) ((u, v) - 128) * k
        affine = np.array([[c * k, -s * k, cx - (c - s) * size / 2],
                           [s * k, c * k, cy - (s + c) * size / 2]])
        crop = _warp(image, affine, LANDMARKS_SIZE).astype(np.float32) / 255.0
        lm = self.landmarks_model
        lm.set_tensor(lm.get_input_details()[0]["index"], crop[None])
        lm.invoke()
        outs = [lm.get_tensor(d["index"]) for d in lm.get_output_details()]
        raw = next(o for o in outs if o.size == NUM_LANDMARKS * 3).reshape(NUM_LANDMARKS, 3)
        flag = next(o for o in outs if o.size == 1 and o.ndim == 4)
        presence = float(1.0 / (1.0 + math.exp(-float(np.clip(flag.reshape(()), -100, 100)))))
        raw = raw.astype(np.float64)
        xy = raw[:, :2] @ affine[:, :2].T + affine[:, 2]
        z = raw[:, 2] * k
        return np.concatenate([xy, z[:, None]], axis=1), presence

    def __call__(self, image: np.ndarray, max_faces: int | None = None,
                 min_face_px: float = MIN_FACE_PX) -> list[FaceLandmarks]:
        """Landmarks of every detected face whose presence passes ``min_presence`` (detection
        score order), then of the doubted detections and the candidates that are
        :meth:`confirmed`; two detections that land on one face count once; ``max_faces``: the
        first so many, ``None`` or 0 for all."""
        image = _check_image(image)
        detections, candidates = self.tiled.find(image, min_face_px=min_face_px)
        out: list[FaceLandmarks] = []
        boxes: list[np.ndarray] = []
        doubted: list[Detection] = []

        def add(lms: FaceLandmarks) -> None:
            box = np.concatenate([lms.points[:, :2].min(0), lms.points[:, :2].max(0)])
            if not boxes or not (iou(box, np.array(boxes)) > DUPLICATE_IOU).any():
                boxes.append(box)
                out.append(lms)

        for det in detections:
            if max_faces and len(out) >= max_faces:
                return out
            lms = self.landmarks(image, det)
            if lms.presence < self.min_presence:
                doubted.append(det)
            else:
                add(lms)
        for det in doubted + candidates:
            if max_faces and len(out) >= max_faces:
                break
            lms = self.confirmed(image, det)
            if lms is not None:
                add(lms)
        return out


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------
def _check_image(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an 8-bit RGB image (H, W, 3) uint8, got {image.dtype} "
                         f"{image.shape}")
    return image


def _warp(image: np.ndarray, affine: np.ndarray, size: int) -> np.ndarray:
    """Sample ``image`` on a size×size grid (bilinear, black outside). ``affine`` (2, 3) maps
    continuous output coordinates to continuous photo coordinates (pixel corners at integers,
    centres at +0.5), which is PIL's AFFINE convention."""
    from PIL import Image

    coeffs = tuple(float(v) for v in np.asarray(affine, dtype=np.float64).ravel())
    out = Image.fromarray(image).transform((size, size), Image.Transform.AFFINE, coeffs,
                                           resample=Image.Resampling.BILINEAR,
                                           fillcolor=(0, 0, 0))
    return np.asarray(out)


def _roi_from_landmarks(points: np.ndarray):
    """MediaPipe's tracking ROI: rotation from landmarks 33 -> 263, the landmarks' bounding box
    (in the rotated frame) squared on its long side and scaled ×1.5."""
    a, b = points[ROI_ROTATION_LANDMARKS[0], :2], points[ROI_ROTATION_LANDMARKS[1], :2]
    rotation = -math.atan2(-(b[1] - a[1]), b[0] - a[0])
    c, s = math.cos(rotation), math.sin(rotation)
    xy = points[:NUM_LANDMARKS - 10, :2]
    # landmarks expressed in the ROI's rotated frame
    rot = np.array([[c, s], [-s, c]])
    local = xy @ rot.T
    lo, hi = local.min(0), local.max(0)
    centre_local = (lo + hi) / 2
    centre = centre_local @ rot  # back to photo frame
    size = float(max(hi - lo)) * ROI_SCALE
    return float(centre[0]), float(centre[1]), size, rotation
