"""One photo → face records: landmarks, metric mesh, working-resolution pixels, skin mask, transport.

For each face the landmarker finds (:mod:`f2l.face.landmarker`, score order):

1. reject faces that are too small (narrower than ``min_face_px``: :func:`face_width_px`), cut off by the frame
   (> ``max_outside_fraction`` of the landmarks outside), blurred (blur index of its central box
   above ``max_blur_index``: :mod:`f2l.face.quality`), or in profile (|yaw| > ``max_yaw_deg``);
2. lift the landmarks to a metric mesh (:func:`f2l.face.geometry.reconstruct_vertices`),
   Loop-subdivide it, and rasterise the working view (a square crop around the face resampled
   to ``resolution`` px) from the photo's camera: points, normals;
3. observed linear RGB: the photo's linear image averaged over each working pixel's footprint
   (``k × k`` bilinear samples, k = ceil(footprint) ≤ 8); a working pixel is clipped if any
   sample is, near-black if all are;
4. skin mask: inside the face oval and off the features and border (:mod:`f2l.face.regions`;
   the border's upper-forehead band kept where its colour is the skin's, ``hairline``,
   :mod:`f2l.face.hair`), not clipped, not near-black; a face is refused as ``clipped`` when more
   than ``max_clipped_fraction`` of its skin is clipped (overexposed), as ``too_few_pixels`` when
   fewer than ``min_mask_pixels`` usable skin pixels remain;
5. visibility bits on the lighting grid (:func:`f2l.transport.compute_visibility`), traced
   for the pixels the estimator uses (``transport_pixels="mask"``, the default: the skin mask
   and the clipped skin pixels, which sun models read as censored observations) or for every
   face pixel (``"all"``). With ``"mask"``, the other pixels (features, border, near-black,
   many of them grazing) hold their front-facing hemisphere without self-shadowing, and the
   record's ``meta["transport"]`` says so; the estimator and the metrics never read them.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from f2l.face import geometry
from f2l.lighting.grid import LatLongGrid

MAX_SAMPLES_PER_AXIS = 8
TRANSPORT_PIXELS = ("mask", "all")
HAIRLINE_MODES = ("colour", "exclude", "keep")


@dataclass(frozen=True)
class FitOptions:
    """Parameters of :func:`fit_photo_faces` (all recorded in each face's meta)."""

    resolution: int = 104
    margin: float = 0.08
    subdivisions: int = 2
    depth_source: str = "rigid"
    grid: LatLongGrid = field(default_factory=LatLongGrid)
    visibility_method: str = "adaptive"
    lattice_levels: int = 1
    transport_pixels: str = "mask"
    threads: int = 2
    min_face_px: float = 40.0
    max_yaw_deg: float = 50.0
    max_outside_fraction: float = 0.02
    min_mask_pixels: int = 200
    max_clipped_fraction: float = 0.5  # refuse a face whose skin is more clipped than this
    max_blur_index: float = 0.55  # refuse a blurrier face (f2l.face.quality.MAX_BLUR_INDEX); 1 keeps all
    max_faces: int = 0  # the first so many detections (score order); 0: every face
    body_proxy: bool = False  # a neck-and-shoulders occluder posed with the head (f2l.face.body)
    # the upper forehead's hairline band (f2l.face.regions): "colour" keeps its pixels that have
    # the skin's colour (f2l.face.hair), "exclude" leaves it all out (the default until
    # 2026-11-27), "keep" keeps it all
    hairline: str = "colour"

    def to_meta(self) -> dict:
        return {"resolution": self.resolution, "margin": self.margin,
                "subdivisions": self.subdivisions, "depth_source": self.depth_source,
                "grid": [self.grid.height, self.grid.width],
                "visibility_method": self.visibility_method,
                "lattice_levels": self.lattice_levels,
                "transport_pixels": self.transport_pixels, "min_face_px": self.min_face_px,
                "max_yaw_deg": self.max_yaw_deg,
                "max_outside_fraction": self.max_outside_fraction, "body_proxy": self.body_proxy,
                "hairline": self.hairline, "max_clipped_fraction": self.max_clipped_fraction,
                "max_blur_index": self.max_blur_index}


@dataclass
class FaceFit:
    """A fitted face at working resolution (arrays over its N face pixels)."""

    face_index: int
    landmarks: np.ndarray        # (478, 3) photo px
    head: geometry.HeadFit
    view: geometry.WorkingView
    pixel_rc: np.ndarray         # (N, 2) int32 working (row, col)
    points: np.ndarray           # (N, 3) cm, camera frame
    normals: np.ndarray          # (N, 3) unit
    observed_rgb: np.ndarray     # (N, 3) linear
    mask: np.ndarray             # (N,) usable skin
    excluded: dict               # reason -> (N,) bool
    visibility_bits: np.ndarray  # (N, ceil(L/8)) uint8
    traced: np.ndarray           # (N,) bool: visibility ray-traced (else front hemisphere only)
    crop_display: np.ndarray     # (R, R, 3) uint8 working crop of the display image
    detection_score: float
    presence: float
    timings: dict
    blur_index: float | None = None  # f2l.face.quality (Crete et al. 2007): 0 sharp ... 1 blurred

    @property
    def num_pixels(self) -> int:
        return int(len(self.pixel_rc))

    def counts(self) -> dict:
        out = {"num_pixels": self.num_pixels, "num_masked": int(self.mask.sum())}
        out.update({f"num_{k}": int(v.sum()) for k, v in self.excluded.items()})
        return out


@dataclass(frozen=True)
class Rejected:
    """A detected face that is not turned into a record: ``reason`` is a status code."""

    face_index: int
    reason: str
    message: str
    box: tuple[float, float, float, float] | None = None  # the face's landmark box, photo px


GREYSCALE_TOLERANCE = 2e-3


def is_greyscale(rgb: np.ndarray) -> bool:
    """True when every pixel's channels agree to ``GREYSCALE_TOLERANCE`` of its brightest: a greyscale
    photo (or a colourless face), which says nothing about the light's colour."""
    rgb = np.asarray(rgb, np.float64).reshape(-1, 3)
    if not len(rgb):
        return False
    spread = rgb.max(1) - rgb.min(1)
    return bool((spread <= GREYSCALE_TOLERANCE * np.maximum(rgb.max(1), 1e-6)).all())


def landmark_box(landmarks: np.ndarray) -> tuple[float, float, float, float]:
    """(x0, y0, x1, y1) of a face's mesh landmarks in photo px."""
    xy = np.asarray(landmarks, np.float64)[: geometry.NUM_MESH_LANDMARKS, :2]
    lo, hi = xy.min(0), xy.max(0)
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


# ---------------------------------------------------------------------------------------------
def _footprint_samples(view: geometry.WorkingView):
    """Photo sample positions (R, R, k*k, 2) and k for every working pixel's footprint."""
    k = int(min(MAX_SAMPLES_PER_AXIS, max(1, math.ceil(view.step))))
    r = view.resolution
    sub = (np.arange(k) + 0.5) / k  # within the working pixel, in working units
    cols = (np.arange(r)[:, None] + sub[None, :]).ravel()  # (R*k,)
    xs = view.x0 + cols * view.step
    ys = view.y0 + cols * view.step
    return xs, ys, k


def _taps(coords: np.ndarray, size: int, order: int):
    """Separable interpolation taps along one axis for pixel-centre coordinates ``coords``
    (pixel i covers [i, i + 1)): (indices (n, 2), weights (n, 2)); edge pixels are repeated
    beyond the image (scipy.ndimage's mode="nearest")."""
    c = coords - 0.5
    if order == 0:
        i0 = np.floor(c + 0.5).astype(np.int64)
        idx = np.clip(np.stack([i0, i0], axis=1), 0, size - 1)
        return idx, np.tile(np.float32([1.0, 0.0]), (len(c), 1))
    i0 = np.floor(c).astype(np.int64)
    w1 = (c - i0).astype(np.float32)
    idx = np.clip(np.stack([i0, i0 + 1], axis=1), 0, size - 1)
    return idx, np.stack([1.0 - w1, w1], axis=1)


def _resample(image: np.ndarray, xs: np.ndarray, ys: np.ndarray, k: int, order: int):
    """Sample (H, W, C) or (H, W) at the separable grid (ys × xs), photo coordinates, bilinear
    (order 1) or nearest (order 0); returns (R, R, k*k, C) (or without C): each working pixel's
    k×k samples. Rows first, then columns: two small gathers instead of one per sample."""
    img = image if image.ndim == 3 else image[..., None]
    img = img.astype(np.float32, copy=False)
    (ry, wy), (rx, wx) = _taps(ys, img.shape[0], order), _taps(xs, img.shape[1], order)
    rows = img[ry[:, 0]] * wy[:, 0, None, None] + img[ry[:, 1]] * wy[:, 1, None, None]
    out = rows[:, rx[:, 0]] * wx[None, :, 0, None] + rows[:, rx[:, 1]] * wx[None, :, 1, None]
    r = len(xs) // k
    out = out.reshape(r, k, r, k, -1).transpose(0, 2, 1, 3, 4).reshape(r, r, k * k, -1)
    return out[..., 0] if image.ndim == 2 else out


def _photo_window(view: geometry.WorkingView, hw: tuple[int, int]):
    """The photo rows (sorted, unique) and columns [c0, c1) that a view's footprints read."""
    xs, ys, _ = _footprint_samples(view)
    (ry1, _), (rx1, _) = _taps(ys, hw[0], 1), _taps(xs, hw[1], 1)
    return np.unique(ry1), int(rx1.min()), int(rx1.max()) + 1


def _outside_fraction(xy: np.ndarray, hw: tuple[int, int]) -> float:
    h, w = hw
    out = (xy[:, 0] < 0) | (xy[:, 0] > w) | (xy[:, 1] < 0) | (xy[:, 1] > h)
    return float(out.mean())


def sky_visibility(bits: np.ndarray, grid: LatLongGrid) -> np.ndarray:
    """Solid-angle fraction (N,) of the upper hemisphere that each pixel sees (visible bits).

    Read from the packed bits (little bit order, texels row-major from the zenith): each byte of
    the upper hemisphere's rows indexes a table of the solid angle its 8 texels add up to, so no
    (N, texels) array is made."""
    half = grid.height // 2 * grid.width
    sa = np.asarray(grid.solid_angles, np.float64).reshape(-1)[:half]
    nbytes = -(-half // 8)
    sa = np.concatenate([sa, np.zeros(nbytes * 8 - half)]).reshape(nbytes, 8)
    codes = np.arange(256)[:, None] >> np.arange(8)[None, :] & 1  # (256, 8) little bit order
    table = sa @ codes.T.astype(np.float64)  # (nbytes, 256): solid angle of each byte value
    upper = np.asarray(bits)[:, :nbytes]
    if half % 8:  # the last byte also holds lower-hemisphere texels: keep only the upper ones
        upper = upper.copy()
        upper[:, -1] &= (1 << (half % 8)) - 1
    return table[np.arange(nbytes)[None, :], upper].sum(1) / sa.sum()


# ---------------------------------------------------------------------------------------------
def fit_face(photo, landmarks, face_index: int, options: FitOptions,
             detection_score: float = 1.0, presence: float = 1.0, visibility=None) -> FaceFit | Rejected:
    """Fit one face of ``photo`` (:class:`f2l.io.photo.Photo`) from its (478, 3) landmarks.

    ``visibility``: optional ``(points, normals, head) -> packed bits`` for the traced pixels in
    place of ray casting (a video's head reuses its cached transport: :mod:`f2l.video.head`)."""
    from f2l.face.quality import face_blur_index
    from f2l.face.regions import skin_regions
    from f2l.face.mesh import canonical_face_mesh
    from f2l.transport.visibility import compute_visibility, front_mask, packed_width

    if options.transport_pixels not in TRANSPORT_PIXELS:
        raise ValueError(f"transport_pixels must be one of {TRANSPORT_PIXELS}, "
                         f"got {options.transport_pixels!r}")
    t0 = time.perf_counter()
    hw = photo.shape
    lm = np.asarray(landmarks, dtype=np.float64)
    mesh_xy = lm[: geometry.NUM_MESH_LANDMARKS, :2]
    size_px = face_width_px(lm)
    if size_px < options.min_face_px:
        return Rejected(face_index, "too_small",
                        f"face {face_index} is {size_px:.0f} px wide < {options.min_face_px:.0f} px")
    outside = _outside_fraction(mesh_xy, hw)
    if outside > options.max_outside_fraction:
        return Rejected(face_index, "cut_off", f"face {face_index}: {outside:.0%} of its "
                        f"landmarks lie outside the frame")
    view = geometry.working_view(lm, options.resolution, options.margin)
    rows, c0, c1 = _photo_window(view, hw)
    if hasattr(photo, "ensure_window"):  # a streamed photo: the fit's window, read once, holds the blur's box
        photo.ensure_window((rows[0], rows[-1] + 1, c0, c1))
    blur = face_blur_index(photo, mesh_xy, size_px)
    if blur is not None and blur > options.max_blur_index:
        return Rejected(face_index, "blurred", f"face {face_index}: blur index {blur:.2f} > "
                        f"{options.max_blur_index:.2f} (out of focus or moving): too little detail to fit")
    canon, tri, _ = canonical_face_mesh()
    head = geometry.reconstruct_vertices(lm, photo.focal_px, hw, canon, options.depth_source)
    if abs(head.yaw_deg) > options.max_yaw_deg:
        return Rejected(face_index, "profile", f"face {face_index}: head yaw {head.yaw_deg:+.0f}°"
                        f" exceeds ±{options.max_yaw_deg:.0f}° (profile view)")
    v, f, vn = geometry.subdivided_mesh(head.vertices, tri, options.subdivisions)
    r = view.resolution
    rc_all = np.stack(np.divmod(np.arange(r * r), r), axis=1)
    rays = geometry.rays_for(view.photo_xy(rc_all), photo.focal_px, hw)
    hit, points, normals = geometry.rasterise(v, f, vn, rays)
    pixel_rc = rc_all[hit].astype(np.int32)

    xs, ys, k = _footprint_samples(view)
    # only the photo's rows and columns that the footprints touch are read (a large photo is
    # never converted whole: Photo.rows; a streamed one reads just this window at full
    # resolution: StreamedPhoto.rows)
    part = photo.rows(rows, slice(c0, c1))
    local_y = np.searchsorted(rows, np.clip(np.floor(ys - 0.5), 0, hw[0] - 1).astype(np.int64))
    ys_l = ys - rows[local_y] + local_y  # footprints in the (rows x [c0, c1)) sub-image
    xs_l = xs - c0

    def sample(image, order):
        return _resample(image, xs_l, ys_l, k, order)

    rgb = sample(part["linear"], 1).mean(2).reshape(-1, 3)[hit]
    clipped = sample(part["clipped"].astype(np.uint8), 0).any(2).ravel()[hit]
    black = sample(part["black"].astype(np.uint8), 0).all(2).ravel()[hit]
    crop = sample(part["display"], 1).mean(2)
    crop = np.clip(np.round(crop), 0, 255).astype(np.uint8)

    centres = pixel_rc[:, ::-1] + 0.5
    reg = skin_regions(view.to_working(lm), centres)
    skin, hair = hairline_skin(reg, rgb, centres, clipped, black, options.hairline)
    border = reg["border"] if options.hairline == "exclude" else reg["border"] & ~reg["hairline"]
    excluded = {"features": reg["features"], "border": border, "hair": hair,
                "clipped": clipped & skin, "black": black & skin & ~clipped}
    mask = skin & ~clipped & ~black
    clipped_fraction = float((clipped & skin).sum()) / max(int(skin.sum()), 1)
    if clipped_fraction > options.max_clipped_fraction:
        return Rejected(face_index, "clipped", f"face {face_index}: {clipped_fraction:.0%} of its skin is clipped "
                        f"(> {options.max_clipped_fraction:.0%}): the photo is overexposed there")
    if int(mask.sum()) < options.min_mask_pixels:
        return Rejected(face_index, "too_few_pixels", f"face {face_index}: {int(mask.sum())} "
                        f"usable skin pixels < {options.min_mask_pixels}")
    t1 = time.perf_counter()
    traced = (mask | excluded["clipped"]) if options.transport_pixels == "mask" else np.ones_like(mask)
    bits = np.zeros((len(mask), packed_width(options.grid)), np.uint8)
    bits[~traced] = np.packbits(front_mask(normals[~traced], options.grid), axis=1,
                                bitorder="little")
    if visibility is not None:
        bits[traced] = visibility(points[traced], normals[traced], head)
    else:
        occluder_v, occluder_f, offset = v, f, None
        if options.body_proxy:  # the ray offset stays the face mesh's (1e-4 of its diagonal)
            from f2l.face.body import with_body_proxy

            occluder_v, occluder_f = with_body_proxy(v, f, head.vertices, canon, head.rotation)
            offset = 1e-4 * float(np.linalg.norm(v.max(0) - v.min(0)))
        bits[traced] = compute_visibility(occluder_v, occluder_f, points[traced], normals[traced], options.grid,
                                          offset=offset, method=options.visibility_method,
                                          threads=options.threads, pixel_rc=pixel_rc[traced],
                                          lattice_levels=options.lattice_levels)
    t2 = time.perf_counter()
    return FaceFit(
        face_index=face_index, landmarks=lm, head=head, view=view, pixel_rc=pixel_rc,
        points=points.astype(np.float32), normals=normals.astype(np.float32),
        observed_rgb=np.maximum(rgb, 0).astype(np.float32), mask=mask, excluded=excluded,
        visibility_bits=bits, traced=traced, crop_display=crop, detection_score=float(detection_score),
        presence=float(presence),
        timings={"geometry_s": round(t1 - t0, 4), "transport_s": round(t2 - t1, 4)},
        blur_index=None if blur is None else round(float(blur), 4),
    )


def hairline_skin(reg: dict, rgb: np.ndarray, xy: np.ndarray, clipped: np.ndarray, black: np.ndarray,
                  mode: str):
    """(skin, hair) masks over pixels with linear ``rgb`` at image points ``xy``: ``reg``'s skin
    plus the pixels of its hairline band that ``mode`` keeps ("exclude": none; "keep": all;
    "colour": those with the colour of the skin below the band,
    :func:`f2l.face.hair.skin_coloured`), and the band's pixels left out as hair."""
    band = reg["hairline"]
    if mode == "exclude":
        return reg["skin"], np.zeros_like(band)
    if mode == "keep":
        keep = band
    else:
        from f2l.face.hair import skin_coloured

        keep = np.zeros_like(band)
        ref = reg["skin"] & ~clipped & ~black
        keep[band] = skin_coloured(rgb[band], xy[band], rgb[ref], xy[ref], candidate_clipped=clipped[band])
    return reg["skin"] | keep, band & ~keep


def face_width_px(landmarks: np.ndarray) -> float:
    """A face's width in photo px: the extent of its mesh landmarks along the eye line
    (landmark 33 → 263), so a tilted head measures as an upright one. The width is what
    ``min_face_px`` and the detector's bands count (a frontal face's detection box is as wide)."""
    xy = np.asarray(landmarks, np.float64)[: geometry.NUM_MESH_LANDMARKS, :2]
    axis = xy[263] - xy[33]
    norm = float(np.hypot(*axis))
    axis = axis / norm if norm > 0 else np.array([1.0, 0.0])
    along = xy @ axis
    return float(along.max() - along.min())


def detection_max_side(shape: tuple[int, int], min_face_px: float) -> int:
    """Long side of the copy faces are detected on: ``DETECTION_MAX_SIDE``, or more where an integer
    box reduction to it would shrink a ``min_face_px`` face below the detector's band (a 50 MP
    photo at the default 40 px is reduced by 2, not 3)."""
    from f2l.face.detector import FULL_RANGE
    from f2l.io.photo import DETECTION_MAX_SIDE

    long_side = max(int(shape[0]), int(shape[1]))
    factor = max(1, int(float(min_face_px) // FULL_RANGE.band_px[0]))
    return max(DETECTION_MAX_SIDE, math.ceil(long_side / factor))


def fit_photo_faces(photo, landmarker, options: FitOptions = FitOptions()):
    """All faces of one photo: a list of :class:`FaceFit` or :class:`Rejected`, score order."""
    t0 = time.perf_counter()
    # a large photo: a reduced copy, where position p is offset + p / scale in the photo; reduced
    # no further than keeps a min_face_px face inside the detector's band
    image, scale, offset = photo.detection_image(detection_max_side(photo.shape, options.min_face_px))
    found = landmarker(image, max_faces=options.max_faces or None, min_face_px=options.min_face_px * scale)
    del image
    landmarks_s = (time.perf_counter() - t0) / max(1, len(found))
    found_points = []
    for lms in found:
        points = lms.points
        if scale != 1.0 or offset != (0.0, 0.0):
            points = points / scale  # x, y and z scale alike
            points[:, :2] += np.asarray(offset, np.float64)
        found_points.append(points)
    if len(found) > 1 and hasattr(photo, "prefetch"):  # a streamed photo: every face's window in one pass
        boxes = []
        for points in found_points:
            rows, c0, c1 = _photo_window(geometry.working_view(np.asarray(points, np.float64), options.resolution,
                                                               options.margin), photo.shape)
            boxes.append((rows[0], rows[-1] + 1, c0, c1))
        photo.prefetch(boxes)
    out = []
    for i, (lms, points) in enumerate(zip(found, found_points)):
        fit = fit_face(photo, points, i, options, lms.detection.score, lms.presence)
        if isinstance(fit, FaceFit):
            fit.timings["landmarks_s"] = round(landmarks_s, 4)
        else:
            fit = replace(fit, box=landmark_box(points))
        out.append(fit)
    return out


def face_record(fit: FaceFit, photo, face_id: str, options: FitOptions, *,
                source_path: str, photo_rel: str | None = None,
                gt_probe_rel: str | None = None):
    """The :class:`f2l.io.shards.FaceRecord` of a fit (pixel_rc in the working crop)."""
    from f2l.io.shards import FaceRecord

    head = fit.head
    meta = {
        "fit": options.to_meta(),
        "crop": {**fit.view.to_meta(), "photo_height": int(photo.shape[0]),
                 "photo_width": int(photo.shape[1])},
        "camera": {"focal_px": float(photo.focal_px), "focal_source": photo.focal_source,
                   "orientation": int(photo.orientation)},
        "pose_deg": {"yaw": head.yaw_deg, "pitch": head.pitch_deg, "roll": head.roll_deg},
        "face_distance_cm": head.distance_cm,
        "landmark_residual_cm": head.residual_cm,
        "detection_score": fit.detection_score,
        "presence": fit.presence,
        "counts": fit.counts(),
        "timings": fit.timings,
        "transport": {"traced_pixels": options.transport_pixels,
                      "num_traced": int(fit.traced.sum()),
                      "untraced_bits": "front-facing hemisphere, no self-shadowing"},
        "exif": photo.exif,
        "photo_kind": photo.kind,
        "greyscale": is_greyscale(fit.observed_rgb),
        "face_box_px": [round(v, 2) for v in landmark_box(fit.landmarks)],
        "face_width_px": round(face_width_px(fit.landmarks), 2),
        "blur_index": fit.blur_index,
    }
    r = fit.view.resolution
    return FaceRecord(
        face_id=face_id, source_path=source_path, face_index=fit.face_index,
        image_height=r, image_width=r, pixel_rc=fit.pixel_rc, points=fit.points,
        normals=fit.normals, observed_rgb=fit.observed_rgb, mask=fit.mask,
        grid_height=options.grid.height, grid_width=options.grid.width,
        visibility_bits=fit.visibility_bits, visibility_method=options.visibility_method,
        gt_probe_path=gt_probe_rel, photo_path=photo_rel, meta=meta,
    )
