"""Capture sessions written as real DNG files, with what a photographer would write in
``session.toml``, for tests and ``f2l dev bench-capture``: they disagree with f2l's conveniences.

- :func:`write_fisheye_session`: an 8 mm equisolid circular fisheye on a 36 x 24 mm sensor
  (1536 x 1024 px; image circle radius 2 f sin 45° = 482.7 px, smaller than the short side),
  looking at the zenith, polynomial fall-off on the circle's radius, described by focal length in
  mm, sensor width and circle radius.
- :func:`write_panorama_session`: a panoramic head's rectilinear views (16 mm, 36 mm wide sensor:
  96.7° x 73.7°) at yaw 0, 60, ..., 300 and pitch 30, plus one at the zenith, a bracket each, all
  in **one folder**, exposures in auto-bracketing order (0, -, +, ...), natural cos⁴ fall-off,
  the focal length from EXIF, one ``[[shots]]`` entry per file.

Both take the sky as linear Rec.709 radiance (a lat-long scene, DESIGN convention) and record the
camera's colour matrix (default: LibRaw's table entry for the Canon EOS 30D, not the identity), so
camera RGB differs from Rec.709 as it does in a real camera. The returned :class:`SessionTruth`
holds what make-probes should recover: the scene divided by the sensor's full-scale radiance.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from datetime import datetime, timedelta
from pathlib import Path

import numpy as np

from f2l.capture.cameras import ViewCamera
from f2l.capture.dng import write_bracket
from f2l.io.raw_meta import rec709_to_camera_matrix
from f2l.capture.sphere import render_view

__all__ = ["CANON_EOS_30D_XYZ_TO_CAMERA", "SessionTruth", "write_fisheye_session", "write_panorama_session",
           "default_sky"]

CANON_EOS_30D_XYZ_TO_CAMERA = (0.6257, -0.0303, -0.1000, -0.7880, 1.5621, 0.2396, -0.1714, 0.1904, 0.7046)
"""XYZ (D65) → camera RGB of the Canon EOS 30D in LibRaw's colour table (``rgb_xyz_matrix`` that
rawpy reports for ``../shared/data/raw/IMG_5952.CR2``), row-major."""

FISHEYE_FRAME = (1536, 1024)
FISHEYE_FOCAL_MM, SENSOR_WIDTH_MM = 8.0, 36.0
FISHEYE_FALLOFF = (-0.20, -0.10)  # 1 - 0.20 rho^2 - 0.10 rho^4, rho relative to the image circle
PANORAMA_FRAME = (768, 512)
PANORAMA_FOCAL_MM = 16.0
FULL_WELL_E = 40000.0  # electrons at white level, ISO 100 (a large-pixel sensor at base ISO)


@dataclass(frozen=True)
class SessionTruth:
    """What a written session should give: ``probe`` (H, W, 3) linear Rec.709 radiance in
    make-probes' units (scene / full-scale radiance, 1.0 = full scale at EV100 0) on the scene's
    grid, the sun's elevation/azimuth (deg) and the files written."""

    probe: np.ndarray
    sun_elevation_deg: float
    sun_azimuth_deg: float
    files: tuple[Path, ...]
    brackets: int


def default_sky(height: int = 1024, sun_elevation_deg: float = 35.0, sun_azimuth_deg: float = 60.0) -> np.ndarray:
    """A clear sky (Preetham-like, κ = 8192 sun, ground below), median sky radiance 1, Rec.709,
    float32. 1024 rows put the 0.6° sun lobe on ~3 texels, so its centre is not a texel centre."""
    from f2l.lighting.grid import LatLongGrid
    from f2l.synth.skies import clear_sky

    sky = clear_sky(LatLongGrid(height, 2 * height), math.radians(sun_elevation_deg),
                    math.radians(sun_azimuth_deg), turbidity=3.0, sun_kappa=8192.0)
    return (sky / float(np.median(sky[: height // 2]))).astype(np.float32)


def _camera_rgb(view_rec709: np.ndarray, xyz_to_camera) -> np.ndarray:
    out = view_rec709.astype(np.float64) @ rec709_to_camera_matrix(xyz_to_camera).T
    return np.maximum(out, 0.0)  # sky colours are inside the camera's gamut; guards rounding only


def _full_scale(view: np.ndarray, exposures_s, f_number: float) -> float:
    """The median lit pixel sits at a quarter of full scale in the longest frame."""
    return 4.0 * float(np.median(view[view.sum(2) > 0])) * max(exposures_s) / f_number**2


def write_fisheye_session(root: str | os.PathLike, scene_rec709: np.ndarray | None = None, *,
                          session: str = "fisheye", xyz_to_camera=CANON_EOS_30D_XYZ_TO_CAMERA,
                          exposures_s=tuple(2.0 ** (k - 12) for k in range(0, 14, 2)), f_number: float = 4.0,
                          sun_elevation_deg: float = 35.0, sun_azimuth_deg: float = 60.0,
                          seed: int = 0) -> SessionTruth:
    """An up-looking circular equisolid fisheye bracket in ``root/session/sky/`` + session.toml."""
    scene = default_sky(sun_elevation_deg=sun_elevation_deg, sun_azimuth_deg=sun_azimuth_deg) \
        if scene_rec709 is None else np.asarray(scene_rec709, np.float32)
    w, h = FISHEYE_FRAME
    f_px = FISHEYE_FOCAL_MM * w / SENSOR_WIDTH_MM
    radius = 2.0 * f_px * math.sin(math.pi / 4)  # 482.7 px
    camera = ViewCamera.equisolid(180.0, w, h, circle_diameter_px=2 * radius, pitch_deg=90.0)
    view, valid = render_view(scene, camera, supersample=2)
    yy, xx = np.mgrid[0:h, 0:w] + 0.5
    rho2 = ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / radius**2
    gain = 1.0 + FISHEYE_FALLOFF[0] * rho2 + FISHEYE_FALLOFF[1] * rho2**2
    view = view * (valid * gain)[..., None]  # black outside the circle (where the gain is < 0)
    fs = _full_scale(view, exposures_s, f_number)
    folder = Path(root) / session
    paths = write_bracket(folder / "sky", _camera_rgb(view, xyz_to_camera), list(exposures_s), f_number=f_number,
                          full_well_e=FULL_WELL_E,
                          iso=100, full_scale_radiance=fs, seed=seed, camera_matrix=np.reshape(xyz_to_camera, (3, 3)),
                          make="Canon", model="EOS 30D", focal_length_mm=FISHEYE_FOCAL_MM, prefix="IMG")
    (folder / "session.toml").write_text(f"""# An 8 mm circular fisheye on a full-frame body, pointing at the zenith.
probe_azimuth_deg = 0.0

[lens]
projection = "equisolid"
focal_length_mm = {FISHEYE_FOCAL_MM}
sensor_width_mm = {SENSOR_WIDTH_MM}
image_circle_radius_px = {radius:.1f}

[lens.falloff]
model = "polynomial"
coefficients = [{FISHEYE_FALLOFF[0]}, {FISHEYE_FALLOFF[1]}]
radius = "image_circle"

[[shots]]
files = "sky/*"
pitch_deg = 90.0
""")
    return SessionTruth(scene / fs, sun_elevation_deg, sun_azimuth_deg, tuple(paths), 1)


def aeb_order(n: int, step_ev: float) -> list[float]:
    """Auto-exposure-bracketing order in EV: 0, -s, +s, -2s, +2s, ..."""
    out = [0.0]
    k = 1
    while len(out) < n:
        out += [-k * step_ev, k * step_ev]
        k += 1
    return out[:n]


def write_panorama_session(root: str | os.PathLike, scene_rec709: np.ndarray | None = None, *,
                           session: str = "pano", xyz_to_camera=CANON_EOS_30D_XYZ_TO_CAMERA,
                           frames_per_view: int = 7, step_ev: float = 2.0, f_number: float = 8.0,
                           sun_elevation_deg: float = 35.0, sun_azimuth_deg: float = 60.0,
                           seed: int = 0) -> SessionTruth:
    """Six views at pitch 30° and one at the zenith, ``frames_per_view`` exposures each, every DNG
    in ``root/session/`` (IMG_0001.DNG ...), cos⁴ fall-off, one ``[[shots]]`` per file."""
    scene = default_sky(sun_elevation_deg=sun_elevation_deg, sun_azimuth_deg=sun_azimuth_deg) \
        if scene_rec709 is None else np.asarray(scene_rec709, np.float32)
    w, h = PANORAMA_FRAME
    f_px = PANORAMA_FOCAL_MM * w / SENSOR_WIDTH_MM
    hfov = math.degrees(2 * math.atan(w / 2 / f_px))
    poses = [(yaw, 30.0) for yaw in range(0, 360, 60)] + [(0.0, 90.0)]
    base_s = 1.0 / 250
    offsets = aeb_order(frames_per_view, step_ev)
    exposures = [base_s * 2.0**ev for ev in offsets]
    rendered = []
    for yaw, pitch in poses:
        cam = ViewCamera.pinhole(hfov, w, h, yaw_deg=yaw, pitch_deg=pitch)
        view, valid = render_view(scene, cam, supersample=2)
        yy, xx = np.mgrid[0:h, 0:w] + 0.5
        d, _ = cam.pixel_to_cam_direction(np.stack([xx.ravel(), yy.ravel()], axis=1))
        cos4 = (-d[:, 2].reshape(h, w)) ** 4
        rendered.append(view * (valid * cos4)[..., None])
    fs = max(_full_scale(v, exposures, f_number) for v in rendered)
    folder = Path(root) / session
    start = datetime(2024, 6, 21, 12, 0, 0)
    paths, shots = [], []
    for v, ((yaw, pitch), view) in enumerate(zip(poses, rendered)):
        first = v * frames_per_view + 1
        written = write_bracket(folder, _camera_rgb(view, xyz_to_camera), exposures, f_number=f_number, iso=100,
                                full_well_e=FULL_WELL_E, full_scale_radiance=fs, seed=seed + v,
                                camera_matrix=np.reshape(xyz_to_camera, (3, 3)), make="Canon", model="EOS 30D",
                                focal_length_mm=PANORAMA_FOCAL_MM, prefix=f"tmp{v}",
                                timestamp=start + timedelta(seconds=12 * v), interval_s=1.0)
        for i, p in enumerate(written):  # a camera's running file numbers
            name = folder / f"IMG_{first + i:04d}.DNG"
            os.replace(p, name)
            paths.append(name)
            shots.append(f'[[shots]]\nfiles = "{name.name}"\nyaw_deg = {yaw:g}\npitch_deg = {pitch:g}\n')
    (folder / "session.toml").write_text(
        "# A panoramic head: 6 views at pitch 30 deg and one at the zenith, one bracket each, one folder.\n"
        "probe_azimuth_deg = 0.0\n\n[lens]\nprojection = \"rectilinear\"\n"
        f"sensor_width_mm = {SENSOR_WIDTH_MM}  # focal length from EXIF\n\n"
        "[lens.falloff]\nmodel = \"cos4\"\n\n" + "\n".join(shots))
    return SessionTruth(scene / fs, sun_elevation_deg, sun_azimuth_deg, tuple(paths), len(poses))
