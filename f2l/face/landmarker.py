"""Offline face detection and 478-point 3D landmarks: MediaPipe's FaceLandmarker models on LiteRT.

The pinned ``face_landmarker.task`` bundle (see :mod:`f2l.synth.facemesh`) holds two TFLite
models that ``ai-edge-litert`` runs directly, without the ``mediapipe`` package (which declares
the GUI ``opencv-contrib-python`` and so fights ``opencv-contrib-python-headless`` for ``cv2``):

* ``face_detector.tflite`` — BlazeFace short range: a 128×128 RGB input in [-1, 1] (the photo
  letterboxed), 896 SSD anchors (strides 8, 16, 16, 16; fixed anchor size), 16 regressors per
  anchor (box centre/size + 6 keypoints: right eye, left eye, nose tip, mouth, right and left
  tragion, "right" meaning the subject's right) in units of input pixels, and a logit score.
  Detections above ``min_score`` are merged by weighted non-maximum suppression (IoU 0.3).
* ``face_landmarks_detector.tflite`` — a 256×256 RGB crop in [0, 1] → 478 (x, y, z) in crop
  pixels (468 face-mesh points + 10 iris points) and a face-presence logit. The crop is the
  square around the detection box scaled ×1.5 and rotated so that the eyes are level; a second
  pass re-crops around the first pass's landmarks (MediaPipe's tracking ROI, rotation from
  landmarks 33 → 263), which tightens the fit.

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

_log = logging.getLogger(__name__)

DETECTOR_MEMBER = "face_detector.tflite"
LANDMARKS_MEMBER = "face_landmarks_detector.tflite"
DETECTOR_SIZE = 128
LANDMARKS_SIZE = 256
NUM_LANDMARKS = 478
ROI_SCALE = 1.5
NMS_IOU = 0.3
# Eye-corner landmarks that define the tracking ROI's rotation (subject's right -> left).
ROI_ROTATION_LANDMARKS = (33, 263)


class LandmarkerError(RuntimeError):
    """The LiteRT runtime or the landmarker models are unavailable or unreadable."""


@dataclass(frozen=True)
class Detection:
    """A BlazeFace detection in photo pixels: box (x0, y0, x1, y1), 6 keypoints (6, 2), score."""

    box: np.ndarray
    keypoints: np.ndarray
    score: float


@dataclass(frozen=True)
class FaceLandmarks:
    """478 landmarks (478, 3) in photo pixels (z in the same scale, smaller = nearer).

    ``presence`` is the landmark model's face-presence probability on the final crop,
    ``detection`` the detector hit it started from.
    """

    points: np.ndarray
    presence: float
    detection: Detection


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


@lru_cache(maxsize=4)
def _interpreters(task_path: str, check_sha256: bool, threads: int):
    from f2l.synth.facemesh import canonical_face_mesh

    canonical_face_mesh(task_path, check_sha256=check_sha256)  # verifies the pin
    Interpreter = _interpreter_class()
    out = []
    try:
        with zipfile.ZipFile(task_path) as zf, _native_stderr_to_debug_log():
            for member in (DETECTOR_MEMBER, LANDMARKS_MEMBER):
                it = Interpreter(model_content=zf.read(member), num_threads=int(threads))
                it.allocate_tensors()
                out.append(it)
    except (zipfile.BadZipFile, KeyError, ValueError, RuntimeError) as exc:
        raise LandmarkerError(f"{task_path}: cannot load the landmarker models: {exc}") from exc
    return tuple(out)


class FaceLandmarker:
    """Detect faces and their 478 landmarks in an 8-bit RGB photo (H, W, 3) uint8.

    ``task_path`` overrides the bundle (default: ``$F2L_FACE_LANDMARKER`` or f2l's packaged copy);
    its SHA-256 must match the pin unless ``check_sha256=False``.
    """

    def __init__(self, task_path: str | os.PathLike | None = None, *, check_sha256: bool = True,
                 threads: int = 1, min_score: float = 0.5, min_presence: float = 0.5,
                 refine_passes: int = 1) -> None:
        from f2l.synth.facemesh import default_task_path

        path = Path(task_path) if task_path is not None else default_task_path()
        self.task_path = path.resolve()
        self.detector, self.landmarks_model = _interpreters(str(self.task_path), check_sha256,
                                                            int(threads))
        self.min_score = float(min_score)
        self.min_presence = float(min_presence)
        self.refine_passes = int(refine_passes)
        self._anchors = ssd_anchors()

    # -- detection ---------------------------------------------------------------------------
    def detect(self, image: np.ndarray) -> list[Detection]:
        """BlazeFace detections, highest score first, in photo pixels."""
        image = _check_image(image)
        h, w = image.shape[:2]
        side = max(h, w)
        # letterbox: the photo centred in a square of side `side`, scaled to 128
        scale = DETECTOR_SIZE / side
        pad_x, pad_y = (side - w) / 2.0, (side - h) / 2.0
        affine = np.array([[1.0 / scale, 0.0, -pad_x], [0.0, 1.0 / scale, -pad_y]])
        inp = _warp(image, affine, DETECTOR_SIZE).astype(np.float32) / 127.5 - 1.0
        det = self.detector
        det.set_tensor(det.get_input_details()[0]["index"], inp[None])
        det.invoke()
        outs = {d["name"]: det.get_tensor(d["index"]) for d in det.get_output_details()}
        reg = outs["regressors"][0].astype(np.float64)
        logits = np.clip(outs["classificators"][0, :, 0].astype(np.float64), -100.0, 100.0)
        scores = 1.0 / (1.0 + np.exp(-logits))
        keep = scores >= self.min_score
        if not keep.any():
            return []
        reg, scores, anchors = reg[keep], scores[keep], self._anchors[keep]
        # decode in normalised letterbox units, then to photo pixels
        centre = reg[:, 0:2] / DETECTOR_SIZE + anchors
        size = reg[:, 2:4] / DETECTOR_SIZE
        boxes = np.concatenate([centre - size / 2, centre + size / 2], axis=1)
        kps = reg[:, 4:16].reshape(-1, 6, 2) / DETECTOR_SIZE + anchors[:, None, :]
        to_px = np.array([side, side]), np.array([pad_x, pad_y])
        boxes = boxes * np.tile(to_px[0], 2) - np.tile(to_px[1], 2)
        kps = kps * to_px[0] - to_px[1]
        return _weighted_nms(boxes, kps, scores, NMS_IOU)

    # -- landmarks ---------------------------------------------------------------------------
    def landmarks(self, image: np.ndarray, detection: Detection) -> FaceLandmarks:
        """The 478 landmarks of one detected face (ROI from the detection, then refined)."""
        image = _check_image(image)
        x0, y0, x1, y1 = detection.box
        eye_r, eye_l = detection.keypoints[0], detection.keypoints[1]
        rotation = -math.atan2(-(eye_l[1] - eye_r[1]), eye_l[0] - eye_r[0])
        roi = ((x0 + x1) / 2, (y0 + y1) / 2, max(x1 - x0, y1 - y0) * ROI_SCALE, rotation)
        points, presence = self._run_landmarks(image, roi)
        for _ in range(self.refine_passes):
            roi = _roi_from_landmarks(points)
            points, presence = self._run_landmarks(image, roi)
        return FaceLandmarks(points=points, presence=presence, detection=detection)

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

    def __call__(self, image: np.ndarray, max_faces: int = 8) -> list[FaceLandmarks]:
        """Landmarks of every detected face whose presence passes ``min_presence``."""
        out = []
        for det in self.detect(image)[:max_faces]:
            lms = self.landmarks(image, det)
            if lms.presence >= self.min_presence:
                out.append(lms)
        return out


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------
def ssd_anchors() -> np.ndarray:
    """The 896 BlazeFace short-range anchor centres (normalised [0, 1], x then y).

    SSD layers with strides 8, 16, 16, 16 on a 128² input; layers of equal stride share a feature
    map, 2 anchors per layer per cell (aspect ratio 1 and the interpolated scale); fixed anchor
    size, so only centres matter: 16·16·2 + 8·8·6 = 896.
    """
    out = []
    for stride, per_cell in ((8, 2), (16, 6)):
        n = DETECTOR_SIZE // stride
        c = (np.arange(n) + 0.5) / n
        yy, xx = np.meshgrid(c, c, indexing="ij")
        cells = np.stack([xx.ravel(), yy.ravel()], axis=1)
        out.append(np.repeat(cells, per_cell, axis=0))
    return np.concatenate(out, axis=0)


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


def _iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    x0 = np.maximum(box[0], boxes[:, 0])
    y0 = np.maximum(box[1], boxes[:, 1])
    x1 = np.minimum(box[2], boxes[:, 2])
    y1 = np.minimum(box[3], boxes[:, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area = lambda b: (b[..., 2] - b[..., 0]) * (b[..., 3] - b[..., 1])  # noqa: E731
    return inter / np.maximum(area(box) + area(boxes) - inter, 1e-12)


def _weighted_nms(boxes, keypoints, scores, iou_threshold: float) -> list[Detection]:
    """MediaPipe's WEIGHTED non-maximum suppression: each cluster (IoU > threshold with its
    best member) becomes the score-weighted mean of its boxes and keypoints."""
    order = np.argsort(-scores)
    remaining = list(order)
    out = []
    while remaining:
        best = remaining[0]
        rest = np.array(remaining)
        overlap = _iou(boxes[best], boxes[rest]) > iou_threshold
        members = rest[overlap]
        w = scores[members] / scores[members].sum()
        out.append(Detection(box=(w[:, None] * boxes[members]).sum(0),
                             keypoints=(w[:, None, None] * keypoints[members]).sum(0),
                             score=float(scores[best])))
        remaining = [int(i) for i in rest[~overlap]]
    return out
