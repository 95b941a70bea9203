"""Find a ColorChecker Classic in a photo and measure its 24 patches on the linear image.

Detection: OpenCV ``mcc`` (``CCheckerDetector``, chart type ``MCC24``) on the 8-bit sRGB display
image (downscaled to at most ``MCC_MAX_SIDE`` px). The chart type must be set explicitly:
``CCheckerDetector_create()`` in OpenCV 5.0 leaves it uninitialised (``getColorChartType()``
returns arbitrary numbers) and detection then fails at random; the DNN switch is also turned off
explicitly (no network is loaded). When mcc finds nothing, it is retried on contrast-normalised
versions of the image, in this order:
``display`` → ``exposure`` (the linear image scaled so its 99th luminance percentile is 0.8,
sRGB-encoded) → ``stretch`` (each channel's 1st-99th percentile stretched to 0-255, which also
removes a colour cast) → ``clahe`` (CLAHE on CIELAB L). :attr:`ChartDetection.variant` names the
one that worked.

Geometry: mcc returns a small quad inside each patch; a least-squares homography (canonical chart
frame of :mod:`f2l.colour.chart` → image) is fitted to the 24 quad centres, and full patch squares
and the measured regions (centred squares of side ``MEASURE_FRACTION`` pitch) are mapped through
it. The patch order is checked on the linear image: the unclipped patches of the neutral row
(19-24) must get darker from white to black; if only the 180°-rotated order satisfies this the
order is rotated, and if neither does the detection is rejected as implausible (with fewer than
two unclipped neutral patches the order cannot be checked and mcc's is kept).

Measurement, per patch, over the measured region of ``linear`` (camera RGB, any scale):
``rgb`` = per-channel median; ``spread`` = max over channels of (P90 − P10) / (median + 0.02·clip),
a robust relative spread that catches shadow edges and glare. A patch is excluded with a reason:
``outside`` (region leaves the image), ``too_small`` (< ``MIN_PIXELS`` pixels), ``clipped`` (more
than 1 % of its pixels have a channel ≥ ``CLIP_FRACTION`` × clip level, or are flagged in
``clipped``), ``nonuniform`` (spread > ``SPREAD_LIMIT``). The clip level defaults to
max(1, max of ``linear``): 1.0 is full scale for :func:`f2l.io.photo.load_photo` images.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from f2l.colour.chart import (N_PATCHES, NEUTRAL_INDICES, PATCH_FRACTION, apply_homography, patch_centres_canonical,
                              patch_squares_canonical, srgb_encode_uint8)

MCC_MAX_SIDE = 1600
MEASURE_FRACTION = 0.5  # side of the measured square, in pitches (the patch is PATCH_FRACTION)
CLIP_FRACTION = 0.98
CLIPPED_PIXEL_SHARE = 0.01
SPREAD_FLOOR = 0.02  # × clip level, added to the median in the relative spread
SPREAD_LIMIT = 0.3
MIN_PIXELS = 9
MAX_CENTRE_RESIDUAL = 0.2  # RMS of mcc centres about the fitted homography, in pitches
NEUTRAL_STEP_TOLERANCE = 1.1  # a neutral patch may be at most this much brighter than its lighter neighbour
VARIANTS = ("display", "exposure", "stretch", "clahe")
LUMA = np.array([0.2126, 0.7152, 0.0722])


@dataclass
class ChartDetection:
    """A located chart and its measured patches (image coordinates x right, y down, pixels; index i = patch i+1)."""

    homography: np.ndarray  # (3, 3) canonical chart frame → image
    patch_polygons: np.ndarray  # (24, 4, 2) full patch squares TL, TR, BR, BL
    measure_polygons: np.ndarray  # (24, 4, 2) measured regions
    patch_centres: np.ndarray  # (24, 2)
    rgb: np.ndarray  # (24, 3) median linear RGB of each measured region (NaN when outside)
    spread: np.ndarray  # (24,) robust relative spread
    n_pixels: np.ndarray  # (24,) pixels measured
    reasons: list[str]  # (24) "" when valid, else outside | too_small | clipped | nonuniform
    variant: str  # image variant mcc succeeded on (see VARIANTS)
    mcc_cost: float
    rotated: bool  # patch order rotated by 180° relative to mcc's
    centre_residual: float  # RMS of mcc centres about the homography, pitches
    clip_level: float
    log: list[str] = field(default_factory=list)

    @property
    def valid(self) -> np.ndarray:
        """(24,) bool: patches usable for fitting."""
        return np.array([not r for r in self.reasons])

    @property
    def excluded(self) -> list[tuple[int, str]]:
        """(patch number 1-24, reason) of every excluded patch."""
        return [(i + 1, r) for i, r in enumerate(self.reasons) if r]


# -- mcc ---------------------------------------------------------------------------------------
def _mcc_quads(display_rgb: np.ndarray) -> tuple[np.ndarray, float] | None:
    """(24, 4, 2) mcc patch quads (image px) and cost, or None when mcc finds no MCC24 chart."""
    height, width = display_rgb.shape[:2]
    scale = min(1.0, MCC_MAX_SIDE / max(height, width))
    image = cv2.cvtColor(np.ascontiguousarray(display_rgb), cv2.COLOR_RGB2BGR)
    if scale < 1.0:
        image = cv2.resize(image, (round(width * scale), round(height * scale)), interpolation=cv2.INTER_AREA)
    detector = cv2.mcc.CCheckerDetector_create()
    detector.setColorChartType(cv2.mcc.MCC24)
    detector.setUseDnnModel(False)
    if not detector.process(image, 1):
        return None
    checker = detector.getBestColorChecker()
    quads = np.asarray(checker.getColorCharts(), np.float64).reshape(-1, 4, 2)
    if quads.shape[0] != N_PATCHES:
        return None
    return quads / scale, float(checker.getCost())


def _variant_image(name: str, display: np.ndarray, linear: np.ndarray | None) -> np.ndarray | None:
    if name == "display":
        return display
    if name == "exposure":
        if linear is None:
            return None
        p99 = float(np.percentile(linear @ LUMA, 99))
        return srgb_encode_uint8(linear * (0.8 / p99)) if p99 > 0 else None
    if name == "stretch":
        lo, hi = np.percentile(display.reshape(-1, 3), [1, 99], axis=0)
        scaled = (display.astype(np.float32) - lo) * (255.0 / np.maximum(hi - lo, 1.0))
        return np.clip(np.round(scaled), 0, 255).astype(np.uint8)
    lab = cv2.cvtColor(display, cv2.COLOR_RGB2LAB)
    lab[..., 0] = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)).apply(lab[..., 0])
    return cv2.cvtColor(lab, cv2.COLOR_LAB2RGB)


# -- measurement -------------------------------------------------------------------------------
def _measure(linear: np.ndarray, clipped: np.ndarray | None, polygon: np.ndarray, clip_level: float):
    """(median rgb, relative spread, n pixels, reason) of the pixels inside ``polygon``."""
    height, width = linear.shape[:2]
    if (polygon < 0).any() or (polygon[:, 0] > width - 1).any() or (polygon[:, 1] > height - 1).any():
        return np.full(3, np.nan), np.nan, 0, "outside"
    x0, y0 = np.floor(polygon.min(axis=0)).astype(int)
    x1, y1 = np.ceil(polygon.max(axis=0)).astype(int) + 1
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillConvexPoly(mask, np.round((polygon - [x0, y0]) * 16).astype(np.int32), 1, shift=4)
    inside = mask.astype(bool)
    pixels = linear[y0:y1, x0:x1][inside].astype(np.float64)
    if pixels.shape[0] < MIN_PIXELS:
        return (np.median(pixels, axis=0) if len(pixels) else np.full(3, np.nan)), np.nan, len(pixels), "too_small"
    median = np.median(pixels, axis=0)
    p10, p90 = np.percentile(pixels, [10, 90], axis=0)
    spread = float(np.max((p90 - p10) / (np.abs(median) + SPREAD_FLOOR * clip_level)))
    saturated = (pixels >= CLIP_FRACTION * clip_level).any(axis=1)
    if clipped is not None:
        saturated |= clipped[y0:y1, x0:x1][inside]
    if saturated.mean() > CLIPPED_PIXEL_SHARE:
        return median, spread, len(pixels), "clipped"
    return median, spread, len(pixels), ("nonuniform" if spread > SPREAD_LIMIT else "")


def _neutral_row_plausible(rgb: np.ndarray, reasons: list[str]) -> bool:
    """Whether the unclipped patches of 19-24 get darker from white to black (True if < 2 are unclipped)."""
    kept = [i for i in NEUTRAL_INDICES if reasons[i] != "clipped"]
    lum = np.array([rgb[i] @ LUMA for i in kept])
    if len(kept) < 2:
        return True
    if not np.isfinite(lum).all():
        return False
    return bool(np.all(lum[1:] <= NEUTRAL_STEP_TOLERANCE * lum[:-1]) and lum[0] > lum[-1])


def _locate(quads: np.ndarray, rotate: bool):
    """Homography (canonical → image) fitted to the quad centres and its RMS residual in pitches."""
    centres = quads.mean(axis=1)
    if rotate:
        centres = centres[::-1]
    canon = patch_centres_canonical()
    homography, _ = cv2.findHomography(canon, centres, 0)
    if homography is None:
        return None, np.inf
    residual = np.sqrt(np.mean(np.sum((apply_homography(homography, canon) - centres) ** 2, axis=1)))
    pitch = np.sqrt(abs(np.linalg.det(homography[:2, :2] / homography[2, 2])))
    return homography, float(residual / max(pitch, 1e-9))


def _measure_all(linear, clipped, homography, clip_level):
    polygons = apply_homography(homography, patch_squares_canonical(MEASURE_FRACTION))
    results = [_measure(linear, clipped, poly, clip_level) for poly in polygons]
    rgb = np.array([r[0] for r in results])
    spread = np.array([r[1] for r in results], np.float64)
    n_pixels = np.array([r[2] for r in results], np.int64)
    return polygons, rgb, spread, n_pixels, [r[3] for r in results]


def detect_chart(display_uint8: np.ndarray, linear_image: np.ndarray, *, clipped: np.ndarray | None = None,
                 clip_level: float | None = None, log: list[str] | None = None) -> ChartDetection | None:
    """Locate a ColorChecker Classic in ``display_uint8`` (H, W, 3 sRGB) and measure it on ``linear_image``.

    ``linear_image`` (H, W, 3) is the same photo in linear camera RGB; ``clipped`` (H, W) optionally
    flags saturated pixels. Returns None when no plausible chart is found; the reason of each
    attempt is appended to ``log`` when given.
    """
    notes = [] if log is None else log
    display = np.ascontiguousarray(np.asarray(display_uint8, np.uint8)[..., :3])
    linear = np.asarray(linear_image, np.float32)[..., :3]
    if display.shape[:2] != linear.shape[:2]:
        raise ValueError(f"display {display.shape[:2]} and linear {linear.shape[:2]} images differ in size")
    level = float(clip_level) if clip_level is not None else max(1.0, float(np.max(linear)))
    for name in VARIANTS:
        image = _variant_image(name, display, linear)
        if image is None:
            continue
        found = _mcc_quads(image)
        if found is None:
            notes.append(f"{name}: mcc found no chart")
            continue
        quads, cost = found
        for rotate in (False, True):
            homography, residual = _locate(quads, rotate)
            if homography is None or residual > MAX_CENTRE_RESIDUAL:
                notes.append(f"{name}: patch centres do not fit a 4x6 grid (residual {residual:.2f} pitch)")
                break
            polygons, rgb, spread, n_pixels, reasons = _measure_all(linear, clipped, homography, level)
            if not _neutral_row_plausible(rgb, reasons):
                notes.append(f"{name}{' rotated' if rotate else ''}: neutral row not ordered white to black")
                continue
            notes.append(f"{name}{' rotated' if rotate else ''}: chart found (mcc cost {cost:.3f})")
            return ChartDetection(
                homography=homography, measure_polygons=polygons,
                patch_polygons=apply_homography(homography, patch_squares_canonical(PATCH_FRACTION)),
                patch_centres=apply_homography(homography, patch_centres_canonical()), rgb=rgb, spread=spread,
                n_pixels=n_pixels, reasons=reasons, variant=name, mcc_cost=cost, rotated=rotate,
                centre_residual=residual, clip_level=level, log=list(notes))
    return None
