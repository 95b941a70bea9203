"""Cuts and sudden light changes in a clip, frame by frame (:mod:`f2l.video.estimate`, step 1).

A **cut or a change of the whole scene's light**: the frame's colour histogram outside the faces'
boxes (widened by ``BOX_MARGIN``, both frames' boxes, on the frame reduced to ``HISTOGRAM_SIDE`` px)
moves by more than ``cut_distance`` in L1 between two frames. A **change of the light on a face**
(a cloud over the sun, walking into shade): its mean linear luminance over patches at its 468
landmarks jumps by more than ``change_ratio`` against the median of its last three frames.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

__all__ = ["ChangeDetector", "face_luminance", "face_free_mask", "frame_histogram", "HISTOGRAM_BINS", "HISTOGRAM_SIDE",
           "BOX_MARGIN"]

HISTOGRAM_BINS = 16
HISTOGRAM_SIDE = 96  # frames are reduced to this long side for the histogram
BOX_MARGIN = 1.6  # a face's box widened this much is left out of the frame's histogram (hair, hands)


def face_luminance(image: np.ndarray, landmarks: np.ndarray, radius: int = 2) -> float:
    """Mean linear luminance of an sRGB uint8 frame over (2r+1)² patches at the face's 468 mesh
    landmarks: a whole-face brightness that a shadow edge crossing a few landmarks barely moves."""
    from f2l.io.photo.core import srgb_to_linear

    h, w = image.shape[:2]
    xy = np.rint(np.asarray(landmarks, np.float64)[:468, :2]).astype(np.int64)
    off = np.arange(-radius, radius + 1)
    cols = np.clip(xy[:, 0, None, None] + off[None, None, :], 0, w - 1)
    rows = np.clip(xy[:, 1, None, None] + off[None, :, None], 0, h - 1)
    codes = image[rows, cols].reshape(-1, 3)
    lut = _linear_lut(srgb_to_linear)
    return float((lut[codes] @ np.array([0.2126, 0.7152, 0.0722])).mean())


_LUT = None


def _linear_lut(srgb_to_linear) -> np.ndarray:
    global _LUT
    if _LUT is None:
        _LUT = np.asarray(srgb_to_linear(np.arange(256) / 255.0), np.float64)
    return _LUT


def _small(image: np.ndarray) -> tuple[np.ndarray, int]:
    """The frame reduced (by striding) to about ``HISTOGRAM_SIDE`` px on its long side, and the factor."""
    k = max(1, int(max(image.shape[:2]) // HISTOGRAM_SIDE))
    return np.ascontiguousarray(image[::k, ::k]), k


def face_free_mask(shape: tuple[int, int], k: int, boxes) -> np.ndarray:
    """uint8 mask of a reduced frame (``_small``), 0 inside the faces' ``boxes`` (x0, y0, x1, y1
    px) widened by ``BOX_MARGIN``, 255 elsewhere (all 255 if the faces cover everything)."""
    mask = np.full(shape, 255, np.uint8)
    for x0, y0, x1, y1 in boxes:
        cx, cy, half_w, half_h = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) * BOX_MARGIN / 2, (y1 - y0) * BOX_MARGIN / 2
        r0, r1 = int(max(0, (cy - half_h) / k)), int(min(shape[0], math.ceil((cy + half_h) / k)))
        c0, c1 = int(max(0, (cx - half_w) / k)), int(min(shape[1], math.ceil((cx + half_w) / k)))
        mask[r0:r1, c0:c1] = 0
    if not mask.any():
        mask[:] = 255
    return mask


def frame_histogram(small: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The reduced frame's colour histogram where ``mask`` is set: 3 × ``HISTOGRAM_BINS``, each
    channel's summing to 1."""
    import cv2

    hist = [cv2.calcHist([np.ascontiguousarray(small[..., c])], [0], mask, [HISTOGRAM_BINS], [0, 256]).ravel()
            for c in range(3)]
    return np.concatenate(hist) / max(float((mask > 0).sum()), 1.0)


class ChangeDetector:
    """Cuts and sudden light changes, frame by frame (module docstring)."""

    def __init__(self, cut_distance: float, change_ratio: float) -> None:
        self.cut_distance = float(cut_distance)
        self.change_ratio = float(change_ratio)
        self._last: tuple[np.ndarray, list] | None = None  # the last reduced frame and its face boxes
        self._skin: dict[int, deque] = {}

    def reset(self) -> None:
        self._skin.clear()

    def update(self, image: np.ndarray, faces) -> str | None:
        """Why a new segment starts at this frame (``"cut: ..."``, ``"light: ..."``), or None.
        The colours are compared outside both frames' face boxes."""
        small, k = _small(image)
        boxes = [f.box for f in faces if f.box is not None]
        why = None
        if self._last is not None and self._last[0].shape == small.shape:
            # both frames outside both frames' faces: a face that moves, turns or is covered is no cut
            mask = face_free_mask(small.shape[:2], k, boxes + self._last[1])
            distance = float(np.abs(frame_histogram(small, mask) - frame_histogram(self._last[0], mask)).sum() / 3.0)
            if distance > self.cut_distance:
                why = f"cut or light: the colours outside the faces moved by {distance:.2f} (limit {self.cut_distance:.2f})"
        self._last = (small, boxes)
        if why is not None:
            self.reset()
        for face in faces:
            if face.landmarks is None or face.status != "ok":
                continue
            lum = face_luminance(image, face.landmarks)
            past = self._skin.setdefault(face.person, deque(maxlen=3))
            if why is None and len(past) == past.maxlen:
                ref = float(np.median(past))
                ratio = lum / max(ref, 1e-6)
                if ratio > self.change_ratio or ratio < 1.0 / self.change_ratio:
                    why = (f"light: person {face.person}'s skin changed {ratio:.2f}x in a frame "
                           f"(limit {self.change_ratio:.2f}x)")
            past.append(lum)
        if why is not None and why.startswith("light"):
            keep = {f.person: self._skin[f.person][-1] for f in faces if f.person in self._skin}
            self.reset()
            for person, lum in keep.items():
                self._skin.setdefault(person, deque(maxlen=3)).append(lum)
        return why
