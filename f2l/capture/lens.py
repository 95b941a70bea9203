"""Lens descriptions a photographer can write (``session.toml`` ``[lens]``, overridable per
``[[shots]]``; parsed at ingest into a :class:`~f2l.capture.view_spec.LensSpec`, which checks
keys, types and finite numbers) → a placed :class:`~f2l.capture.cameras.ViewCamera` and a
fall-off gain.

Every pixel quantity is in the **full frame** (the RAW's visible size, COLMAP pixel coordinates:
x right, y down, pixel (i, j) spans [j, j+1] × [i, i+1]); :meth:`Lens.view_camera` maps them to a
merged view that was box-averaged by ``k`` after a centred crop (``x_view = (x - crop_x) / k``).

Geometry, one of
- ``colmap_model`` + ``colmap_params`` (pycolmap's order, full-frame pixels; e.g. OPENCV_FISHEYE
  fx, fy, cx, cy, k1..k4), with an optional ``max_angle_deg`` (the image circle of a fisheye);
- ``projection`` ``equidistant`` (r = f θ), ``equisolid`` (r = 2 f sin(θ/2)) or ``rectilinear``
  (r = f tan θ) with the focal length as ``focal_length_px``, or ``focal_length_mm`` with
  ``sensor_width_mm`` (the frame's width; pixels are square), or EXIF FocalLength with
  ``sensor_width_mm``, or ``fov_deg`` (across the image circle for a fisheye, across the image
  width for rectilinear); ``principal_point_px`` [cx, cy] (default: the frame centre);
  for a fisheye ``image_circle_radius_px``. Fisheye rules: focal + circle → the circle's half
  angle θ_max = r⁻¹(radius); fov + circle → the focal length; focal + fov → the circle; fov alone →
  a circle that spans the short side (f2l's earlier default); focal alone → a hemisphere.
  pycolmap's fisheye models cover at most a hemisphere: θ_max is capped at 90°.

Fall-off (``falloff``; a vignetted image is ``gain × ideal``, so it is divided out; only pixels
that see the scene, i.e. inside the image circle, must have gain > 0):
- ``{model = "polynomial", coefficients = [k1, k2, k3], radius = R}``: g = 1 + k1 ρ² + k2 ρ⁴ +
  k3 ρ⁶, ρ = |p − principal point| / R, R ``"image_circle"`` (default for a fisheye with a
  circle), ``"half_diagonal"`` (default otherwise), ``"half_width"``, ``"half_height"`` or pixels;
- ``{model = "cos4"}``: natural fall-off g = cos⁴ θ, θ the ray's angle off the optical axis;
- ``{model = "flat_field", file = "flat.exr"}``: an image of a uniform field (any HDR format
  :func:`f2l.io.probe_io.read_hdr_image` reads; the full frame's size), normalised to 1 at the
  principal point (mean over a disc of 1% of the short side).
- ``vignetting = [k1, k2, k3]`` (the earlier key) is the polynomial on the half diagonal.

Plausible values (a session.toml is input from outside; :func:`lens_from_view` refuses with a
:class:`LensError` naming the key, and ``f2l ingest`` checks every sky frame's lens with it, so a
lens that cannot place its view is an ingest error, not a merge crash): every number finite; a
focal length in px within :data:`FOCAL_PX_PER_LONG_SIDE` × the frame's long side (however it was
given: ``focal_length_px``, mm with ``sensor_width_mm``, ``fov_deg``, a COLMAP model's fx / fy);
``focal_length_mm`` within :data:`FOCAL_LENGTH_MM_RANGE`, ``sensor_width_mm`` within
:data:`SENSOR_WIDTH_MM_RANGE`; the principal point inside the frame or at most
:data:`PRINCIPAL_POINT_MARGIN` × its width / height outside it; an image-circle radius within
:data:`IMAGE_CIRCLE_PER_LONG_SIDE` × the long side; fall-off coefficients and COLMAP distortion
parameters bounded by :data:`FALLOFF_COEFFICIENT_MAX` / :data:`COLMAP_EXTRA_PARAM_MAX`.

A flat-field ``file`` is read relative to the capture root only when it stays inside it (no
absolute path, no ``..``, no symlink out of the root: :func:`flat_field_path`), unless ingest
recorded that the user allowed paths outside (``f2l ingest --allow-outside``).
"""

from __future__ import annotations

import math
import numbers
import os
from dataclasses import dataclass
from pathlib import Path, PurePosixPath, PureWindowsPath

import numpy as np

from f2l.capture.cameras import ViewCamera, equisolid_coefficients
from f2l.capture.view_spec import PROJECTIONS, RADIUS_NAMES, LensSpec, ViewSpecError

__all__ = ["Lens", "Falloff", "lens_from_view", "lens_of", "PROJECTIONS", "FISHEYES", "LensError",
           "flat_field_path", "FOCAL_PX_PER_LONG_SIDE", "FOCAL_LENGTH_MM_RANGE", "SENSOR_WIDTH_MM_RANGE",
           "PRINCIPAL_POINT_MARGIN", "IMAGE_CIRCLE_PER_LONG_SIDE", "FALLOFF_COEFFICIENT_MAX", "COLMAP_EXTRA_PARAM_MAX"]

FISHEYES = ("equidistant", "equisolid")

FOCAL_PX_PER_LONG_SIDE = (1e-2, 1e2)
"""Plausible focal length in px as a multiple of the frame's long side (px per px): 0.01 × is a
fisheye whose whole hemisphere spans 3% of the frame, 100 × a rectilinear view 0.6° across (a
2000 mm lens on a 36 mm-wide frame is 56 ×)."""
FOCAL_LENGTH_MM_RANGE = (0.1, 1e4)
"""Plausible ``focal_length_mm`` (mm)."""
SENSOR_WIDTH_MM_RANGE = (0.5, 1e3)
"""Plausible ``sensor_width_mm`` (mm): a phone's 1/4" sensor is ~3.6 mm, 8 × 10" film 254 mm."""
PRINCIPAL_POINT_MARGIN = 0.5
"""The principal point may lie at most this fraction of the frame's width (x) / height (y) outside
the frame (a shifted or cropped lens); farther, the description is a mistake."""
IMAGE_CIRCLE_PER_LONG_SIDE = (1e-2, 1e1)
"""Plausible ``image_circle_radius_px`` and polynomial fall-off ``radius`` in px, as a multiple
of the frame's long side."""
FALLOFF_COEFFICIENT_MAX = 1e2
"""Largest |k| of a polynomial fall-off (dimensionless; real lenses are within ±2)."""
COLMAP_EXTRA_PARAM_MAX = 1e3
"""Largest |value| of a COLMAP model's parameters other than focal lengths and principal point
(distortion terms, dimensionless; real ones are within ±10)."""


class LensError(ViewSpecError):
    """A lens description that cannot place the view (for a frame of its size); the message
    names the key, ``key`` holds it (the lens key, e.g. ``focal_length_px`` or ``falloff``; ""
    when none applies).

    >>> try:
    ...     lens_from_view({"projection": "rectilinear"}, 400, 300)
    ... except LensError as error:
    ...     print(error.key)
    focal_length_px
    """


@dataclass(frozen=True)
class Falloff:
    """``model`` "polynomial" (``coefficients``, ``radius_px``), "cos4" or "flat_field" (``file``,
    a path relative to the capture root; ``outside_allowed``: ingest ran with ``--allow-outside``
    and recorded the path as the user gave it).

    >>> lens_from_view({"projection": "equidistant", "fov_deg": 180.0,
    ...                 "vignetting": [-0.2, 0.0, 0.0]}, 400, 300).falloff  # the earlier key
    Falloff(model='polynomial', coefficients=(-0.2, 0.0, 0.0), radius_px=250.0, file=None, outside_allowed=False)
    """

    model: str
    coefficients: tuple[float, ...] = ()
    radius_px: float = 0.0
    file: str | None = None
    outside_allowed: bool = False


@dataclass(frozen=True)
class Lens:
    """A full-frame camera model (``model``, ``params`` in pycolmap's order), its image-circle half
    angle (None: limited by the frame only) and its fall-off.

    A 90° rectilinear lens on a 400 x 300 frame: the principal point (the frame's centre) sees
    along the optical axis (-Z in f2l's camera frame), the frame's right edge 45° off it.

    >>> lens = lens_from_view({"projection": "rectilinear", "fov_deg": 90.0}, 400, 300)
    >>> lens.model, [round(p, 6) for p in lens.params], lens.principal_point
    ('PINHOLE', [200.0, 200.0, 200.0, 150.0], (200.0, 150.0))
    >>> camera = lens.view_camera(400, 300)
    >>> direction, valid = camera.pixel_to_cam_direction([lens.principal_point])
    >>> bool(np.allclose(direction, [[0.0, 0.0, -1.0]])), valid.tolist()
    (True, [True])
    >>> direction, _ = camera.pixel_to_cam_direction([[400.0, 150.0]])
    >>> round(math.degrees(math.acos(-direction[0, 2])), 6)
    45.0
    """

    model: str
    params: tuple[float, ...]
    width: int
    height: int
    max_angle_deg: float | None
    falloff: Falloff | None

    @property
    def principal_point(self) -> tuple[float, float]:
        cam = ViewCamera.from_model(self.model, self.width, self.height, self.params).colmap
        return float(cam.principal_point_x), float(cam.principal_point_y)

    def view_camera(self, view_width: int, view_height: int, k: int = 1, crop_x: int = 0, crop_y: int = 0,
                    **pose_deg) -> ViewCamera:
        """The camera of a view box-averaged by ``k`` after dropping ``crop_x``/``crop_y`` full-frame
        pixels on the left/top: focal lengths / k, principal point (c − crop) / k.

        >>> lens = lens_from_view({"projection": "equidistant", "fov_deg": 180.0}, 400, 300)
        >>> camera = lens.view_camera(200, 150, k=2)  # the view box-averaged by 2
        >>> [round(p, 4) for p in camera.params[:4]]  # fx, fy, cx, cy halved
        [47.7465, 47.7465, 100.0, 75.0]
        >>> direction, _ = camera.pixel_to_cam_direction([[100.0, 75.0]])
        >>> bool(np.allclose(direction, [[0.0, 0.0, -1.0]]))
        True
        """
        base = ViewCamera.from_model(self.model, self.width, self.height, self.params).colmap
        params = list(self.params)
        for i in base.focal_length_idxs():
            params[i] = params[i] / k
        ix, iy = base.principal_point_idxs()
        params[ix], params[iy] = (params[ix] - crop_x) / k, (params[iy] - crop_y) / k
        return ViewCamera.from_model(self.model, view_width, view_height, params,
                                     max_angle_deg=self.max_angle_deg, **pose_deg)

    def gain(self, camera: ViewCamera, k: int = 1, crop_x: int = 0, crop_y: int = 0,
             root: Path | None = None) -> np.ndarray | None:
        """(h, w) float32 fall-off gain at the view's pixel centres (``camera`` from
        :meth:`view_camera`), 1 where the lens sees nothing; None without a fall-off model.
        LensError where a pixel that sees the scene has gain <= 0 or not finite.

        Natural fall-off, cos⁴ of the angle off the axis (1 at the centre):

        >>> lens = lens_from_view({"projection": "rectilinear", "fov_deg": 90.0, "falloff": {"model": "cos4"}},
        ...                       40, 30)
        >>> gain = lens.gain(lens.view_camera(40, 30))
        >>> gain.shape, gain.dtype, round(float(gain[15, 0]), 3), round(math.cos(math.atan(19.5 / 20)) ** 4, 3)
        ((30, 40), dtype('float32'), 0.263, 0.263)
        >>> print(lens_from_view({"projection": "rectilinear", "fov_deg": 90.0}, 40, 30).gain(None))
        None
        """
        f = self.falloff
        if f is None:
            return None
        h, w = camera.height, camera.width
        valid = camera.valid_pixel_mask()
        if f.model == "polynomial":
            cx, cy = self.principal_point
            x = crop_x + k * (np.arange(w, dtype=np.float64) + 0.5) - cx
            y = crop_y + k * (np.arange(h, dtype=np.float64) + 0.5) - cy
            r2 = (x[None, :] ** 2 + y[:, None] ** 2) / f.radius_px**2
            g = np.ones_like(r2)
            for i, c in enumerate(f.coefficients):
                g += c * r2 ** (i + 1)
        elif f.model == "cos4":
            yy, xx = np.mgrid[0:h, 0:w] + 0.5
            d, ok = camera.pixel_to_cam_direction(np.stack([xx.ravel(), yy.ravel()], axis=1))
            g = np.where(ok, np.nan_to_num(-d[:, 2]) ** 4, 1.0).reshape(h, w)
        else:
            g = self._flat_field(root, k, crop_x, crop_y, h, w)
        g = np.where(valid, g, 1.0)
        bad = valid & ~(np.isfinite(g) & (g > 0))
        if bad.any():
            low = float(np.nanmin(np.where(valid, g, np.inf)))
            raise LensError(f"fall-off gain is not positive where the lens sees the scene "
                            f"({int(bad.sum())} px, min {low:g}): {f}")
        return g.astype(np.float32)

    def _flat_field(self, root, k, crop_x, crop_y, h, w) -> np.ndarray:
        from f2l.io.probe_io import read_hdr_image

        path = flat_field_path(self.falloff, root)
        flat = read_hdr_image(path).astype(np.float64).mean(axis=2)
        if flat.shape != (self.height, self.width):
            raise LensError(f"{path}: flat field is {flat.shape[1]}x{flat.shape[0]}, the frames are "
                            f"{self.width}x{self.height}")
        cx, cy = self.principal_point
        yy, xx = np.mgrid[0:self.height, 0:self.width] + 0.5
        disc = np.hypot(xx - cx, yy - cy) <= max(1.0, 0.01 * min(self.width, self.height))
        centre = float(flat[disc].mean())
        if not (math.isfinite(centre) and centre > 0):
            raise LensError(f"{path}: flat field is not positive at the principal point")
        block = flat[crop_y:crop_y + h * k, crop_x:crop_x + w * k]
        return block.reshape(h, k, w, k).mean(axis=(1, 3)) / centre


def flat_field_path(falloff: Falloff, root: str | os.PathLike | None) -> Path:
    """The file of a flat-field fall-off: ``root / file`` (``root`` the capture root), refused
    (LensError) where ``file`` is absolute, climbs with ``..`` or resolves (symlinks followed)
    outside ``root``, unless ``falloff.outside_allowed``; ``file`` itself when ``root`` is None
    (a caller's own path).

    >>> flat_field_path(Falloff("flat_field", file="flat.exr"), "/data/session").as_posix()
    '/data/session/flat.exr'
    >>> try:
    ...     flat_field_path(Falloff("flat_field", file="../flat.exr"), "/data/session")
    ... except LensError as error:
    ...     print(error)
    falloff file '../flat.exr' leaves the capture folder (f2l ingest --allow-outside allows it)
    """
    name = str(falloff.file)
    if root is None:
        return Path(name)
    if falloff.outside_allowed:
        return Path(root) / name
    hint = "f2l ingest --allow-outside allows it"
    if PurePosixPath(name).is_absolute() or PureWindowsPath(name).is_absolute() or PureWindowsPath(name).drive:
        raise LensError(f"falloff file {name!r} is an absolute path, not a path inside the capture folder ({hint})",
                        "falloff")
    if ".." in PurePosixPath(name.replace("\\", "/")).parts:
        raise LensError(f"falloff file {name!r} leaves the capture folder ({hint})", "falloff")
    base = os.path.realpath(root)
    real = os.path.realpath(Path(root) / name)
    if os.path.commonpath([base, real]) != base:
        raise LensError(f"falloff file {name!r} resolves to {real}, outside the capture folder {base} "
                        f"(a symbolic link; {hint})", "falloff")
    return Path(root) / name


def _number(view: dict, key: str, lo: float | None = None, hi: float | None = None,
            unit: str = "") -> float | None:
    value = view.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise LensError(f"{key} must be a positive number, got {value!r}", key)
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise LensError(f"{key} = {value:g}{unit} is implausible (expected {lo:g}..{hi:g}{unit})", key)
    return float(value)


def _check_focal(focal: float, key: str, width: int, height: int) -> None:
    lo, hi = (f * max(width, height) for f in FOCAL_PX_PER_LONG_SIDE)
    if not (math.isfinite(focal) and lo <= focal <= hi):
        raise LensError(f"{key} gives a focal length of {focal:g} px, implausible for a {width}x{height} frame "
                        f"(expected {lo:g}..{hi:g} px: {FOCAL_PX_PER_LONG_SIDE[0]:g}..{FOCAL_PX_PER_LONG_SIDE[1]:g} x "
                        f"the long side)", key)


def _check_principal_point(cx: float, cy: float, key: str, width: int, height: int) -> None:
    m = PRINCIPAL_POINT_MARGIN
    if not (math.isfinite(cx) and math.isfinite(cy) and -m * width <= cx <= (1 + m) * width
            and -m * height <= cy <= (1 + m) * height):
        raise LensError(f"{key} [{cx:g}, {cy:g}] is outside the {width}x{height} frame (at most {m:g} x its "
                        f"width / height outside it is accepted)", key)


def _check_frame(width, height) -> None:
    if not (isinstance(width, numbers.Integral) and isinstance(height, numbers.Integral) and width > 0 and height > 0):
        raise LensError(f"the frame's size {width!r} x {height!r} px is not known")


def _focal_px(view: dict, width: int, exif_focal_mm: float | None) -> tuple[float | None, str]:
    """(focal length in full-frame px or None, where it came from)."""
    if "focal_length_px" in view:
        return _number(view, "focal_length_px"), "focal_length_px"
    sensor = _number(view, "sensor_width_mm", *SENSOR_WIDTH_MM_RANGE, " mm")
    mm = _number(view, "focal_length_mm", *FOCAL_LENGTH_MM_RANGE, " mm")
    if mm is not None and sensor is None:
        raise LensError("focal_length_mm needs sensor_width_mm (the frame's width in mm) to give pixels",
                        "focal_length_mm")
    if sensor is not None:
        if mm is None and exif_focal_mm:
            mm = float(exif_focal_mm)
            return mm * width / sensor, "EXIF FocalLength"
        if mm is not None:
            return mm * width / sensor, "focal_length_mm"
    return None, ""


def _r_of_theta(projection: str, theta: float) -> float:
    return theta if projection == "equidistant" else 2.0 * math.sin(theta / 2)


def _theta_of_r(projection: str, r_over_f: float) -> float:
    if projection == "equidistant":
        return r_over_f
    return 2.0 * math.asin(min(1.0, r_over_f / 2))


def _falloff(view: dict, circle_px: float | None, width: int, height: int) -> Falloff | None:
    spec = view.get("falloff")
    if spec is None and view.get("vignetting"):
        spec = {"model": "polynomial", "coefficients": list(view["vignetting"]), "radius": "half_diagonal"}
    if spec is None:
        return None
    model = spec.get("model")
    if model == "cos4":
        return Falloff("cos4")
    if model == "flat_field":
        if not spec.get("file"):
            raise LensError("falloff model flat_field needs file = \"...\" (relative to the session folder)",
                            "falloff")
        return Falloff("flat_field", file=str(spec["file"]), outside_allowed=spec.get("allow_outside") is True)
    if model != "polynomial":
        raise LensError(f"falloff model must be polynomial, cos4 or flat_field, got {model!r}", "falloff")
    coeffs = tuple(float(c) for c in spec.get("coefficients", ()))
    if not all(math.isfinite(c) and abs(c) <= FALLOFF_COEFFICIENT_MAX for c in coeffs):
        raise LensError(f"falloff coefficients {list(coeffs)} must be finite and at most {FALLOFF_COEFFICIENT_MAX:g} "
                        f"in magnitude", "falloff")
    radius = spec.get("radius", "image_circle" if circle_px else "half_diagonal")
    named = {"half_diagonal": 0.5 * math.hypot(width, height), "half_width": 0.5 * width,
             "half_height": 0.5 * height, "image_circle": circle_px}
    if isinstance(radius, str):
        if radius not in named:
            raise LensError(f"falloff radius must be one of {', '.join(RADIUS_NAMES)} or pixels, got {radius!r}",
                            "falloff")
        if named[radius] is None:
            raise LensError("falloff radius image_circle needs a fisheye lens with an image circle", "falloff")
        radius_px = float(named[radius])
    else:
        radius_px = float(radius)
        lo, hi = (f * max(width, height) for f in IMAGE_CIRCLE_PER_LONG_SIDE)
        if not (math.isfinite(radius_px) and lo <= radius_px <= hi):
            raise LensError(f"falloff radius must be {lo:g}..{hi:g} px for a {width}x{height} frame, got {radius!r}",
                            "falloff")
    return Falloff("polynomial", coeffs, radius_px)


def lens_of(spec: LensSpec, width: int, height: int, exif_focal_mm: float | None = None) -> Lens:
    """The :class:`Lens` a view spec's lens (:class:`~f2l.capture.view_spec.LensSpec`, decoded
    from a row's ``view_json``) describes for a full frame of ``width`` × ``height`` px
    (:func:`lens_from_view`).

    >>> lens = lens_of(LensSpec(projection="rectilinear", fov_deg=90), 400, 300)
    >>> lens.model, lens.principal_point
    ('PINHOLE', (200.0, 150.0))
    """
    return lens_from_view(spec.as_dict(), width, height, exif_focal_mm)


def lens_from_view(view: dict, width: int, height: int, exif_focal_mm: float | None = None) -> Lens:
    """The :class:`Lens` a lens description (the lens keys of a session TOML view, as a dict)
    describes for a full frame of ``width`` × ``height`` px (LensError naming the missing,
    inconsistent or implausible key: module doc).

    An 8 mm equisolid fisheye on a 36 mm-wide, 600 px frame (f = 133.3 px) with a 150 px image
    circle sees 2 asin(150 / (2 f)) = 68.5° off its axis:

    >>> lens = lens_from_view({"projection": "equisolid", "focal_length_mm": 8.0, "sensor_width_mm": 36.0,
    ...                        "image_circle_radius_px": 150}, 600, 400)
    >>> lens.model, [round(p, 4) for p in lens.params[:4]], round(lens.max_angle_deg, 3)
    ('OPENCV_FISHEYE', [133.3333, 133.3333, 300.0, 200.0], 68.458)
    >>> lens_from_view({"colmap_model": "opencv_fisheye", "colmap_params": [100, 100, 210, 150, 0, 0, 0, 0]},
    ...                400, 300).principal_point
    (210.0, 150.0)
    >>> try:
    ...     lens_from_view({"projection": "fisheye"}, 400, 300)
    ... except LensError as error:
    ...     print(error.key)
    projection
    """
    _check_frame(width, height)
    circle_range = tuple(f * max(width, height) for f in IMAGE_CIRCLE_PER_LONG_SIDE)
    if "colmap_model" in view:
        model = str(view["colmap_model"]).upper()
        try:
            params = tuple(float(p) for p in view.get("colmap_params", ()))
            cam = ViewCamera.from_model(model, width, height, params).colmap
        except (ValueError, TypeError) as exc:
            raise LensError(f"colmap_model {model}: {exc}", "colmap_params") from None
        if not all(math.isfinite(p) for p in params):
            raise LensError(f"colmap_params {list(params)} must be finite numbers", "colmap_params")
        focal_idx, pp_idx = list(cam.focal_length_idxs()), list(cam.principal_point_idxs())
        for i in focal_idx:
            _check_focal(params[i], "colmap_params (focal length)", width, height)
        _check_principal_point(params[pp_idx[0]], params[pp_idx[1]], "colmap_params (principal point)", width, height)
        extra = [p for i, p in enumerate(params) if i not in focal_idx + pp_idx]
        if any(abs(p) > COLMAP_EXTRA_PARAM_MAX for p in extra):
            raise LensError(f"colmap_params distortion terms {extra} exceed {COLMAP_EXTRA_PARAM_MAX:g} in magnitude",
                            "colmap_params")
        max_angle = _number(view, "max_angle_deg", 0.0, 180.0, "°")
        circle = _number(view, "image_circle_radius_px", *circle_range, " px")
        return Lens(model, params, width, height, max_angle, _falloff(view, circle, width, height))
    projection = view.get("projection")
    if projection not in PROJECTIONS:
        raise LensError(f"no usable lens projection (got {projection!r}; session.toml [lens] projection must be "
                        f"one of {', '.join(PROJECTIONS)}, or colmap_model with colmap_params)", "projection")
    pp = view.get("principal_point_px", [width / 2, height / 2])
    if not (isinstance(pp, (list, tuple)) and len(pp) == 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in pp)):
        raise LensError(f"principal_point_px must be [cx, cy], got {pp!r}", "principal_point_px")
    cx, cy = (float(v) for v in pp)
    _check_principal_point(cx, cy, "principal_point_px", width, height)
    focal, focal_key = _focal_px(view, width, exif_focal_mm)
    fov = _number(view, "fov_deg")
    if projection == "rectilinear":
        if focal is None:
            if fov is None:
                raise LensError("no focal length: give focal_length_px, focal_length_mm with sensor_width_mm, "
                                "or fov_deg (session.toml [lens])", "focal_length_px")
            if not fov < 180:
                raise LensError(f"rectilinear fov_deg must be below 180, got {fov:g}", "fov_deg")
            focal, focal_key = (width / 2) / math.tan(math.radians(fov) / 2), "fov_deg"
        _check_focal(focal, focal_key, width, height)
        return Lens("PINHOLE", (focal, focal, cx, cy), width, height, None, _falloff(view, None, width, height))
    circle = _number(view, "image_circle_radius_px", *circle_range, " px")
    if fov is not None and not fov <= 360:
        raise LensError(f"fov_deg must be at most 360, got {fov:g}", "fov_deg")
    half = None if fov is None else math.radians(fov) / 2
    if focal is None and half is None:
        raise LensError("no focal length or field of view: give focal_length_px, focal_length_mm with "
                        "sensor_width_mm, or fov_deg (session.toml [lens])", "focal_length_px")
    if focal is None:
        circle = circle if circle is not None else min(width, height) / 2
        focal, focal_key = circle / _r_of_theta(projection, half), "fov_deg"
    elif half is None:
        half = math.pi / 2 if circle is None else _theta_of_r(projection, circle / focal)
    _check_focal(focal, focal_key, width, height)
    half = min(half, math.pi / 2)  # pycolmap's fisheye models: at most a hemisphere
    circle = focal * _r_of_theta(projection, half) if circle is None else circle
    k = (0.0, 0.0, 0.0, 0.0) if projection == "equidistant" else equisolid_coefficients(half)
    return Lens("OPENCV_FISHEYE", (focal, focal, cx, cy, *k), width, height, math.degrees(half),
                _falloff(view, circle, width, height))
