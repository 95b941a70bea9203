"""Is a detected face sharp enough to fit? The blur index of its central region.

The index is the no-reference measure of Crete, Dolmiere, Ladret and Nicolas, "The blur effect:
perception and estimation with a new no-reference perceptual blur metric", Proc. SPIE 6492 (2007):
blur the image again with a 9-tap box filter along rows (and along columns) and measure how much
of the variation between neighbouring pixels survives. A sharp image loses much of it (index near
0.2), a blurred one little (index toward 1). It is computed on the luma of the face's central box
(the landmarks' box shrunk to 70%, so the background at the face's edge does not count), box-reduced
by an integer factor so that the face is about :data:`BLUR_FACE_PX` wide: a large face's sharpness
is judged at the scale the fit uses, and a small face at its own pixels.

Measured on the 303 faces of at least 40 px in the path-traced framing sets (``make eval-framings``,
seeds 0 and 1; 16 spp, JPEG): 0.15-0.39, median 0.24, 99th percentile 0.36. On 66 of them and
scikit-image's astronaut blurred with a Gaussian of sigma = 1%, 2% and 4% of the face's width:
medians 0.46, 0.63 and 0.76, minima 0.29, 0.44 and 0.52. ``FitOptions.max_blur_index`` (:data:`MAX_BLUR_INDEX`)
refuses a face as ``blurred`` above it (docs/experiments/face_detection.md).
"""

from __future__ import annotations

import numpy as np

__all__ = ["BLUR_FACE_PX", "MAX_BLUR_INDEX", "blur_index", "face_blur_index", "central_box"]

BLUR_FACE_PX = 128
"""Faces wider than this (eye-line width, px) are box-reduced toward it before the index is taken."""
MAX_BLUR_INDEX = 0.55
"""Default refusal threshold: above every unblurred face measured (max 0.39), below most faces
blurred by sigma = 3-4% of their width."""
_TAPS = 9


def blur_index(luma: np.ndarray) -> float:
    """Crete et al. (2007) blur index of a 2-D image: 0 sharp ... 1 blurred, the larger of the
    indices along columns and along rows; an axis without any variation has none and is skipped
    (a sharp vertical step edge gives exactly 1/9), an image without any variation gives 1."""
    import cv2

    f = np.asarray(luma, dtype=np.float64)
    if f.ndim != 2 or min(f.shape) < 2:
        raise ValueError(f"blur_index needs a 2-D image of at least 2x2, got shape {f.shape}")
    box, one = np.full(_TAPS, 1.0 / _TAPS), np.ones(1)
    worst, varied = 0.0, False
    for axis in (0, 1):
        kx, ky = (one, box) if axis == 0 else (box, one)
        reblurred = cv2.sepFilter2D(f, cv2.CV_64F, kx, ky, borderType=cv2.BORDER_REFLECT)
        d_image = np.abs(np.diff(f, axis=axis))
        d_blur = np.abs(np.diff(reblurred, axis=axis))
        total = float(d_image.sum())
        lost = float(np.maximum(d_image - d_blur, 0.0).sum())
        if total > 0:
            worst = max(worst, (total - lost) / total)
            varied = True
    return worst if varied else 1.0


def central_box(landmarks_xy: np.ndarray, hw: tuple[int, int], keep: float = 0.7) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1): the landmarks' bounding box shrunk to ``keep`` of its size about its
    centre, clipped to the photo."""
    xy = np.asarray(landmarks_xy, dtype=np.float64)[:, :2]
    lo, hi = xy.min(0), xy.max(0)
    centre, half = (lo + hi) / 2, (hi - lo) * keep / 2
    x0, y0 = np.floor(centre - half).astype(int)
    x1, y1 = np.ceil(centre + half).astype(int)
    return max(0, y0), min(hw[0], y1), max(0, x0), min(hw[1], x1)


def face_blur_index(photo, landmarks_xy: np.ndarray, face_width_px: float) -> float | None:
    """The blur index of one face of ``photo`` (anything with ``shape`` and ``rows(index, cols)``
    returning ``display`` uint8 RGB: :class:`f2l.io.photo.Photo` or a streamed photo), or None
    when its central box is smaller than 8x8 px."""
    y0, y1, x0, x1 = central_box(landmarks_xy, photo.shape)
    if y1 - y0 < 8 or x1 - x0 < 8:
        return None
    display = photo.rows(np.arange(y0, y1), slice(x0, x1))["display"]
    luma = display.astype(np.float32) @ np.float32([0.2126, 0.7152, 0.0722])
    factor = max(1, int(face_width_px // BLUR_FACE_PX))
    if factor > 1:
        h, w = luma.shape[0] // factor * factor, luma.shape[1] // factor * factor
        luma = luma[:h, :w].reshape(h // factor, factor, w // factor, factor).mean(axis=(1, 3))
    if min(luma.shape) < 8:
        return None
    return blur_index(luma)
