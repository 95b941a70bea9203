"""Faces at every scale and position: a BlazeFace detector run over a pyramid of windows.

BlazeFace sees a fixed square input (N × N) and finds faces whose width lies in a band of that
input, ``[min_face_input_px, max_face_input_px]`` (measured: short range 16–150 px of 128, full
range 14–150 px of 192; ``docs/experiments/face_detection.md``). Letterboxing a whole photo into
N × N therefore loses every face narrower than ``min_face_input_px / N`` of the long side. Here
the photo is searched at several scales instead (:func:`tile_plan`):

* level k looks for faces of width ``[F_k, r · F_k]`` photo px with ``F_0 = min_face_px`` and
  ``F_{k+1} = r · F_k / LEVEL_OVERLAP`` (``r = max/min`` of the band used, inside the model's
  measured band; neighbouring levels overlap, so a face at a boundary is also seen well above
  the coarser level's lower end); the last level holds faces up to 1.25 × the long side;
* at level k the photo is resized by ``s_k = lo / F_k`` (``lo`` = the band's lower end) and cut
  into N × N windows at stride ``N − hi`` (``hi`` = the band's upper end), so a face of the
  level's band lies wholly inside at least one window; windows past the edge are padded black
  (the detector's letterbox), a photo smaller than N at a level is one padded window;
* windows whose pixels span fewer than ``FLAT_RANGE`` codes (clear sky, a wall, padding) cannot
  hold a face and are skipped;
* a window's detections are kept when their width is inside the level's band (widened by
  ``BAND_SLACK``: the next level takes the rest) and, for windows not on the photo's border,
  when they do not touch the window's edge (a face cut by the edge lies whole in a neighbour);
* all levels' detections are merged in photo pixels by MediaPipe's weighted non-maximum
  suppression (IoU > ``NMS_IOU``), and a box mostly inside a higher-scoring one
  (intersection over the smaller box > ``CONTAIN_IOM``) is dropped as its duplicate;
* hits scoring in ``[LOW_SCORE, min_score)`` are merged apart into *candidates* (those not on a
  detection). A candidate, or a detection the landmark model doubts, counts only when it is
  confirmed (:meth:`TiledDetector.support`: the model finds it again in windows centred on it, at
  its level's scale and 1.3× either side, each as is and mirrored; the landmarker decides).

Detections are in photo pixels (x right, y down, pixel centres at +0.5): box (x0, y0, x1, y1),
6 keypoints (the subject's right eye, left eye, nose tip, mouth, right and left tragion), score.
Deterministic; the cost grows with the photo's area over ``min_face_px²``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

NMS_IOU = 0.3
CONTAIN_IOM = 0.65
FLAT_RANGE = 12  # codes of luminance (max - min) below which a window is skipped
# a detection is kept if its width is within [lo / BAND_SLACK_LOW, hi * BAND_SLACK] input px: a turned
# face's box is narrower than its level's faces (and a window this small still finds it: 14 px ~ 100%)
BAND_SLACK = 1.25
BAND_SLACK_LOW = 1.5
EDGE_PX = 1.0
TOP_FACE_FRACTION = 1.25  # the widest face searched for, as a fraction of the long side
# each level starts this factor below where the last one's band ends, so a face near the boundary is
# also seen by the finer level, at more than its band's lower end (a 167 px box at 17 px scored 0.47)
LEVEL_OVERLAP = 1.3  # a box this close to an inner window edge is left to the neighbouring window
# hits from here up to the spec's min_score are candidates, kept only when confirmed: at 0.5 as plain
# detections they gave 4 false faces per 100 face-free photos (docs/experiments/face_detection.md)
LOW_SCORE = 0.45
# the windows that confirm a face: (scale factor on its level's scale, mirrored left to right)
SUPPORT_WINDOWS = ((1.0, False), (1.0, True), (1.3, False), (1 / 1.3, False), (1.3, True), (1 / 1.3, True))
SUPPORT_IOU = 0.5  # a hit in a support window is the same face when it overlaps it this much
# keypoint order after mirroring: right and left eye swap, and so do the tragions
_MIRRORED_KEYPOINTS = (1, 0, 2, 3, 5, 4)


@dataclass(frozen=True)
class Detection:
    """A face detection in photo pixels: box (x0, y0, x1, y1), 6 keypoints (6, 2), score, and the
    scale (window px per photo px) of the level where its best hit was found (0: not known)."""

    box: np.ndarray
    keypoints: np.ndarray
    score: float
    scale: float = 0.0

    @property
    def width(self) -> float:
        return float(self.box[2] - self.box[0])


@dataclass(frozen=True)
class DetectorSpec:
    """A BlazeFace model: input side, SSD anchor layout and the band of face widths it finds.

    ``band_px`` is the band the tiling plans with (input px), inside the model's measured band;
    ``strides``/``anchors_per_cell`` give the anchor centres (fixed anchor size, so only centres
    matter); ``min_score`` is the detection score a window's hit needs.
    """

    name: str
    input_size: int
    strides: tuple[int, ...]
    anchors_per_cell: tuple[int, ...]
    band_px: tuple[float, float]
    min_score: float

    def anchors(self) -> np.ndarray:
        """Anchor centres (A, 2), normalised [0, 1], x then y, in the models' output order."""
        out = []
        for stride, per_cell in zip(self.strides, self.anchors_per_cell):
            n = self.input_size // stride
            c = (np.arange(n) + 0.5) / n
            yy, xx = np.meshgrid(c, c, indexing="ij")
            out.append(np.repeat(np.stack([xx.ravel(), yy.ravel()], axis=1), per_cell, axis=0))
        return np.concatenate(out, axis=0)


# BlazeFace short range (MediaPipe face_detection_short_range_common): 128², strides 8, 16, 16, 16
# (layers of one stride share a map: 2 + 6 anchors a cell), 896 anchors; finds 16-150 px faces.
SHORT_RANGE = DetectorSpec("short_range", 128, (8, 16), (2, 6), (20.0, 60.0), 0.5)
# BlazeFace full range (face_detection_full_range_common): 192², one stride-4 layer, 2304 anchors;
# finds 14-150 px faces (wider context: trained for faces up to ~5 m away). Score threshold 0.6:
# at 0.5 the tiling's extra windows let 4 false faces per 100 face-free photos past the landmark
# check, for 3 more of 186 path-traced faces (docs/experiments/face_detection.md).
FULL_RANGE = DetectorSpec("full_range", 192, (4,), (1,), (17.0, 60.0), 0.6)


@dataclass(frozen=True)
class Level:
    """One scale of the search: the photo resized by ``scale`` to ``size`` (w, h), windows at
    ``origins`` (x, y) in the resized image, each ``input_size`` square; faces of photo width
    ``face_px`` (lo, hi)."""

    scale: float
    size: tuple[int, int]
    origins: tuple[tuple[int, int], ...]
    face_px: tuple[float, float]


def _starts(length: int, window: int, stride: int) -> list[int]:
    """Window starts covering [0, length): from 0 at ``stride``, the last one flush with the end."""
    if length <= window:
        return [0]
    n = math.ceil((length - window) / stride)
    return [round(i * (length - window) / n) for i in range(n + 1)]


def tile_plan(height: int, width: int, spec: DetectorSpec, min_face_px: float = 40.0,
              max_face_px: float | None = None) -> list[Level]:
    """The levels and windows that hold every face of width in [min_face_px, max_face_px]
    (default: ``TOP_FACE_FRACTION`` of the photo's long side) wholly inside one window at a scale where the model finds it.
    """
    n = spec.input_size
    lo, hi = spec.band_px
    long_side = max(height, width)
    # a face cut by the frame can be a little wider than the photo: its box still counts
    top = float(max_face_px) if max_face_px is not None else TOP_FACE_FRACTION * long_side
    stride = max(1, int(n - hi))
    levels: list[Level] = []
    face_lo = max(1.0, float(min_face_px))
    while True:
        scale = lo / face_lo
        w, h = max(1, round(width * scale)), max(1, round(height * scale))
        origins = tuple((x, y) for y in _starts(h, n, stride) for x in _starts(w, n, stride))
        levels.append(Level(scale=scale, size=(w, h), origins=origins,
                            face_px=(face_lo, hi / scale)))
        if hi / scale >= top:
            return levels
        face_lo = hi / scale / LEVEL_OVERLAP


class TiledDetector:
    """Run a BlazeFace interpreter (LiteRT) over :func:`tile_plan`'s windows of an RGB uint8 photo."""

    def __init__(self, interpreter, spec: DetectorSpec, *, min_score: float | None = None,
                 low_score: float = LOW_SCORE) -> None:
        self.interpreter = interpreter
        self.spec = spec
        self.min_score = spec.min_score if min_score is None else float(min_score)
        self.low_score = min(self.min_score, float(low_score))
        self._anchors = spec.anchors()
        self._in = interpreter.get_input_details()[0]["index"]
        outs = interpreter.get_output_details()
        self._reg = next(d["index"] for d in outs if d["shape"][-1] == 16)
        self._cls = next(d["index"] for d in outs if d["shape"][-1] == 1)
        self.windows_run = 0
        self.windows_skipped = 0

    def _invoke(self, window: np.ndarray):
        it = self.interpreter
        it.set_tensor(self._in, (window.astype(np.float32) * (1.0 / 127.5) - 1.0)[None])
        it.invoke()
        reg = it.get_tensor(self._reg)[0].astype(np.float64)
        logits = np.clip(it.get_tensor(self._cls)[0, :, 0].astype(np.float64), -80.0, 80.0)
        return reg, 1.0 / (1.0 + np.exp(-logits))

    def window(self, window: np.ndarray, min_score: float | None = None):
        """Raw detections of one N × N window: boxes (K, 4), keypoints (K, 6, 2) in window px,
        scores (K,), those above ``min_score`` (default: the detector's)."""
        n = self.spec.input_size
        reg, scores = self._invoke(window)
        keep = scores >= (self.min_score if min_score is None else min_score)
        reg, scores, anchors = reg[keep], scores[keep], self._anchors[keep]
        centre = reg[:, 0:2] + anchors * n
        size = reg[:, 2:4]
        boxes = np.concatenate([centre - size / 2, centre + size / 2], axis=1)
        kps = reg[:, 4:16].reshape(-1, 6, 2) + anchors[:, None, :] * n
        return boxes, kps, scores

    def __call__(self, image: np.ndarray, min_face_px: float = 40.0,
                 max_face_px: float | None = None) -> list[Detection]:
        """The detections (score >= ``min_score``), merged, highest score first."""
        return self.find(image, min_face_px, max_face_px)[0]

    def find(self, image: np.ndarray, min_face_px: float = 40.0,
             max_face_px: float | None = None) -> tuple[list[Detection], list[Detection]]:
        """(detections, candidates): the merged hits scoring at least ``min_score``, and apart from
        them the merged hits in ``[low_score, min_score)`` that lie on no detection (IoU > ``NMS_IOU``
        or mostly inside or around one), each highest score first. The detections are those of a
        search with ``min_score`` alone."""
        image = _check_rgb(image)
        h, w = image.shape[:2]
        n = self.spec.input_size
        found: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        for level in tile_plan(h, w, self.spec, min_face_px, max_face_px):
            # one band of the resized photo per row of windows: memory is a band, not the level
            for y0 in sorted({y for _, y in level.origins}):
                band, row0, sy = _level_band(image, level, y0, n)
                sx = w / level.size[0]
                luma = band.max(axis=2)
                for x0, _ in (o for o in level.origins if o[1] == y0):
                    if int(luma[:, x0:x0 + n].max()) - int(luma[:, x0:x0 + n].min()) < FLAT_RANGE:
                        self.windows_skipped += 1
                        continue
                    win = band[:, x0:x0 + n]
                    if win.shape[:2] != (n, n):  # past the photo's edge: the detector's black letterbox
                        pad = np.zeros((n, n, 3), np.uint8)
                        pad[:win.shape[0], :win.shape[1]] = win
                        win = pad
                    self.windows_run += 1
                    kept = self._keep(*self.window(win, self.low_score), (x0, y0), level.size)
                    if kept is None:
                        continue
                    boxes, kps, scores = kept
                    # window px -> photo px: x by the level's scale, y by the band's own
                    scale = np.array([sx, 1.0 / sy])
                    off = np.array([x0 * sx, row0])
                    found.append((boxes * np.tile(scale, 2) + np.tile(off, 2), kps * scale + off, scores,
                                  np.full(len(scores), level.scale)))
        if not found:
            return [], []
        boxes, kps, scores, scales = (np.concatenate(parts) for parts in zip(*found))
        high = scores >= self.min_score
        detections = merge_detections(boxes[high], kps[high], scores[high], scales=scales[high])
        low = merge_detections(boxes[~high], kps[~high], scores[~high], scales=scales[~high])
        if detections and low:
            taken = np.array([d.box for d in detections])
            low = [c for c in low if not _overlaps(c.box, taken, NMS_IOU, CONTAIN_IOM).any()]
        return detections, low

    def support(self, image: np.ndarray, detection: Detection) -> float:
        """How firmly the model finds ``detection`` again: the sum, over ``SUPPORT_WINDOWS`` (N × N
        windows centred on its box at its level's scale and 1.3× either side, each as is and
        mirrored), of the best score (>= ``low_score``) of a hit overlapping its box by IoU >
        ``SUPPORT_IOU``; 0 to 6. Measured: true faces the landmark model doubts 4.2-4.7, path-traced
        faces scoring under ``min_score`` 2.4-3.9, face-like textures of face-free photos up to 3.1
        (``docs/experiments/face_detection.md``)."""
        image = _check_rgb(image)
        scale = detection.scale or self.spec.band_px[1] / max(detection.width, 1.0)
        cx, cy = (detection.box[0] + detection.box[2]) / 2, (detection.box[1] + detection.box[3]) / 2
        total = 0.0
        for factor, mirrored in SUPPORT_WINDOWS:
            boxes, _, scores = self._window_at(image, cx, cy, scale * factor, mirrored)
            same = iou(detection.box, boxes) > SUPPORT_IOU if len(scores) else np.zeros(0, bool)
            total += float(scores[same].max()) if same.any() else 0.0
        return total

    def _window_at(self, image: np.ndarray, cx: float, cy: float, scale: float, mirrored: bool):
        """Hits (>= ``low_score``) of the N × N window centred at photo (cx, cy) with the photo
        resized by ``scale`` (black past its edges), mirrored left to right if asked; boxes and
        keypoints in photo px, keypoints in the subject's order."""
        import cv2

        n = self.spec.input_size
        side = n / scale
        x0, y0 = cx - side / 2, cy - side / 2
        if scale < 1:  # area averaging of the photo region, padded black past the photo's edges
            xa, ya = math.floor(x0), math.floor(y0)
            xb, yb = math.ceil(x0 + side), math.ceil(y0 + side)
            h, w = image.shape[:2]
            region = np.zeros((yb - ya, xb - xa, 3), np.uint8)
            sx0, sy0, sx1, sy1 = max(0, xa), max(0, ya), min(w, xb), min(h, yb)
            if sx1 > sx0 and sy1 > sy0:
                region[sy0 - ya:sy1 - ya, sx0 - xa:sx1 - xa] = image[sy0:sy1, sx0:sx1]
            win = cv2.resize(region, (n, n), interpolation=cv2.INTER_AREA)
            step, origin = np.array([(xb - xa) / n, (yb - ya) / n]), np.array([xa, ya], float)
        else:
            affine = np.array([[scale, 0.0, -x0 * scale], [0.0, scale, -y0 * scale]])
            win = cv2.warpAffine(image, affine, (n, n), flags=cv2.INTER_LINEAR, borderValue=0)
            step, origin = np.array([1 / scale, 1 / scale]), np.array([x0, y0])
        if mirrored:
            win = np.ascontiguousarray(win[:, ::-1])
        boxes, kps, scores = self.window(win, self.low_score)
        if mirrored:
            boxes = np.stack([n - boxes[:, 2], boxes[:, 1], n - boxes[:, 0], boxes[:, 3]], axis=1)
            kps = np.stack([n - kps[..., 0], kps[..., 1]], axis=-1)[:, _MIRRORED_KEYPOINTS]
        return boxes * np.tile(step, 2) + np.tile(origin, 2), kps * step + origin, scores

    def _keep(self, boxes, kps, scores, origin, level_size):
        """The window's detections inside the level's band and not cut by an inner window edge."""
        if not len(scores):
            return None
        n = self.spec.input_size
        lo, hi = self.spec.band_px
        (x0, y0), (lw, lh) = origin, level_size
        bw = boxes[:, 2] - boxes[:, 0]
        ok = (bw >= lo / BAND_SLACK_LOW) & (bw <= hi * BAND_SLACK)
        inner = (x0 > 0, y0 > 0, x0 + n < lw, y0 + n < lh)
        ok &= ~(((boxes[:, 0] < EDGE_PX) & inner[0]) | ((boxes[:, 1] < EDGE_PX) & inner[1])
                | ((boxes[:, 2] > n - EDGE_PX) & inner[2]) | ((boxes[:, 3] > n - EDGE_PX) & inner[3]))
        if not ok.any():
            return None
        return boxes[ok], kps[ok], scores[ok]


def _check_rgb(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an 8-bit RGB image (H, W, 3) uint8, got {image.dtype} {image.shape}")
    return image


def _level_band(image: np.ndarray, level: Level, y0: int, n: int):
    """About rows [y0, y0 + n) of the photo resized to ``level.size`` (at most n rows, starting
    within a row of y0): (band, its first photo row, scale from photo rows to band rows). The band is resized from just the photo rows it covers (area
    averaging when reducing, bilinear when enlarging), so it aligns exactly with those rows."""
    import cv2

    h = image.shape[0]
    lw, lh = level.size
    scale_y = lh / h
    r0 = min(h - 1, int(math.floor(y0 / scale_y)))
    r1 = max(r0 + 1, min(h, int(math.ceil(min(lh, y0 + n) / scale_y))))
    rows = max(1, round((r1 - r0) * scale_y))
    interp = cv2.INTER_AREA if scale_y < 1 else cv2.INTER_LINEAR
    band = cv2.resize(np.ascontiguousarray(image[r0:r1]), (lw, rows), interpolation=interp)
    return band.reshape(rows, lw, 3)[:n], float(r0), rows / (r1 - r0)


def _intersection(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    x0 = np.maximum(box[0], boxes[:, 0])
    y0 = np.maximum(box[1], boxes[:, 1])
    x1 = np.minimum(box[2], boxes[:, 2])
    y1 = np.minimum(box[3], boxes[:, 3])
    return np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)


def _area(boxes: np.ndarray) -> np.ndarray:
    return (boxes[..., 2] - boxes[..., 0]) * (boxes[..., 3] - boxes[..., 1])


def iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Intersection over union of one box (4,) with boxes (K, 4)."""
    inter = _intersection(box, boxes)
    return inter / np.maximum(_area(box) + _area(boxes) - inter, 1e-12)


def _overlaps(box: np.ndarray, boxes: np.ndarray, iou_threshold: float, contain: float) -> np.ndarray:
    """Which of ``boxes`` overlap ``box`` by IoU > iou_threshold or lie mostly inside or around it."""
    inter = _intersection(box, boxes)
    smaller = np.minimum(_area(box), _area(boxes))
    return (inter / np.maximum(_area(box) + _area(boxes) - inter, 1e-12) > iou_threshold) | (
        inter / np.maximum(smaller, 1e-12) > contain)


def merge_detections(boxes: np.ndarray, keypoints: np.ndarray, scores: np.ndarray,
                     iou_threshold: float = NMS_IOU, contain: float = CONTAIN_IOM,
                     scales: np.ndarray | None = None) -> list[Detection]:
    """MediaPipe's weighted non-maximum suppression, highest score first: each cluster (IoU >
    threshold with its best member) becomes the score-weighted mean of its members' boxes and
    keypoints (and takes the best member's ``scales`` entry); a box mostly inside or around the best
    one (intersection over the smaller box > ``contain``: a part of the face found alone, or the
    face with its surroundings) is dropped."""
    order = np.argsort(-scores, kind="stable")
    remaining = order
    out = []
    while len(remaining):
        best = remaining[0]
        inter = _intersection(boxes[best], boxes[remaining])
        union = _area(boxes[best]) + _area(boxes[remaining]) - inter
        smaller = np.minimum(_area(boxes[best]), _area(boxes[remaining]))
        joined = inter / np.maximum(union, 1e-12) > iou_threshold
        joined[0] = True
        overlap = joined | (inter / np.maximum(smaller, 1e-12) > contain)
        members = remaining[joined]
        w = scores[members] / scores[members].sum()
        out.append(Detection(box=(w[:, None] * boxes[members]).sum(0),
                             keypoints=(w[:, None, None] * keypoints[members]).sum(0),
                             score=float(scores[best]),
                             scale=float(scales[best]) if scales is not None else 0.0))
        remaining = remaining[~overlap]
    return out
