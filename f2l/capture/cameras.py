"""View cameras for sphere assembly: pycolmap lens models placed in the f2l world frame.

Frames and pixels
- World (DESIGN.md): +Y up; an unrotated camera looks along -Z with +X to its right.
- f2l camera frame: the world frame of an unrotated camera (+X right, +Y up, looking along -Z).
- COLMAP camera frame: +X right, +Y down, +Z forward, so ``p_colmap = diag(1, -1, -1) p_f2l``.
- Pixel coordinates (COLMAP): x to the right, y down, origin at the top-left corner of the image;
  pixel (row i, col j) spans [j, j+1] x [i, i+1] and its centre is (j + 0.5, i + 0.5).

Orientation: ``world_from_camera = R_y(-yaw) R_x(pitch) R_z(roll)`` (right-handed elementary
rotations), ``d_world = R d_cam``. yaw is the azimuth of the optical axis in the grid convention
(0 = -Z, +90 deg = +X), pitch its elevation (+90 deg looks at the zenith; image-up then points
to world +Z), roll turns the camera about its axis, positive lifting its +X (right) side.
Angles are degrees at the constructors (``*_deg``) and radians in the fields.

pycolmap 4.2.1 behaviour relied on (checked by experiment, see tests/test_capture_sphere.py):
- ``Camera.img_from_cam(points (N, 3))`` -> (N, 2); with the default ``check_cheirality=True`` rows
  with z < machine epsilon are NaN (the single-point overload returns None instead). Without the
  check, points behind the camera are mirrored to wrong pixels.
- The fisheye models (OPENCV_FISHEYE, SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE, THIN_PRISM_FISHEYE,
  and 4.x's FISHEYE / SIMPLE_FISHEYE) project through (x/z, y/z), so they represent at most a
  hemisphere: field of view <= 180 deg, and exactly 90 deg off-axis (z = 0) is already invalid.
- ``Camera.cam_from_img(pixels (N, 2))`` -> normalised (x/z, y/z). For the fisheye models a pixel
  beyond theta_d = pi/2 silently returns the distorted coordinates (a wrong ray, no NaN), so every
  unprojection here is validated by reprojection (residual < 1e-3 px); projections are likewise
  validated by unprojection (catches folded distortion polynomials).
- ``Camera(model=..., width=..., height=..., params=...)`` accepts a wrong number of parameters
  (``verify_params()`` is then False): checked here.
- OPENCV_FISHEYE with k1..k4 = 0 is the ideal equidistant fisheye r = f theta (verified to 1e-12).
  No model is exactly equisolid (r = 2 f sin(theta/2)); it is OPENCV_FISHEYE with k1..k4 fitted by
  least squares over [0, fov/2] (max angular error ~2e-11 rad at fov 180 deg, see
  ``equisolid_max_error_rad``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import pycolmap

__all__ = [
    "ViewCamera", "MirrorBallCamera", "Vignetting", "rotation_from_ypr", "ypr_from_rotation",
    "apply_vignetting", "correct_vignetting", "equisolid_coefficients", "equisolid_max_error_rad",
    "mirror_ball_view", "COLMAP_FROM_F2L",
]  # fmt: skip

COLMAP_FROM_F2L = np.diag([1.0, -1.0, -1.0])
"""Maps f2l camera-frame vectors to COLMAP camera-frame vectors (and back: it is its own inverse)."""

_REPROJ_TOL_PX = 1e-3
_RAY_TOL = 1e-6


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_from_ypr(yaw_rad: float, pitch_rad: float, roll_rad: float) -> np.ndarray:
    """world_from_camera = R_y(-yaw) R_x(pitch) R_z(roll), (3, 3) float64."""
    return _ry(-yaw_rad) @ _rx(pitch_rad) @ _rz(roll_rad)


def ypr_from_rotation(rotation: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`rotation_from_ypr` (radians). At pitch = +-90 deg yaw is set to 0 and
    the whole turn about the vertical goes into roll (gimbal lock)."""
    r = np.asarray(rotation, dtype=np.float64)
    fwd = -r[:, 2]
    pitch = math.asin(float(np.clip(fwd[1], -1.0, 1.0)))
    yaw = math.atan2(fwd[0], -fwd[2]) if math.hypot(fwd[0], fwd[2]) > 1e-12 else 0.0
    rz = _rx(pitch).T @ _ry(yaw) @ r
    return yaw, pitch, math.atan2(rz[1, 0], rz[0, 0])


@dataclass(frozen=True, kw_only=True)
class _Oriented:
    """World placement shared by the camera-like mappings (fields in radians)."""

    yaw_rad: float = 0.0
    pitch_rad: float = 0.0
    roll_rad: float = 0.0

    radiance_gain = 1.0  # image value = radiance_gain * scene radiance along the mapped direction

    @cached_property
    def rotation(self) -> np.ndarray:
        """world_from_camera (3, 3)."""
        return rotation_from_ypr(self.yaw_rad, self.pitch_rad, self.roll_rad)

    def with_rotation(self, rotation: np.ndarray):
        """A copy with world_from_camera = ``rotation``."""
        yaw, pitch, roll = ypr_from_rotation(rotation)
        return dataclasses.replace(self, yaw_rad=yaw, pitch_rad=pitch, roll_rad=roll)

    def direction_to_pixel(self, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World unit directions (N, 3) -> (pixel xy (N, 2), valid (N,)); invalid rows are NaN."""
        return self.cam_direction_to_pixel(np.asarray(directions, dtype=np.float64) @ self.rotation)

    def pixel_to_direction(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel xy (N, 2) -> (world unit directions (N, 3), valid (N,)); invalid rows are NaN."""
        d, valid = self.pixel_to_cam_direction(pixels)
        return d @ self.rotation.T, valid

    def valid_pixel_mask(self) -> np.ndarray:
        """(height, width) bool: pixels whose centre maps to a valid direction (inside a fisheye's
        image circle, a mirror ball's silhouette, ...)."""
        y, x = np.mgrid[0 : self.height, 0 : self.width] + 0.5
        px = np.stack([x.ravel(), y.ravel()], axis=1)
        rows = max(1, (1 << 19) // self.width) * self.width  # bounded memory per call
        ok = np.concatenate([self.pixel_to_cam_direction(px[i : i + rows])[1] for i in range(0, len(px), rows)])
        return ok.reshape(self.height, self.width)

    def _inside(self, px: np.ndarray) -> np.ndarray:
        x, y = px[:, 0], px[:, 1]
        with np.errstate(invalid="ignore"):
            return (x >= 0) & (x <= self.width) & (y >= 0) & (y <= self.height)

    def _border_weight(self, px: np.ndarray) -> np.ndarray:
        """sin(pi x / width) sin(pi y / height): 1 at the image centre, 0 on its border."""
        wx = np.sin(np.pi * np.clip(px[:, 0] / self.width, 0.0, 1.0))
        wy = np.sin(np.pi * np.clip(px[:, 1] / self.height, 0.0, 1.0))
        return np.nan_to_num(wx * wy)


def _check_size(width: int, height: int) -> None:
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise ValueError(f"image size must be positive integers, got {width}x{height}")


@dataclass(frozen=True, kw_only=True)
class ViewCamera(_Oriented):
    """A pycolmap camera model (``model`` name, ``params`` in pycolmap's order) with a world pose.

    ``max_angle_rad``: directions farther than this from the optical axis are invalid (the image
    circle of a circular fisheye); None limits validity only by the model and the image bounds.
    """

    model: str
    width: int
    height: int
    params: tuple[float, ...]
    max_angle_rad: float | None = None

    def __post_init__(self) -> None:
        _check_size(self.width, self.height)
        name = str(self.model).upper()
        if name not in pycolmap.CameraModelId.__members__ or name in ("INVALID", "EQUIRECTANGULAR"):
            raise ValueError(f"unknown or unsupported pycolmap camera model {self.model!r}")
        object.__setattr__(self, "model", name)
        object.__setattr__(self, "params", tuple(float(p) for p in self.params))
        if not all(math.isfinite(p) for p in self.params):
            raise ValueError(f"camera params must be finite, got {self.params}")
        if not self.colmap.verify_params():
            raise ValueError(f"{name} needs params ({self.colmap.params_info}), got {len(self.params)} values")
        if self.max_angle_rad is not None and not 0.0 < self.max_angle_rad <= math.pi:
            raise ValueError(f"max_angle_rad must be in (0, pi], got {self.max_angle_rad}")

    @cached_property
    def colmap(self) -> pycolmap.Camera:
        """The wrapped ``pycolmap.Camera``."""
        return pycolmap.Camera(model=self.model, width=int(self.width), height=int(self.height),
                               params=list(self.params))

    # -- constructors (degrees) -----------------------------------------------------------
    @classmethod
    def from_model(cls, model: str, width: int, height: int, params, *, yaw_deg: float = 0.0,
                   pitch_deg: float = 0.0, roll_deg: float = 0.0,
                   max_angle_deg: float | None = None) -> ViewCamera:
        """Any pycolmap model, e.g. OPENCV_FISHEYE (fx, fy, cx, cy, k1..k4), PINHOLE, OPENCV."""
        return cls(model=model, width=width, height=height, params=tuple(params),
                   yaw_rad=math.radians(yaw_deg), pitch_rad=math.radians(pitch_deg),
                   roll_rad=math.radians(roll_deg),
                   max_angle_rad=None if max_angle_deg is None else math.radians(max_angle_deg))

    @classmethod
    def equidistant(cls, fov_deg: float, width: int, height: int, *, circle_diameter_px: float | None = None,
                    **pose_deg) -> ViewCamera:
        """Ideal equidistant fisheye r = f theta: OPENCV_FISHEYE with zero distortion whose image
        circle (default diameter min(width, height), centred) spans ``fov_deg`` (<= 180)."""
        half = _half_fov(fov_deg)
        f = _circle_radius(width, height, circle_diameter_px) / half
        return cls.from_model("OPENCV_FISHEYE", width, height, (f, f, width / 2, height / 2, 0, 0, 0, 0),
                              max_angle_deg=fov_deg / 2, **pose_deg)

    @classmethod
    def equisolid(cls, fov_deg: float, width: int, height: int, *, circle_diameter_px: float | None = None,
                  **pose_deg) -> ViewCamera:
        """Equisolid fisheye r = 2 f sin(theta / 2) as OPENCV_FISHEYE with fitted k1..k4 (see
        :func:`equisolid_coefficients`); image circle as in :meth:`equidistant`."""
        half = _half_fov(fov_deg)
        f = _circle_radius(width, height, circle_diameter_px) / (2.0 * math.sin(half / 2))
        k = equisolid_coefficients(half)
        return cls.from_model("OPENCV_FISHEYE", width, height, (f, f, width / 2, height / 2, *k),
                              max_angle_deg=fov_deg / 2, **pose_deg)

    @classmethod
    def pinhole(cls, hfov_deg: float, width: int, height: int, **pose_deg) -> ViewCamera:
        """Rectilinear PINHOLE camera with horizontal field of view ``hfov_deg``, square pixels."""
        if not 0.0 < hfov_deg < 180.0:
            raise ValueError(f"pinhole field of view must be in (0, 180) deg, got {hfov_deg}")
        f = (width / 2) / math.tan(math.radians(hfov_deg) / 2)
        return cls.from_model("PINHOLE", width, height, (f, f, width / 2, height / 2), **pose_deg)

    # -- camera-frame mapping -------------------------------------------------------------
    def _angle_ok(self, d_cam: np.ndarray) -> np.ndarray:
        if self.max_angle_rad is None:
            return np.ones(len(d_cam), dtype=bool)
        with np.errstate(invalid="ignore"):
            return -d_cam[:, 2] >= math.cos(self.max_angle_rad) - 1e-12

    def _rays(self, px: np.ndarray) -> np.ndarray:
        n = self.colmap.cam_from_img(px)
        ray = np.concatenate([n, np.ones((len(n), 1))], axis=1)
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        return ray @ COLMAP_FROM_F2L  # row vectors: (C r)^T = r^T C, C symmetric

    def cam_direction_to_pixel(self, d_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """f2l camera-frame unit directions (N, 3) -> (pixel xy (N, 2), valid (N,)).

        Valid: in front of the lens (COLMAP z > 0), within ``max_angle_rad``, inside the image, and
        the pixel unprojects back to the direction (rejects folded distortion)."""
        d = np.asarray(d_cam, dtype=np.float64).reshape(-1, 3)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        px = self.colmap.img_from_cam(np.ascontiguousarray(d @ COLMAP_FROM_F2L))
        valid = np.all(np.isfinite(px), axis=1) & self._angle_ok(d) & self._inside(px)
        if valid.any():
            back = self._rays(px[valid])
            ok = np.linalg.norm(back - d[valid], axis=1)
            valid[np.flatnonzero(valid)[ok > _RAY_TOL]] = False
        px[~valid] = np.nan
        return px, valid

    def pixel_to_cam_direction(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel xy (N, 2) -> (f2l camera-frame unit directions (N, 3), valid (N,)).

        Valid: inside the image, within ``max_angle_rad`` and reprojecting to the pixel within
        1e-3 px (pycolmap's fisheye unprojection is wrong, silently, beyond 90 deg)."""
        px = np.ascontiguousarray(np.asarray(pixels, dtype=np.float64).reshape(-1, 2))
        d = self._rays(px)
        with np.errstate(invalid="ignore"):
            back = self.colmap.img_from_cam(d @ COLMAP_FROM_F2L)
            err = np.linalg.norm(back - px, axis=1)
            valid = self._inside(px) & self._angle_ok(d) & (err < _REPROJ_TOL_PX)
        d[~valid] = np.nan
        return d, valid

    def blend_weight(self, d_cam: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """Weight in [0, 1] favouring the view centre: sin(pi x/w) sin(pi y/h), times
        cos^2(pi/2 * angle/max_angle) when ``max_angle_rad`` is set; 0 at the valid region's edge."""
        w = self._border_weight(np.asarray(pixels, dtype=np.float64))
        if self.max_angle_rad is not None:
            ang = np.arccos(np.clip(-np.asarray(d_cam)[:, 2], -1.0, 1.0))
            w = w * np.cos(0.5 * np.pi * np.clip(np.nan_to_num(ang / self.max_angle_rad, nan=1.0), 0, 1)) ** 2
        return w


def _half_fov(fov_deg: float) -> float:
    if not 0.0 < fov_deg <= 180.0:
        raise ValueError(f"fisheye field of view must be in (0, 180] deg (pycolmap's fisheye models "
                         f"cover at most a hemisphere), got {fov_deg}")
    return math.radians(fov_deg) / 2


def _circle_radius(width: int, height: int, diameter_px: float | None) -> float:
    _check_size(width, height)
    return (min(width, height) if diameter_px is None else float(diameter_px)) / 2


def _equisolid_design(half_fov_rad: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    th = np.linspace(0.0, half_fov_rad, 2001)
    basis = np.stack([th ** (2 * i + 3) for i in range(4)], axis=1)  # theta_d - theta = sum k_i th^(2i+3)
    return th, basis, 2.0 * np.sin(th / 2) - th


def equisolid_coefficients(half_fov_rad: float) -> tuple[float, float, float, float]:
    """OPENCV_FISHEYE k1..k4 with theta (1 + k1 th^2 + ... + k4 th^8) ~= 2 sin(theta / 2) on
    [0, half_fov_rad]: least squares weighted by 1 / cos(theta/2), i.e. in angle error."""
    th, basis, target = _equisolid_design(half_fov_rad)
    w = 1.0 / np.cos(th / 2)
    k = np.linalg.lstsq(basis * w[:, None], target * w, rcond=None)[0]
    return tuple(float(v) for v in k)


def equisolid_max_error_rad(half_fov_rad: float) -> float:
    """Max angular error of the fitted equisolid model on [0, half_fov_rad] (~2e-11 at pi/2)."""
    th, basis, target = _equisolid_design(half_fov_rad)
    k = np.array(equisolid_coefficients(half_fov_rad))
    return float(np.max(np.abs(basis @ k - target) / np.cos(th / 2)))


@dataclass(frozen=True, kw_only=True)
class MirrorBallCamera(_Oriented):
    """A photo of a mirror (chrome) sphere: the standard Debevec light-probe mapping.

    The ball's silhouette is the circle (``centre_px``, ``radius_px``); the camera's pose is
    the yaw/pitch/roll fields. Pixel offset s (in silhouette radii, s <= 1) from the centre, with
    image azimuth a, sees the world along the f2l camera-frame direction
    r = (sin psi cos a, sin psi sin a, cos psi) (psi measured from +Z, toward the camera):
    orthographic (``distance_over_radius`` None): psi = 2 asin(s);
    perspective (camera at D = distance_over_radius ball radii, ball on the optical axis): the
    pinhole ray at tan(beta) = s tan(alpha), sin(alpha) = 1/D, reflected about the sphere normal;
    psi reaches pi - alpha at the rim (a blind cone of half-angle alpha behind the ball).
    Reflectance assumption: an ideal mirror with constant, colourless reflectance
    ``reflectance`` (no Fresnel rise at grazing angles), image = reflectance * L(r). Valid: psi
    <= ``max_reflection_rad`` (default: the whole ball) and s <= 1 - 1/radius_px (one pixel
    inside the rim, so samples never touch the background).
    """

    width: int
    height: int
    centre_px: tuple[float, float]
    radius_px: float
    distance_over_radius: float | None = None
    reflectance: float = 1.0
    max_reflection_rad: float | None = None
    _table: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        _check_size(self.width, self.height)
        if not self.radius_px > 1.0:
            raise ValueError(f"mirror ball radius must exceed 1 px, got {self.radius_px}")
        if self.distance_over_radius is not None and not self.distance_over_radius > 1.0:
            raise ValueError(f"distance_over_radius must exceed 1, got {self.distance_over_radius}")
        if not self.reflectance > 0.0:
            raise ValueError(f"reflectance must be positive, got {self.reflectance}")
        s = np.linspace(0.0, 1.0, 4097)
        object.__setattr__(self, "_table", self.psi_of_s(s))

    @property
    def radiance_gain(self) -> float:
        return float(self.reflectance)

    @property
    def s_max(self) -> float:
        return 1.0 - 1.0 / self.radius_px

    @property
    def psi_max_rad(self) -> float:
        """Largest valid reflection angle from +Z (toward the camera)."""
        psi = float(self.psi_of_s(np.array([self.s_max]))[0])
        return psi if self.max_reflection_rad is None else min(psi, self.max_reflection_rad)

    def psi_of_s(self, s: np.ndarray) -> np.ndarray:
        """Reflection angle psi (rad, from +Z) of normalised silhouette radius s in [0, 1]."""
        s = np.clip(np.asarray(s, dtype=np.float64), 0.0, 1.0)
        if self.distance_over_radius is None:
            return 2.0 * np.arcsin(s)
        k = self.distance_over_radius
        beta = np.arctan(s * math.tan(math.asin(1.0 / k)))
        sb, cb = np.sin(beta), np.cos(beta)
        t = k * cb - np.sqrt(np.clip(1.0 - (k * sb) ** 2, 0.0, None))  # ray/sphere hit, camera at 0
        nx, nz = t * sb, -t * cb + k  # unit normal at the hit (ball centre at (0, 0, -k))
        dn = sb * nx - cb * nz
        return np.arctan2(sb - 2 * dn * nx, -cb - 2 * dn * nz)

    def _s_of_psi(self, psi: np.ndarray) -> np.ndarray:
        if self.distance_over_radius is None:
            return np.sin(np.clip(psi, 0.0, np.pi) / 2)
        return np.interp(psi, self._table, np.linspace(0.0, 1.0, len(self._table)), right=np.nan)

    def cam_direction_to_pixel(self, d_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """f2l camera-frame directions (N, 3) -> (pixel xy (N, 2), valid (N,))."""
        d = np.asarray(d_cam, dtype=np.float64).reshape(-1, 3)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        psi = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
        if self.distance_over_radius is not None:
            psi_fine = np.clip(psi, 0.0, self._table[-1])
            s = self._s_of_psi(psi_fine)
            for _ in range(2):  # Newton polish of the table inverse
                ds = 1e-7
                g = (self.psi_of_s(s + ds) - self.psi_of_s(s - ds)) / (2 * ds)
                s = np.clip(s - (self.psi_of_s(s) - psi_fine) / np.maximum(g, 1e-9), 0.0, 1.0)
        else:
            s = self._s_of_psi(psi)
        rho = np.hypot(d[:, 0], d[:, 1])
        with np.errstate(invalid="ignore", divide="ignore"):
            cos_a = np.where(rho > 0, d[:, 0] / rho, 1.0)
            sin_a = np.where(rho > 0, d[:, 1] / rho, 0.0)
        px = np.stack([self.centre_px[0] + self.radius_px * s * cos_a,
                       self.centre_px[1] - self.radius_px * s * sin_a], axis=1)
        valid = (psi <= self.psi_max_rad + 1e-12) & (s <= self.s_max) & self._inside(px)
        px[~valid] = np.nan
        return px, valid

    def pixel_to_cam_direction(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel xy (N, 2) -> (f2l camera-frame unit directions (N, 3), valid (N,))."""
        px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
        ox = (px[:, 0] - self.centre_px[0]) / self.radius_px
        oy = -(px[:, 1] - self.centre_px[1]) / self.radius_px  # image y down -> camera +Y up
        s = np.hypot(ox, oy)
        psi = self.psi_of_s(s)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos_a = np.where(s > 0, ox / s, 1.0)
            sin_a = np.where(s > 0, oy / s, 0.0)
        d = np.stack([np.sin(psi) * cos_a, np.sin(psi) * sin_a, np.cos(psi)], axis=1)
        valid = (s <= self.s_max) & (psi <= self.psi_max_rad + 1e-12) & self._inside(px)
        d[~valid] = np.nan
        return d, valid

    def blend_weight(self, d_cam: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """cos^2(pi/2 * psi / psi_max): 1 at the ball centre, 0 at the usable rim."""
        psi = np.arccos(np.clip(np.asarray(d_cam)[:, 2], -1.0, 1.0))
        return np.cos(0.5 * np.pi * np.clip(np.nan_to_num(psi / self.psi_max_rad, nan=1.0), 0, 1)) ** 2


def mirror_ball_view(width: int, height: int, centre_px: tuple[float, float], radius_px: float, *,
                     yaw_deg: float = 0.0, pitch_deg: float = 0.0, roll_deg: float = 0.0,
                     distance_over_radius: float | None = None, reflectance: float = 1.0,
                     max_reflection_deg: float | None = None) -> MirrorBallCamera:
    """A :class:`MirrorBallCamera` from degrees; the pose is that of the camera photographing the ball."""
    return MirrorBallCamera(
        width=width, height=height, centre_px=(float(centre_px[0]), float(centre_px[1])),
        radius_px=float(radius_px), distance_over_radius=distance_over_radius, reflectance=reflectance,
        max_reflection_rad=None if max_reflection_deg is None else math.radians(max_reflection_deg),
        yaw_rad=math.radians(yaw_deg), pitch_rad=math.radians(pitch_deg), roll_rad=math.radians(roll_deg),
    )


# -- vignetting ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Vignetting:
    """Radial gain g(r) = 1 + k1 r^2 + k2 r^4 + k3 r^6, r = |p - principal point| / half diagonal
    (p at pixel centres, COLMAP pixel coordinates). A vignetted image is ``g * ideal``."""

    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0

    def gain(self, height: int, width: int, principal_point: tuple[float, float] | None = None) -> np.ndarray:
        """(height, width) float32 gain map; principal point defaults to the image centre."""
        cx, cy = (width / 2, height / 2) if principal_point is None else principal_point
        x = np.arange(width, dtype=np.float64) + 0.5 - cx
        y = np.arange(height, dtype=np.float64) + 0.5 - cy
        r2 = (x[None, :] ** 2 + y[:, None] ** 2) / (0.25 * (width**2 + height**2))
        return (1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))).astype(np.float32)


def _vignette(image: np.ndarray, vignetting: Vignetting, principal_point, invert: bool) -> np.ndarray:
    img = np.asarray(image, dtype=np.float32)
    g = vignetting.gain(img.shape[0], img.shape[1], principal_point)
    if not np.all(g > 0):
        raise ValueError(f"vignetting gain is not positive everywhere (min {float(g.min()):g}): {vignetting}")
    g = g[..., None] if img.ndim == 3 else g
    return img / g if invert else img * g


def apply_vignetting(image: np.ndarray, vignetting: Vignetting,
                     principal_point: tuple[float, float] | None = None) -> np.ndarray:
    """``image * g`` (float32, (H, W) or (H, W, C))."""
    return _vignette(image, vignetting, principal_point, invert=False)


def correct_vignetting(image: np.ndarray, vignetting: Vignetting,
                       principal_point: tuple[float, float] | None = None) -> np.ndarray:
    """``image / g`` (float32): undoes :func:`apply_vignetting`."""
    return _vignette(image, vignetting, principal_point, invert=True)
