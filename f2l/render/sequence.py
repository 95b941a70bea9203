"""``f2l eval render-faces --sequence``: path-traced video clips of one person turning and nodding.

Each clip ``clip-s<seed>-<index>-<kind>`` is drawn from its own seeded streams and rendered by the
same path tracer as the photos (:mod:`f2l.render.scene`, Anny heads, real HDR maps or Hosek–Wilkie
skies). What a clip holds:

- a static pinhole camera, 16:9 (``image_px`` on the long side, 1280 → 1280 × 720), horizontal
  field of view 40–60°; one person whose head (16 cm wide) is 20–34% of the long side (its face
  box, cheek to cheek, 0.55–0.8 of that: about 11–27%), the eyes 35–45% from the top, shifted
  ±12% sideways; the torso reaches below the frame;
- a head turning and nodding smoothly: yaw(t) = A_y sin(2π t/T + φ_y), one cycle over the clip,
  A_y 35–45°; pitch(t) = A_p sin(4π t/T + φ_p), two nods, A_p 10–15°; a constant roll ±4°. Only
  the head turns (about a pivot 6 cm below and 8 cm behind the eyes); the neck twists, shoulders
  stay (:func:`twist_weights`);
- ``kind`` ``static``: one light; ``cloud``: a Hosek–Wilkie sky whose sun drops to 10–20% of its
  power at ``change_frame`` (frames // 2), the sky above the horizon unchanged (the ground below
  it, lit by the sun, darkens with it); its sun lights the face (a drawn sun behind the head,
  |azimuth| < 90°, is turned by 180°), or the cloud would hardly show on it; ``cut``: at
  ``change_frame`` another shot: another map or sky (a map's turn or a sky's sun ≥ 40° from the
  first's when the source is the same), and with probability ½ each another person and another
  camera distance (a new exposure);
- exposure fixed per shot: a percentile of the first frame's face pixels (as the photos,
  :func:`f2l.render.dataset.expose`); a cloud keeps it (the face darkens). Per frame, shot + read
  noise from a stream of its own, 8-bit sRGB, then the codec's compression (OpenCV's FFmpeg
  ``mp4v``, MPEG-4 part 2 at OpenCV's default bit rate; ``docs/experiments/video_clips.md``
  measures it: 2–6 Mbit/s and ≈ 36 dB PSNR at 1280 × 720, and OpenCV's round trip darkens
  by 1–4 codes).

Segment k of clip i draws its light, skin material and noise levels as render-faces' portrait
case ``CASE_BASE + 4 i + k`` of the same seed (:func:`f2l.render.dataset.draw_case`), its head
from that case's head stream.

Cost (``docs/experiments/video_clips.md``): per shot, the scene, the sky and a background frame
(the map seen by the camera) are built once; per frame only the head's vertices change (Mitsuba's
scene parameters, the BVH rebuilt) and only two windows are path-traced: the head (down to the
chin, :data:`HEAD_WEIGHT`) at ``spp`` samples per pixel, the neck and torso at ``spp // 2`` (at
least 1), each denoised below 16 spp
(:func:`denoise`), the head's window faded into the torso's; the rest is the background.

Written per clip (resumable: a clip whose truth JSON exists is skipped; a failing clip is recorded
and the others go on; every file atomic):

- ``clips/<id>.mp4``: the video (``fps``, default 24);
- ``probes/<id>-seg<k>.exr``: the true probe of segment k (128 × 256, f2l's camera frame, in the
  video's linear units: radiance × that segment's exposure), as render-faces' photo probes;
- ``truth/<id>.json``, written last. Keys:

  - ``clip_id``, ``kind`` (static | cloud | cut), ``fps``, ``frames``, ``width_px``,
    ``height_px``, ``focal_px``, ``change_frame`` (first frame of segment 1, or null), ``video``
    and ``codec``;
  - ``segments``: per segment ``segment`` (k), ``first_frame``, ``last_frame`` (inclusive),
    ``probe`` (path relative to the output folder), ``lighting`` (the draw), ``sky_kind`` (clear |
    overcast), ``sun_direction`` (unit, camera frame), ``sun_elevation_deg``, ``sun_azimuth_deg``,
    ``sun_power_scale``, ``exposure`` (linear radiance × exposure = the video's linear units),
    ``camera_distance_cm``, ``camera`` (the draw), ``person`` (head stream case and skin tone),
    ``head`` (Anny's draw);
  - ``per_frame``: a list, one dict per frame: ``frame``, ``time_s``, ``segment``,
    ``sun_direction`` (unit vector in the CAMERA frame, f2l's convention: +Y up, the camera looks
    along −Z, azimuth 0 = −Z; exact for a sky, the probe's brightest upper texel for a map),
    ``sun_elevation_deg``, ``sun_azimuth_deg``, ``sun_power_scale`` (1, or the cloud's factor),
    ``head_yaw_deg``, ``head_pitch_deg``, ``head_roll_deg`` (the head's rotation Rz(roll)
    Rx(pitch) Ry(yaw) as render-faces' poses: yaw + turns the face toward +X, the image's right),
    ``face_box`` ([x0, y0, x1, y1] px: cheek to cheek, chin to mid-forehead, as the framed
    photos'), ``face_in_frame``;
  - ``draw`` (seed, index, motion: :func:`head_pose`'s parameters), ``options``, ``timings_s``
    (``per_frame_mean`` wall, ``per_frame_cpu_mean`` process CPU, all threads);

- ``clips.json``: the index (render-faces' summary keys, and per clip its kind, status and
  files).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from f2l.io.progress import Progress, ProgressCallback
from f2l.render.dataset import PROBE_GRID, RenderOptions, _lighting, _stream, _sun_of, draw_case, turn_lighting
from f2l.render.scene import SunSkyLighting

__all__ = ["CLIP_KINDS", "CloudedSunSky", "SequenceOptions", "clip_id", "denoise", "draw_clip", "frame_size", "head_pose",
           "pose_vertices", "render_clip", "render_clips", "twist_weights"]

CLIP_KINDS = ("static", "cloud", "cut")
CASE_BASE = 1_000_000  # segment k of clip i draws as portrait case CASE_BASE + 4 i + k
HEAD_WIDTH_CM = 16.0
PIVOT_CM = np.array([0.0, -6.0, -8.0])  # the head turns about this point of its own frame (eyes at 0)
CUT_MIN_SUN_DEG = 40.0
CODEC = "mp4v"
DENOISE_BELOW_SPP = 16  # windows rendered with fewer samples per pixel are denoised
FEATHER_PX = 12  # the head's window fades into the torso's over this many pixels
HEAD_WEIGHT = 0.75  # vertices turning with at least this share of the head's rotation are the head's window


@dataclass(frozen=True)
class SequenceOptions:
    """What every clip of one run shares."""

    frames: int = 48
    fps: float = 24.0
    clip_kind: str = "mixed"  # one of CLIP_KINDS, or mixed: clip i is CLIP_KINDS[i % 3]

    def __post_init__(self):
        if self.clip_kind not in CLIP_KINDS + ("mixed",):
            raise ValueError(f"clip kind must be one of {', '.join(CLIP_KINDS + ('mixed',))}, got {self.clip_kind!r}")
        if self.frames < 2 or self.fps <= 0:
            raise ValueError("a clip needs at least 2 frames and fps > 0")

    def kind(self, index: int) -> str:
        return CLIP_KINDS[index % 3] if self.clip_kind == "mixed" else self.clip_kind


def clip_id(seed: int, index: int, kind: str) -> str:
    return f"clip-s{seed}-{index:05d}-{kind}"


def _case_index(index: int, segment: int) -> int:
    return CASE_BASE + 4 * int(index) + int(segment)


def _camera_draw(rng: np.random.Generator) -> dict:
    return {"fov_x_deg": round(float(rng.uniform(40.0, 60.0)), 4),
            "head_width_fraction": round(float(np.exp(rng.uniform(np.log(0.20), np.log(0.34)))), 5),
            "shift_fraction": round(float(rng.uniform(-0.12, 0.12)), 4),
            "eyes_row_fraction": round(float(rng.uniform(0.35, 0.45)), 4)}


def draw_clip(seed: int, index: int, options: RenderOptions = RenderOptions(),
              sequence: SequenceOptions = SequenceOptions()) -> dict:
    """Every random choice of clip ``index`` (JSON-ready): camera, motion and segments."""
    kind = sequence.kind(index)
    rng = _stream(seed, index, 50)
    camera = _camera_draw(rng)
    motion = {"yaw_amplitude_deg": round(float(rng.uniform(35.0, 45.0)), 3),
              "yaw_phase_rad": round(float(rng.uniform(0, 2 * np.pi)), 4),
              "pitch_amplitude_deg": round(float(rng.uniform(10.0, 15.0)), 3),
              "pitch_phase_rad": round(float(rng.uniform(0, 2 * np.pi)), 4),
              "roll_deg": round(float(rng.uniform(-4.0, 4.0)), 3)}
    light_options = replace(options, sunsky_fraction=1.0) if kind == "cloud" else options
    first = draw_case(seed, _case_index(index, 0), light_options)
    if kind == "cloud" and abs(first["lighting"]["sun_azimuth_deg"]) < 90.0:  # a sun behind the head: bring it round
        first = {**first, "lighting": turn_lighting(first["lighting"], 180.0)}
    person = {"case": _case_index(index, 0), "skin_tone": first["material"]["skin_tone"]}
    segments = [{"lighting": first["lighting"], "material": first["material"], "noise": _noise(first),
                 "person": person, "camera": camera, "sun_power_scale": 1.0}]
    change = None
    if kind == "cloud":
        change = sequence.frames // 2
        segments.append({**segments[0], "sun_power_scale": round(float(rng.uniform(0.1, 0.2)), 4)})
    elif kind == "cut":
        change = sequence.frames // 2
        cut_rng = _stream(seed, index, 51)
        second = draw_case(seed, _case_index(index, 1), options)
        lighting = second["lighting"]
        if lighting["source"] == first["lighting"]["source"]:
            lighting = _away_from(lighting, first["lighting"])
        new_person = bool(cut_rng.uniform() < 0.5)
        new_distance = bool(cut_rng.uniform() < 0.5)
        cam2 = _camera_draw(cut_rng)
        segments.append({"lighting": lighting, "material": second["material"] if new_person else first["material"],
                         "noise": _noise(second),
                         "person": {"case": _case_index(index, 1), "skin_tone": second["material"]["skin_tone"]}
                         if new_person else person,
                         "camera": {**camera, "head_width_fraction": cam2["head_width_fraction"]}
                         if new_distance else camera, "sun_power_scale": 1.0})
    return {"clip_id": clip_id(seed, index, kind), "seed": int(seed), "index": int(index), "kind": kind,
            "frames": int(sequence.frames), "fps": float(sequence.fps), "change_frame": change,
            "motion": motion, "segments": segments}


def _away_from(lighting: dict, other: dict) -> dict:
    """``lighting`` turned about +Y so its azimuth (sun or map rotation) is ≥ CUT_MIN_SUN_DEG from ``other``'s."""
    key = "sun_azimuth_deg" if lighting["source"] == "sunsky" else "rotation_deg"
    gap = (lighting[key] - other[key] + 180.0) % 360.0 - 180.0
    if abs(gap) >= CUT_MIN_SUN_DEG:
        return lighting
    turn = 120.0 if gap >= 0 else -120.0  # a map's rotation moves its light the other way (turn_lighting)
    return turn_lighting(lighting, -turn if key == "sun_azimuth_deg" else turn)


def _noise(case: dict) -> dict:
    cam = case["camera"]
    return {k: cam[k] for k in ("exposure_percentile", "shot_noise", "read_noise")}


def head_pose(motion: dict, frame: int, frames: int) -> tuple[float, float, float]:
    """(yaw, pitch, roll) in degrees of the head at ``frame`` of a clip of ``frames`` (module docstring)."""
    t = frame / frames
    yaw = motion["yaw_amplitude_deg"] * np.sin(2 * np.pi * t + motion["yaw_phase_rad"])
    pitch = motion["pitch_amplitude_deg"] * np.sin(4 * np.pi * t + motion["pitch_phase_rad"])
    return float(yaw), float(pitch), float(motion["roll_deg"])


def _smoothstep(x, lo: float, hi: float):
    t = np.clip((np.asarray(x, np.float64) - lo) / (hi - lo), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def twist_weights(vertices_cm: np.ndarray) -> np.ndarray:
    """How much of the head's rotation each vertex (head frame, eyes at 0) follows: 1 from the chin
    up (y > −9 cm), easing to 0 down the neck (−9 → −26 cm); below the chin also easing to 0 outward
    from the neck's axis (9 → 14 cm from x = 0, z = −7 cm), so the shoulders stay."""
    x, y, z = np.asarray(vertices_cm, np.float64).T
    below_chin = 1.0 - _smoothstep(y, -14.0, -9.0)
    outward = _smoothstep(np.hypot(x, z + 7.0), 9.0, 14.0)
    return _smoothstep(y, -26.0, -9.0) * (1.0 - outward * below_chin)


def _rotations(yaw_deg, pitch_deg, roll_deg) -> np.ndarray:
    """Rz(roll) Rx(pitch) Ry(yaw) (render-faces' pose) for arrays of angles: (..., 3, 3)."""
    y, p, r = (np.radians(np.asarray(a, np.float64)) for a in (yaw_deg, pitch_deg, roll_deg))
    one, zero = np.ones_like(y), np.zeros_like(y)
    ry = np.stack([np.stack([np.cos(y), zero, np.sin(y)], -1), np.stack([zero, one, zero], -1),
                   np.stack([-np.sin(y), zero, np.cos(y)], -1)], -2)
    rx = np.stack([np.stack([one, zero, zero], -1), np.stack([zero, np.cos(p), -np.sin(p)], -1),
                   np.stack([zero, np.sin(p), np.cos(p)], -1)], -2)
    rz = np.stack([np.stack([np.cos(r), -np.sin(r), zero], -1), np.stack([np.sin(r), np.cos(r), zero], -1),
                   np.stack([zero, zero, one], -1)], -2)
    return rz @ rx @ ry


def pose_vertices(vertices_cm, normals, weights, pose_deg, offset_cm) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, normals) of a rest head turned by ``pose_deg`` (yaw, pitch, roll) about
    :data:`PIVOT_CM`, each vertex by ``weights`` × the angles, then moved by ``offset_cm``."""
    w = np.asarray(weights, np.float64)
    rot = _rotations(*(w * a for a in pose_deg))
    v = np.einsum("nij,nj->ni", rot, vertices_cm - PIVOT_CM) + PIVOT_CM + np.asarray(offset_cm, np.float64)
    n = np.einsum("nij,nj->ni", rot, normals)
    return v, n / np.linalg.norm(n, axis=1, keepdims=True)


def frame_size(long_px: int) -> tuple[int, int]:
    """(width, height) of a 16:9 frame, the height rounded to even (codecs want even sizes)."""
    return int(long_px), int(2 * round(long_px * 9 / 32))


class _Shot:
    """One segment's renderer: the head, camera, Mitsuba scene and background, built once; then
    :meth:`render` per frame (only the head's vertices change)."""

    def __init__(self, spec: dict, segment: dict, options: RenderOptions, head_cache: dict):
        from f2l.render.framing import _face_corners
        from f2l.render.heads import anny_head
        from f2l.render.scene import RenderSettings

        width, height = frame_size(options.image_px)
        cam = segment["camera"]
        tan = np.tan(np.radians(cam["fov_x_deg"]) / 2.0)
        width_cm = HEAD_WIDTH_CM / cam["head_width_fraction"]
        height_cm = width_cm * height / width
        self.distance_cm = width_cm / (2.0 * tan)
        self.offset_cm = np.array([cam["shift_fraction"] * width_cm, (0.5 - cam["eyes_row_fraction"]) * height_cm, 0.0])
        crop_cm = max(42.0, 12.0 + height_cm / 2.0 + self.offset_cm[1] + 8.0)  # the torso reaches below the frame
        key = (segment["person"]["case"], round(crop_cm, 1))
        if key not in head_cache:
            head_cache.clear()
            head_cache[key] = anny_head(_stream(spec["seed"], segment["person"]["case"], 1), crop_cm=crop_cm,
                                        skin_tone=segment["person"]["skin_tone"])
        self.head = head_cache[key]
        self.weights = twist_weights(self.head.vertices)
        self.face_corners = _face_corners(self.head)
        self.settings = RenderSettings(width_px=width, height_px=height, fov_x_deg=cam["fov_x_deg"],
                                       camera_distance_cm=float(self.distance_cm), spp=options.spp,
                                       max_depth=options.max_depth, specular=options.specular,
                                       skin_roughness=segment["material"]["skin_roughness"],
                                       skin_specular=segment["material"]["skin_specular"], seed=spec["index"])
        self.focal_px = width / (2.0 * tan)
        self.lighting = _lighting(segment["lighting"])
        if segment["sun_power_scale"] != 1.0:
            self.lighting = _clouded(self.lighting, segment["sun_power_scale"])
        self._build()

    def _build(self) -> None:
        import tempfile

        from f2l.render.scene import _bsdf, _write_ply, head_parts, mitsuba, sensor_dict

        mi = self.mi = mitsuba()
        emitters = self.lighting.emitters(mi)
        scene = {"type": "scene", "integrator": {"type": "path", "max_depth": int(self.settings.max_depth)},
                 "sensor": sensor_dict(mi, self.settings, "rgb"), **emitters}
        self.background = np.clip(np.array(mi.render(mi.load_dict(scene), spp=4), np.float64), 0.0, None)
        self.parts = {}
        with tempfile.TemporaryDirectory() as tmp:
            for kind, mask in head_parts(self.head).items():
                if mask.any():
                    path = Path(tmp) / f"{kind}.ply"
                    _write_ply(path, self.head, mask)
                    scene[f"head_{kind}"] = {"type": "ply", "filename": str(path), "bsdf": _bsdf(kind, self.settings)}
                    self.parts[f"head_{kind}"] = np.unique(self.head.faces[mask])  # _write_ply's vertex order
            self.scene = mi.load_dict(scene)
        self.params = mi.traverse(self.scene)

    def pose(self, pose_deg) -> np.ndarray:
        """Pose the scene's head; returns its vertices (camera frame, cm)."""
        v, n = pose_vertices(self.head.vertices, self.head.normals, self.weights, pose_deg, self.offset_cm)
        for name, used in self.parts.items():
            for attr, values in (("vertex_positions", v), ("vertex_normals", n)):
                key = f"{name}.{attr}"
                self.params[key] = type(self.params[key])(values[used].astype(np.float32).ravel())
        self.params.update()
        return v

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        z = self.distance_cm - points[:, 2]
        return (self.settings.width_px / 2 + self.focal_px * points[:, 0] / z,
                self.settings.height_px / 2 - self.focal_px * points[:, 1] / z)

    def _window(self, points: np.ndarray, pad_px: int = 4):
        cols, rows = self.project(points)
        w, h = self.settings.width_px, self.settings.height_px
        x0, x1 = np.clip([int(np.floor(cols.min())) - pad_px, int(np.ceil(cols.max())) + pad_px], 0, w)
        y0, y1 = np.clip([int(np.floor(rows.min())) - pad_px, int(np.ceil(rows.max())) + pad_px], 0, h)
        return (x0, y0, x1, y1) if x1 > x0 and y1 > y0 else None

    def render(self, vertices: np.ndarray, seed: int) -> np.ndarray:
        """The linear frame (H, W, 3) of the posed head: the torso's window at spp // 2, the head's
        at spp, cross-faded over :data:`FEATHER_PX` where both cover a pixel (both are estimates
        of the same image), the background elsewhere."""
        from f2l.render.scene import sensor_dict

        image = self.background.copy()
        covered = np.zeros(image.shape[:2], bool)
        head = self.weights >= HEAD_WEIGHT
        windows = [(self._window(vertices[~head]), max(1, self.settings.spp // 2)),
                   (self._window(vertices[head]), self.settings.spp)]
        for i, (window, spp) in enumerate(windows):
            if window is None:
                continue
            sensor = self.mi.load_dict(sensor_dict(self.mi, self.settings, "rgb", window))
            x0, y0, x1, y1 = window
            crop = np.clip(np.array(self.mi.render(self.scene, sensor=sensor, seed=(seed * 2 + i) % (2**31), spp=spp)),
                           0.0, None)
            if spp < DENOISE_BELOW_SPP:
                crop = denoise(crop)
            rows, cols = np.arange(y0, y1), np.arange(x0, x1)
            edge = np.minimum.outer(np.minimum(rows - y0, y1 - 1 - rows), np.minimum(cols - x0, x1 - 1 - cols))
            fade = np.where(covered[y0:y1, x0:x1], np.clip(edge / FEATHER_PX, 0.0, 1.0), 1.0)[..., None]
            image[y0:y1, x0:x1] = fade * crop + (1.0 - fade) * image[y0:y1, x0:x1]
            covered[y0:y1, x0:x1] = True
        return image

    def face_box(self, vertices: np.ndarray) -> list[float]:
        cols, rows = self.project(vertices[self.face_corners])
        return [float(cols.min()), float(rows.min()), float(cols.max()), float(rows.max())]

    def face_pixels(self, vertices: np.ndarray, box: list[float]) -> np.ndarray:
        """Mask (H, W) of the pixels of ``box`` whose centre ray hits the head (embree)."""
        import trimesh

        w, h = self.settings.width_px, self.settings.height_px
        x0, x1 = np.clip([int(box[0]), int(np.ceil(box[2]))], 0, w)
        y0, y1 = np.clip([int(box[1]), int(np.ceil(box[3]))], 0, h)
        mask = np.zeros((h, w), bool)
        if x1 <= x0 or y1 <= y0:
            return mask
        rows, cols = np.mgrid[y0:y1, x0:x1]
        dirs = np.stack([(cols + 0.5 - w / 2) / self.focal_px, -(rows + 0.5 - h / 2) / self.focal_px,
                         -np.ones(cols.shape)], -1).reshape(-1, 3)
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        origins = np.tile([0.0, 0.0, self.distance_cm], (len(dirs), 1))
        mesh = trimesh.Trimesh(vertices, self.head.faces, process=False)
        mask[y0:y1, x0:x1] = mesh.ray.intersects_any(origins, dirs).reshape(rows.shape)
        return mask


class CloudedSunSky(SunSkyLighting):
    """:class:`SunSkyLighting` whose sun gives ``sun_scale`` of its power (a cloud over the sun); the
    sky above the horizon is unchanged, the ground below it, lit by the sun, follows."""

    sun_scale: float = 1.0

    def sun_power(self) -> np.ndarray:
        return super().sun_power() * self.sun_scale


def _clouded(lighting, scale: float) -> CloudedSunSky:
    if not isinstance(lighting, SunSkyLighting):
        raise ValueError("a cloud dims a Hosek-Wilkie sun; maps have no separate sun")
    dimmed = CloudedSunSky(lighting.sun_direction, lighting.turbidity, lighting.ground_albedo)
    dimmed.sun_scale = float(scale)
    return dimmed


def denoise(linear: np.ndarray) -> np.ndarray:
    """A path-traced window (H, W, 3) with its Monte Carlo noise smoothed, in √(image / its 99th
    percentile): a 3 × 3 median (isolated bright samples), then OpenCV's bilateral filter (9 px,
    σ_space 3 px, σ_colour 0.2), so that hard shadow and silhouette edges stay
    (``docs/experiments/video_clips.md``: about half the noise at 4 spp)."""
    import cv2

    scale = max(float(np.percentile(linear.max(axis=-1), 99)), 1e-12)
    root = cv2.medianBlur(np.sqrt(linear / scale).astype(np.float32), 3)
    return cv2.bilateralFilter(root, 9, 0.2, 3.0).astype(np.float64) ** 2 * scale


def _sensor(image: np.ndarray, exposure: float, noise: dict, rng: np.random.Generator) -> np.ndarray:
    """8-bit sRGB frame: ``image`` × ``exposure`` with shot + read noise (as the photos')."""
    from f2l.colour.chart import srgb_encode_uint8

    exposed = image * exposure
    sigma = np.sqrt(noise["shot_noise"] * np.clip(exposed, 0, None) + noise["read_noise"] ** 2)
    return srgb_encode_uint8(exposed + sigma * rng.standard_normal(exposed.shape))


def _exposure(image: np.ndarray, face: np.ndarray, percentile: float) -> float:
    if not face.any():
        raise RuntimeError("the face is not in the frame")
    return 1.0 / max(float(np.percentile(image.max(axis=-1)[face], percentile)), 1e-12)


class _VideoWriter:
    """cv2.VideoWriter into a temporary name beside ``path``, renamed into place by :meth:`close`."""

    def __init__(self, path: Path, fps: float, size: tuple[int, int]):
        import cv2

        self.path = Path(path)
        for stale in self.path.parent.glob(f".{self.path.stem}.*.tmp{self.path.suffix}"):
            stale.unlink(missing_ok=True)  # left by a run that was killed
        self.tmp = self.path.with_name(f".{self.path.stem}.{os.getpid()}.tmp{self.path.suffix}")
        self.writer = cv2.VideoWriter(str(self.tmp), cv2.VideoWriter_fourcc(*CODEC), float(fps), size)
        if not self.writer.isOpened():
            raise RuntimeError(f"OpenCV cannot write {CODEC} video to {self.tmp}")

    def write(self, rgb: np.ndarray) -> None:
        self.writer.write(np.ascontiguousarray(rgb[..., ::-1]))

    def close(self, keep: bool) -> None:
        self.writer.release()
        if keep:
            os.replace(self.tmp, self.path)
        else:
            self.tmp.unlink(missing_ok=True)


def _sun_of_segment(probe: np.ndarray, lighting: dict) -> dict:
    sky = _sun_of(probe, lighting)
    return {"sky_kind": sky["kind"], "sun_direction": sky["sun_direction"],
            "sun_elevation_deg": sky["sun_elevation_deg"], "sun_azimuth_deg": sky["sun_azimuth_deg"]}


def render_clip(spec: dict, options: RenderOptions, out: Path) -> dict:
    """Render clip ``spec`` into ``out`` (video, probes, then truth); returns its truth dict."""
    from f2l.io.atomic import write_text_atomic
    from f2l.io.exr import write_exr
    from f2l.render.scene import ground_truth_probe

    t0 = time.perf_counter()
    cid, frames, change = spec["clip_id"], spec["frames"], spec["change_frame"]
    for sub in ("clips", "probes", "truth"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    width, height = frame_size(options.image_px)
    writer = _VideoWriter(out / "clips" / f"{cid}.mp4", spec["fps"], (width, height))
    heads: dict = {}
    segments, per_frame, frame_s, frame_cpu_s = [], [], [], []
    ok = False
    try:
        shot, exposure = None, None
        for frame in range(frames):
            k = 0 if change is None or frame < change else 1
            segment = spec["segments"][k]
            if len(segments) == k:  # a new segment: its shot, exposure and probe
                shot = _Shot(spec, segment, options, heads)
                same_shot = k > 0 and spec["kind"] == "cloud"
                segments.append({"segment": k, "first_frame": frame, "shot": shot, "same_shot": same_shot})
            t, cpu = time.perf_counter(), time.process_time()
            pose = head_pose(spec["motion"], frame, frames)
            vertices = shot.pose(pose)
            image = shot.render(vertices, seed=int(spec["index"]) * 100_003 + frame)
            box = shot.face_box(vertices)
            info = segments[k]
            if "exposure" not in info:
                info["exposure"] = exposure if info["same_shot"] else _exposure(
                    image, shot.face_pixels(vertices, box), segment["noise"]["exposure_percentile"])
                exposure = info["exposure"]
                probe = ground_truth_probe(shot.lighting, PROBE_GRID) * exposure
                rel = f"probes/{cid}-seg{k}.exr"
                write_exr(out / rel, probe.astype(np.float32), {"f2l_convention": "latlong +Y up, u=0.5 is -Z",
                                                                "f2l_face_id": f"{cid}-seg{k}"})
                info.update(probe=rel, **_sun_of_segment(probe, segment["lighting"]))
            rng = np.random.default_rng([int(spec["seed"]), int(spec["index"]), 60, frame])
            writer.write(_sensor(image, info["exposure"], segment["noise"], rng))
            frame_s.append(time.perf_counter() - t)
            frame_cpu_s.append(time.process_time() - cpu)
            w, h = width, height
            per_frame.append({"frame": frame, "time_s": round(frame / spec["fps"], 6), "segment": k,
                              "sun_direction": info["sun_direction"],
                              "sun_elevation_deg": round(info["sun_elevation_deg"], 4),
                              "sun_azimuth_deg": round(info["sun_azimuth_deg"], 4),
                              "sun_power_scale": segment["sun_power_scale"],
                              "head_yaw_deg": round(pose[0], 4), "head_pitch_deg": round(pose[1], 4),
                              "head_roll_deg": round(pose[2], 4), "face_box": [round(v, 2) for v in box],
                              "face_in_frame": bool(box[0] >= 0 and box[1] >= 0 and box[2] <= w and box[3] <= h)})
            if frame + 1 == frames or (change is not None and frame + 1 == change):
                info["last_frame"] = frame
        ok = True
    finally:
        writer.close(keep=ok)
    truth_segments = []
    for info, segment in zip(segments, spec["segments"]):
        shot = info.pop("shot")
        info.pop("same_shot")
        truth_segments.append({**info, "exposure": float(info["exposure"]), "lighting": segment["lighting"],
                               "sun_power_scale": segment["sun_power_scale"],
                               "camera_distance_cm": round(float(shot.distance_cm), 4),
                               "camera": segment["camera"], "person": segment["person"],
                               "head": shot.head.info})
    truth = {"clip_id": cid, "kind": spec["kind"], "fps": spec["fps"], "frames": frames, "width_px": width,
             "height_px": height, "focal_px": float(shot.focal_px),
             "change_frame": change, "video": f"clips/{cid}.mp4", "codec": CODEC, "segments": truth_segments,
             "per_frame": per_frame, "draw": {k: spec[k] for k in ("seed", "index", "motion")},
             "options": asdict(options),
             "timings_s": {"total": round(time.perf_counter() - t0, 3),
                           "per_frame_mean": round(float(np.mean(frame_s)), 4),
                           "per_frame_cpu_mean": round(float(np.mean(frame_cpu_s)), 4)}}
    write_text_atomic(out / "truth" / f"{cid}.json", json.dumps(truth, indent=1))
    return truth


def render_clips(out: Path, n: int, seed: int = 0, options: RenderOptions = RenderOptions(),
                 sequence: SequenceOptions = SequenceOptions(), *, start: int = 0,
                 progress: ProgressCallback | None = None) -> dict:
    """Render clips ``start .. start + n − 1`` into ``out`` (module docstring); resumable; a failing
    clip is recorded with its reason and the others go on. Writes and returns the index ``clips.json``."""
    from f2l.io.atomic import write_text_atomic

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    bar = Progress(progress, "render-faces (sequence)", "clip", n)
    status, clips, t0, per_frame, per_frame_cpu = {}, [], time.perf_counter(), [], []
    for index in range(start, start + n):
        spec = draw_clip(seed, index, options, sequence)
        cid = spec["clip_id"]
        truth_path = out / "truth" / f"{cid}.json"
        if truth_path.is_file():
            status[cid] = "exists"
        else:
            try:
                truth = render_clip(spec, options, out)
                status[cid] = "ok"
                per_frame.append(truth["timings_s"]["per_frame_mean"])
                per_frame_cpu.append(truth["timings_s"]["per_frame_cpu_mean"])
            except Exception as exc:  # noqa: BLE001 - one bad clip never stops the set
                status[cid] = f"error: {type(exc).__name__}: {exc}"
        clips.append({"clip_id": cid, "kind": spec["kind"], "status": status[cid], "video": f"clips/{cid}.mp4",
                      "truth": f"truth/{cid}.json"})
        bar.advance()
    summary = {"out": str(out), "cases": len(status), "seed": seed, "sequence": asdict(sequence),
               "options": asdict(options), "ok": sum(v == "ok" for v in status.values()),
               "skipped_existing": sum(v == "exists" for v in status.values()),
               "errors": {k: v for k, v in status.items() if v.startswith("error")},
               "elapsed_s": round(time.perf_counter() - t0, 2),
               "seconds_per_frame": round(float(np.mean(per_frame)), 3) if per_frame else None,
               "cpu_seconds_per_frame": round(float(np.mean(per_frame_cpu)), 3) if per_frame_cpu else None}
    write_text_atomic(out / "clips.json", json.dumps({"summary": summary, "clips": clips}, indent=1))
    return summary
