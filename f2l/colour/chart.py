"""ColorChecker Classic reference values, chart layout, and synthetic chart photos.

Reference values. colour-science stores each edition's 24 patches as CIE xyY under the chart's
illuminant (D50 for the X-Rite editions). :func:`reference_chart` converts them to XYZ, adapts
them to D65 with the Bradford von Kries transform, and converts to linear Rec.709 RGB
(``RGB = M_709 · XYZ_D65``, no transfer function). That is the target of calibration: "what the
patch would be in linear, scene-referred Rec.709 under a white (D65) light, white patch ≈ 0.88".
Rec.709 cannot hold every patch: cyan (18) has R ≈ -0.04; negative targets are kept as they are.

Layout (canonical chart frame, units of one patch pitch, x right, y down): the 4 × 6 grid of
cells spans [0, 6] × [0, 4]; patch ``i`` (0-based; patch number ``i + 1`` as printed) is in row
``i // 6`` and column ``i % 6``, a square of side ``PATCH_FRACTION`` centred in its cell. The dark
card extends ``CARD_MARGIN`` beyond the grid. Patches 19-24 (indices 18-23) are the neutral row,
white to black.

Synthetic photos (:func:`render_chart_photo`): scene reflectance (linear Rec.709) × ``exposure``
→ camera RGB ``= camera_matrix · rgb_709`` → × vignetting ``1 - s (r / r_corner)²`` (``r`` from
the image centre) → + Gaussian noise N(0, σ²) → clipped to [0, 1] (1.0 = sensor saturation).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import colour
import cv2
import numpy as np

DEFAULT_EDITION = "ColorChecker24 - After November 2014"
CHART_ROWS, CHART_COLS, N_PATCHES = 4, 6, 24
NEUTRAL_INDICES = tuple(range(18, 24))  # patches 19-24, white → black
PATCH_FRACTION = 0.84  # patch side / pitch
CARD_MARGIN = 0.4  # card border beyond the patch grid, in pitches
CARD_REFLECTANCE = 0.03  # the dark card and the gaps between patches
D65_XY = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
REC709 = colour.RGB_COLOURSPACES["ITU-R BT.709"]
CHROMATIC_ADAPTATION = "Bradford"
DEFAULT_CAMERA_MATRIX = np.array([[0.62, 0.25, 0.05],
                                  [0.12, 0.80, 0.12],
                                  [0.03, 0.20, 0.55]])  # camera RGB from linear Rec.709


@dataclass(frozen=True)
class ChartReference:
    """Reference patches of one edition: ``rgb`` (24, 3) linear Rec.709 D65, ``lab`` (24, 3) CIELAB D65."""

    edition: str
    names: tuple[str, ...]
    rgb: np.ndarray
    lab: np.ndarray


def editions() -> list[str]:
    """Names of the 24-patch ColorChecker editions colour-science knows."""
    return [name for name, cc in colour.CCS_COLOURCHECKERS.items()
            if len(cc.data) == N_PATCHES and name not in ("babel_average", "cc2005", "ccb2014", "cca2014")]


def rgb709_to_lab(rgb: np.ndarray) -> np.ndarray:
    """CIELAB (D65 white, Y of white = 1) of linear Rec.709 RGB, shape (..., 3)."""
    xyz = np.asarray(rgb, np.float64) @ REC709.matrix_RGB_to_XYZ.T
    return colour.XYZ_to_Lab(xyz, D65_XY)


def reference_chart(edition: str = DEFAULT_EDITION) -> ChartReference:
    """Reference values of ``edition`` in linear Rec.709 (Bradford-adapted from its illuminant to D65)."""
    if edition not in colour.CCS_COLOURCHECKERS or len(colour.CCS_COLOURCHECKERS[edition].data) != N_PATCHES:
        raise ValueError(f"unknown 24-patch ColorChecker edition {edition!r}; known: {editions()}")
    checker = colour.CCS_COLOURCHECKERS[edition]
    xyz = colour.xyY_to_XYZ(np.array(list(checker.data.values()), np.float64))
    xyz_d65 = colour.chromatic_adaptation(xyz, colour.xy_to_XYZ(checker.illuminant), colour.xy_to_XYZ(D65_XY),
                                          method="Von Kries", transform=CHROMATIC_ADAPTATION)
    rgb = xyz_d65 @ REC709.matrix_XYZ_to_RGB.T
    return ChartReference(edition, tuple(checker.data.keys()), rgb, colour.XYZ_to_Lab(xyz_d65, D65_XY))


def patch_centres_canonical() -> np.ndarray:
    """(24, 2) patch centres (x, y) in the canonical chart frame (pitch units)."""
    idx = np.arange(N_PATCHES)
    return np.stack([idx % CHART_COLS + 0.5, idx // CHART_COLS + 0.5], axis=1).astype(np.float64)


def patch_squares_canonical(fraction: float = PATCH_FRACTION) -> np.ndarray:
    """(24, 4, 2) squares of side ``fraction`` (pitches) around each centre: TL, TR, BR, BL."""
    half = fraction / 2
    offsets = np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
    return patch_centres_canonical()[:, None, :] + offsets[None]


def card_corners_canonical() -> np.ndarray:
    """(4, 2) outer corners of the card (TL, TR, BR, BL) in the canonical frame."""
    m = CARD_MARGIN
    return np.array([[-m, -m], [CHART_COLS + m, -m], [CHART_COLS + m, CHART_ROWS + m], [-m, CHART_ROWS + m]])


def apply_homography(homography: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map (..., 2) points (x, y) through a 3 × 3 homography."""
    pts = np.asarray(points, np.float64)
    x, y = pts[..., 0], pts[..., 1]
    h = np.asarray(homography, np.float64)
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    return np.stack([(h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w, (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w], -1)


def srgb_encode_uint8(linear: np.ndarray) -> np.ndarray:
    """8-bit sRGB codes of linear values (clipped to [0, 1]; IEC 61966-2-1 transfer function)."""
    v = np.clip(np.asarray(linear, np.float64), 0.0, 1.0)
    encoded = np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)
    return np.round(encoded * 255).astype(np.uint8)


@dataclass
class SyntheticChartPhoto:
    """A rendered chart photo and its ground truth (image coordinates: x right, y down, pixels)."""

    linear: np.ndarray  # (H, W, 3) float32 camera RGB, clipped to [0, 1]
    display: np.ndarray  # (H, W, 3) uint8 sRGB encoding of ``linear``
    clipped: np.ndarray  # (H, W) bool, any channel saturated
    patch_polygons: np.ndarray  # (24, 4, 2) full patch squares TL, TR, BR, BL
    card_corners: np.ndarray  # (4, 2)
    homography: np.ndarray  # (3, 3) canonical chart frame → image
    patch_camera_rgb: np.ndarray  # (24, 3) noiseless camera RGB at each patch centre (before clipping)
    reference: ChartReference
    camera_matrix: np.ndarray
    exposure: float
    meta: dict = field(default_factory=dict)


def _default_corners(height: int, width: int) -> np.ndarray:
    """A mildly keystoned card covering about half the image width, centred."""
    cx, cy, w = width / 2, height / 2, 0.5 * width
    h = w * (CHART_ROWS + 2 * CARD_MARGIN) / (CHART_COLS + 2 * CARD_MARGIN)
    return np.array([[cx - 0.50 * w, cy - 0.46 * h], [cx + 0.47 * w, cy - 0.52 * h],
                     [cx + 0.50 * w, cy + 0.50 * h], [cx - 0.46 * w, cy + 0.47 * h]])


def _clutter(height: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """Linear Rec.709 reflectance of a cluttered scene: smooth colour noise, rectangles, discs, lines."""
    low = rng.uniform(0.05, 0.5, size=(6, 9, 3)).astype(np.float32)
    img = cv2.resize(low, (width, height), interpolation=cv2.INTER_CUBIC)
    for _ in range(40):
        colour_ = tuple(float(c) for c in rng.uniform(0.02, 0.75, 3))
        x0, y0 = int(rng.integers(0, width)), int(rng.integers(0, height))
        size = int(rng.integers(8, max(9, min(height, width) // 5)))
        shape = rng.integers(0, 3)
        if shape == 0:
            cv2.rectangle(img, (x0, y0), (x0 + size, y0 + int(size * rng.uniform(0.3, 1.5))), colour_, -1)
        elif shape == 1:
            cv2.circle(img, (x0, y0), size // 2, colour_, -1)
        else:
            cv2.line(img, (x0, y0), (int(rng.integers(0, width)), int(rng.integers(0, height))), colour_,
                     int(rng.integers(1, 6)))
    return np.clip(img, 0.0, 1.0)


def _chart_reflectance(canon: np.ndarray, reference_rgb: np.ndarray, patch_scale: np.ndarray):
    """Reflectance (N, 3) and on-card mask (N,) at canonical points (N, 2)."""
    x, y = canon[:, 0], canon[:, 1]
    m = CARD_MARGIN
    on_card = (x >= -m) & (x <= CHART_COLS + m) & (y >= -m) & (y <= CHART_ROWS + m)
    col, row = np.floor(x), np.floor(y)
    fx, fy = x - col, y - row
    lo, hi = (1 - PATCH_FRACTION) / 2, (1 + PATCH_FRACTION) / 2
    in_patch = (on_card & (col >= 0) & (col < CHART_COLS) & (row >= 0) & (row < CHART_ROWS)
                & (fx >= lo) & (fx <= hi) & (fy >= lo) & (fy <= hi))
    refl = np.full((canon.shape[0], 3), CARD_REFLECTANCE)
    idx = (row[in_patch] * CHART_COLS + col[in_patch]).astype(int)
    refl[in_patch] = reference_rgb[idx] * patch_scale[idx, None]
    return refl, on_card


def render_chart_photo(camera_matrix: np.ndarray | None = None, *, exposure: float = 0.8,
                       noise_sigma: float = 0.002, vignetting: float = 0.1, corners: np.ndarray | None = None,
                       homography: np.ndarray | None = None, size: tuple[int, int] = (480, 720), seed: int = 0,
                       clipped_patches: tuple[int, ...] | list[int] = (), background: str | np.ndarray = "clutter",
                       edition: str = DEFAULT_EDITION, supersample: int = 3) -> SyntheticChartPhoto:
    """Render a linear camera-RGB photo of a ColorChecker Classic placed by a perspective warp.

    ``camera_matrix`` (3 × 3): camera RGB from linear Rec.709 (cross-talk and white balance).
    ``corners`` (4, 2): image positions (x, y, px) of the card's TL, TR, BR, BL corners, or
    ``homography``: canonical chart frame → image. ``size`` is (height, width). ``clipped_patches``
    (1-based numbers) are made so bright that every channel saturates. ``background`` is
    ``"clutter"``, ``"grey"`` or an (H, W, 3) linear Rec.709 reflectance. Anti-aliased by
    ``supersample``² samples per pixel. Deterministic for a given ``seed``.
    """
    height, width = size
    matrix = DEFAULT_CAMERA_MATRIX if camera_matrix is None else np.asarray(camera_matrix, np.float64)
    reference = reference_chart(edition)
    rng = np.random.default_rng(seed)
    if homography is None:
        corners = _default_corners(height, width) if corners is None else np.asarray(corners, np.float64)
        homography = cv2.getPerspectiveTransform(card_corners_canonical().astype(np.float32),
                                                 corners.astype(np.float32)).astype(np.float64)
    homography = np.asarray(homography, np.float64)
    if isinstance(background, str):
        scene = _clutter(height, width, rng) if background == "clutter" else np.full((height, width, 3), 0.18,
                                                                                      np.float32)
    else:
        scene = np.asarray(background, np.float32)

    patch_scale = np.ones(N_PATCHES)
    cam_ref = reference.rgb @ matrix.T
    for number in clipped_patches:
        i = int(number) - 1
        patch_scale[i] = 1.5 / (exposure * max(float(cam_ref[i].min()), 1e-3))

    inverse = np.linalg.inv(homography)
    card = apply_homography(homography, card_corners_canonical())
    x0, y0 = np.maximum(np.floor(card.min(axis=0)).astype(int) - 1, 0)
    x1, y1 = np.minimum(np.ceil(card.max(axis=0)).astype(int) + 1, [width, height])
    ys, xs = np.mgrid[y0:y1, x0:x1].astype(np.float64)
    box_h, box_w = ys.shape
    chart = np.zeros((box_h, box_w, 3))
    coverage = np.zeros((box_h, box_w))
    for sy in range(supersample):
        for sx in range(supersample):
            px = np.stack([xs + (sx + 0.5) / supersample, ys + (sy + 0.5) / supersample], -1).reshape(-1, 2)
            refl, on_card = _chart_reflectance(apply_homography(inverse, px), reference.rgb, patch_scale)
            chart += (refl * on_card[:, None]).reshape(box_h, box_w, 3)
            coverage += on_card.reshape(box_h, box_w)
    n = supersample * supersample
    alpha = (coverage / n)[..., None]
    scene = scene.astype(np.float64)
    scene[y0:y1, x0:x1] = (1 - alpha) * scene[y0:y1, x0:x1] + chart / n
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)

    r2 = ((xs + 0.5 - width / 2) ** 2 + (ys + 0.5 - height / 2) ** 2) / ((width / 2) ** 2 + (height / 2) ** 2)
    vignette = 1.0 - vignetting * r2
    camera = (exposure * scene) @ matrix.T * vignette[..., None]
    camera = camera + rng.normal(0.0, noise_sigma, camera.shape) if noise_sigma > 0 else camera
    clipped = (camera >= 1.0).any(axis=-1)
    linear = np.clip(camera, 0.0, 1.0).astype(np.float32)

    canon_polygons = patch_squares_canonical()
    polygons = apply_homography(homography, canon_polygons)
    centres = apply_homography(homography, patch_centres_canonical())
    cx = np.clip(centres[:, 0].astype(int), 0, width - 1)
    cy = np.clip(centres[:, 1].astype(int), 0, height - 1)
    patch_camera = exposure * (reference.rgb * patch_scale[:, None]) @ matrix.T * vignette[cy, cx][:, None]
    return SyntheticChartPhoto(
        linear=linear, display=srgb_encode_uint8(linear), clipped=clipped, patch_polygons=polygons,
        card_corners=card, homography=homography,
        patch_camera_rgb=patch_camera, reference=reference, camera_matrix=matrix, exposure=float(exposure),
        meta={"seed": seed, "noise_sigma": noise_sigma, "vignetting": vignetting,
              "clipped_patches": [int(p) for p in clipped_patches]})
