"""``f2l eval render-faces``: photos of heads f2l did not model, path-traced under real and physical skies.

Each case ``pbr-s<seed>-<index>`` draws, from its own seeded streams (so an ablation that changes
one switch re-renders *the same* person, pose, camera and sky):

- a head (:func:`f2l.render.heads.anny_head`: random Anny adult, skin light to dark, lips, brows,
  hair, shirt, eyes), posed with yaw ±30°, pitch ±10°, roll ±5°;
- lighting: half the cases one of the seven CC0 outdoor maps (:mod:`f2l.render.hdri`; ``maps=
  "held-out"``: the three held out from tuning) turned by a random angle about +Y, half a
  Hosek–Wilkie sky (sun 5–80° high, any azimuth, turbidity 2–8,
  ground albedo 0.1–0.3);
- skin: Mitsuba's ``principled`` BSDF, roughness 0.3–0.7, specular 0.35–0.6 (F0 ≈ 0.03–0.05);
- a pinhole camera, horizontal field of view 20–60°, the head 35–55% of the frame's width;
- exposure: the q-th percentile of the face's brightest channel (q in 90–99.5) maps to 1.0, so
  the brightest 0.5–10% of the face clip; shot + read noise; sRGB-encoded to 8 bits.

Written per case: ``photos/<id>.jpg`` (quality 95, EXIF focal length), ``png/<id>.png`` (the same
8-bit codes, lossless), ``probes/<id>.exr`` (the ground truth on a 128 × 256 grid, float32, in the
photo's linear units: radiance × exposure), ``truth/<id>.npz`` (the posed mesh, cm, f2l's camera
frame) and ``meta/<id>.json`` (every draw, settings, timings), written last: a case whose meta
exists is complete and is skipped when the command runs again (resumable).

Ablation switches (``RenderOptions``): ``specular=False`` (Lambertian skin), ``max_depth=2``
(no interreflection), ``head="canonical"`` (MediaPipe's canonical face closed into a head),
``clipping=False`` (exposure puts the face's maximum at 0.9). ``shade_one`` is the framed groups'
(:mod:`f2l.render.occluder`).

Sessions (``session_size`` K > 1, :func:`draw_session_case`): cases ``jK .. jK + K − 1`` are the
photos of session j. Each keeps its own person, pose, camera and skin draws, but all share the
first case's lighting, seen by a camera turned ``camera_yaw_deg`` right (+ = toward +X from -Z;
0 for the first photo, the others uniform in ±90° from a stream of their own): the lighting is
the session's turned about +Y so that the photo sees at azimuth a what the first sees at a + yaw,
and the truth probe is in the photo's own camera frame. Meta: ``session`` (the id K photos share)
and ``camera_yaw_deg``. Without sessions every draw is as before, bit for bit.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from f2l.io.progress import Progress, ProgressCallback
from f2l.lighting.grid import LatLongGrid, angles_from_direction, direction_from_angles, rotate_y

__all__ = ["RenderOptions", "case_id", "draw_case", "draw_session_case", "render_faces"]

PROBE_GRID = LatLongGrid(128, 256)
HEADS = ("anny", "canonical")


def case_id(seed: int, index: int) -> str:
    return f"pbr-s{seed}-{index:05d}"


@dataclass(frozen=True)
class RenderOptions:
    """What every case of one ``render-faces`` run shares (the ablation switches among them)."""

    image_px: int = 384
    spp: int = 64
    max_depth: int = 6
    specular: bool = True
    head: str = "anny"
    clipping: bool = True
    sunsky_fraction: float = 0.5
    maps: str = "eval"  # a key of f2l.render.hdri.MAP_SETS
    shade_one: bool = False  # framed groups: one person in an occluder's shadow (f2l.render.occluder)

    def __post_init__(self):
        from f2l.render.hdri import MAP_SETS

        if self.head not in HEADS:
            raise ValueError(f"head must be one of {', '.join(HEADS)}, got {self.head!r}")
        if self.maps not in MAP_SETS:
            raise ValueError(f"maps must be one of {', '.join(MAP_SETS)}, got {self.maps!r}")
        if self.image_px < 32 or self.spp < 1 or self.max_depth < 2:
            raise ValueError("image_px >= 32, spp >= 1 and max_depth >= 2 are required")
        if not 0.0 <= self.sunsky_fraction <= 1.0:
            raise ValueError("sunsky_fraction must be in [0, 1]")


def _stream(seed: int, index: int, what: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), int(index), what])


def draw_case(seed: int, index: int, options: RenderOptions = RenderOptions()) -> dict:
    """Every random choice of case ``index`` except the head's own (JSON-ready)."""
    from f2l.render.hdri import MAP_SETS

    light_rng, cam_rng, mat_rng = _stream(seed, index, 2), _stream(seed, index, 3), _stream(seed, index, 4)
    if light_rng.uniform() < options.sunsky_fraction:
        elevation, azimuth = light_rng.uniform(5.0, 80.0), light_rng.uniform(-180.0, 180.0)
        lighting = {"source": "sunsky", "sun_elevation_deg": round(elevation, 4), "sun_azimuth_deg": round(azimuth, 4),
                    "turbidity": round(light_rng.uniform(2.0, 8.0), 4),
                    "ground_albedo": round(light_rng.uniform(0.1, 0.3), 4)}
    else:
        lighting = {"source": str(light_rng.choice(MAP_SETS[options.maps])),
                    "rotation_deg": round(light_rng.uniform(0.0, 360.0), 4)}
    fov = cam_rng.uniform(20.0, 60.0)
    width_fraction = cam_rng.uniform(0.35, 0.55)
    camera = {"fov_x_deg": round(fov, 4), "head_width_fraction": round(width_fraction, 4),
              "yaw_deg": round(cam_rng.uniform(-30, 30), 4), "pitch_deg": round(cam_rng.uniform(-10, 10), 4),
              "roll_deg": round(cam_rng.uniform(-5, 5), 4),
              "offset_fraction": [round(cam_rng.uniform(-0.08, 0.08), 4), round(cam_rng.uniform(-0.08, 0.05), 4)],
              "exposure_percentile": round(cam_rng.uniform(90.0, 99.5), 3),
              "shot_noise": round(float(np.exp(cam_rng.uniform(np.log(2e-4), np.log(1e-3)))), 6),
              "read_noise": round(float(np.exp(cam_rng.uniform(np.log(1e-3), np.log(4e-3)))), 6)}
    material = {"skin_roughness": round(mat_rng.uniform(0.3, 0.7), 4), "skin_specular": round(mat_rng.uniform(0.35, 0.6), 4),
                "skin_tone": round(mat_rng.uniform(0.0, 1.0), 4)}
    return {"face_id": case_id(seed, index), "seed": int(seed), "index": int(index),
            "lighting": lighting, "camera": camera, "material": material}


SESSION_YAW_DEG = 90.0  # a session's other cameras turn uniformly within ± this of the first


def session_id(seed: int, first: int) -> str:
    """The id shared by the photos of the session whose first case is ``first``."""
    return f"pbr-s{seed}-session{first:05d}"


def session_yaws(seed: int, first: int, size: int) -> list[float]:
    """The cameras' headings (degrees, + = right) of the session starting at case ``first``: 0 for
    the first photo, the others uniform in ±SESSION_YAW_DEG from the session's own stream."""
    rng = _stream(seed, first, 6)
    return [0.0] + [round(float(rng.uniform(-SESSION_YAW_DEG, SESSION_YAW_DEG)), 4) for _ in range(size - 1)]


def turn_lighting(lighting: dict, yaw_deg: float) -> dict:
    """A case's lighting as a camera turned ``yaw_deg`` right sees it: a light at azimuth a moves
    to a − yaw (the sun's azimuth; a map's ``rotation_deg``, :func:`rotate_y` moving by −angle)."""
    if lighting["source"] == "sunsky":
        azimuth = (lighting["sun_azimuth_deg"] - yaw_deg + 180.0) % 360.0 - 180.0
        return {**lighting, "sun_azimuth_deg": round(azimuth, 4)}
    return {**lighting, "rotation_deg": round((lighting["rotation_deg"] + yaw_deg) % 360.0, 4)}


def draw_session_case(seed: int, index: int, options: RenderOptions = RenderOptions(), size: int = 1) -> dict:
    """:func:`draw_case`, photo ``index % size`` of a session of ``size`` (module docstring): the
    session's first case's lighting turned by this camera's heading; ``size`` 1 is draw_case."""
    spec = draw_case(seed, index, options)
    if size <= 1:
        return spec
    first = index - index % size
    yaw = session_yaws(seed, first, size)[index - first]
    reference = draw_case(seed, first, options)["lighting"]
    return {**spec, "lighting": turn_lighting(reference, yaw), "session": session_id(seed, first),
            "camera_yaw_deg": yaw, "session_lighting": reference}


def _rotation(yaw_deg, pitch_deg, roll_deg) -> np.ndarray:
    y, p, r = np.radians([yaw_deg, pitch_deg, roll_deg])
    ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    rx = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
    rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])
    return rz @ rx @ ry


def _lighting(spec: dict):
    from f2l.render.hdri import load_map
    from f2l.render.scene import MapLighting, SunSkyLighting

    if spec["source"] == "sunsky":
        sun = direction_from_angles(np.radians(spec["sun_elevation_deg"]), np.radians(spec["sun_azimuth_deg"]))
        return SunSkyLighting(sun, spec["turbidity"], spec["ground_albedo"])
    radiance = rotate_y(load_map(spec["source"]), np.radians(spec["rotation_deg"]))
    return MapLighting(np.clip(radiance, 0.0, None), spec["source"])


def _sun_of(probe: np.ndarray, spec: dict) -> dict:
    """The true sun (or brightest light) of a case: exact for the sky model, the probe's brightest
    upper-hemisphere texel for a map."""
    from f2l.metrics.lighting import brightest_direction, is_overcast

    overcast = bool(is_overcast(probe, PROBE_GRID))
    if spec["source"] == "sunsky":
        sun = direction_from_angles(np.radians(spec["sun_elevation_deg"]), np.radians(spec["sun_azimuth_deg"]))
    else:
        sun = brightest_direction(probe, PROBE_GRID)[1]
    elevation, azimuth = angles_from_direction(sun)
    return {"kind": "overcast" if overcast else "clear", "sun_direction": [float(c) for c in sun],
            "sun_elevation_deg": float(np.degrees(elevation)), "sun_azimuth_deg": float(np.degrees(azimuth)),
            # the face looks toward +Z: a sun with a negative z component is behind the head
            "sun_behind_head": bool(sun[2] < 0.0)}


def _face_box(head_posed, settings, width_px) -> tuple[slice, slice]:
    """Image rows/cols of the face's front (eyes to chin, cheek to cheek) in the rendered image."""
    focal = settings.width_px / (2.0 * np.tan(np.radians(settings.fov_x_deg) / 2.0))
    front = head_posed.info["face_front_points"]
    z = settings.camera_distance_cm - front[:, 2]
    col = width_px / 2 + focal * front[:, 0] / z
    row = width_px / 2 - focal * front[:, 1] / z
    c0, c1 = np.clip([col.min(), col.max()], 0, width_px - 1).astype(int)
    r0, r1 = np.clip([row.min(), row.max()], 0, width_px - 1).astype(int)
    return slice(r0, r1 + 1), slice(c0, c1 + 1)


def render_settings(spec: dict, options: RenderOptions, width_px: int, height_px: int, fov_x_deg: float,
                    distance_cm: float):
    """The :class:`f2l.render.scene.RenderSettings` of a case: its frame, camera, sampling and skin."""
    from f2l.render.scene import RenderSettings

    return RenderSettings(width_px=width_px, height_px=height_px, fov_x_deg=fov_x_deg,
                          camera_distance_cm=float(distance_cm), spp=options.spp, max_depth=options.max_depth,
                          specular=options.specular, skin_roughness=spec["material"]["skin_roughness"],
                          skin_specular=spec["material"]["skin_specular"], seed=spec["index"])


def expose(image: np.ndarray, face: np.ndarray, spec: dict, options: RenderOptions) -> tuple[np.ndarray, float]:
    """(8-bit sRGB photo, exposure) of a linear render: the ``exposure_percentile`` of the face
    pixels' brightest channel to 1.0 (``clipping``; else the face's maximum to 0.9), shot and read
    noise from the case's noise stream, sRGB-encoded."""
    from f2l.colour.chart import srgb_encode_uint8

    cam = spec["camera"]
    if options.clipping:
        exposure = 1.0 / max(np.percentile(image.max(axis=-1)[face], cam["exposure_percentile"]), 1e-12)
    else:
        exposure = 0.9 / max(image[face].max(), 1e-12)
    exposed = image * exposure
    noise_rng = _stream(spec["seed"], spec["index"], 5)
    sigma = np.sqrt(cam["shot_noise"] * np.clip(exposed, 0, None) + cam["read_noise"] ** 2)
    return srgb_encode_uint8(exposed + sigma * noise_rng.standard_normal(exposed.shape)), float(exposure)


def render_case(spec: dict, options: RenderOptions) -> dict:
    """Render one drawn case; returns the linear image, 8-bit photo, probe and extra meta."""
    from f2l.render.heads import anny_head, canonical_head
    from f2l.render.scene import ground_truth_probe, render_head

    t0 = time.perf_counter()
    head_rng = _stream(spec["seed"], spec["index"], 1)
    tone = spec["material"]["skin_tone"]
    head = anny_head(head_rng, skin_tone=tone) if options.head == "anny" else canonical_head(head_rng, skin_tone=tone)
    cam = spec["camera"]
    fov = cam["fov_x_deg"]
    distance = 8.0 / (cam["head_width_fraction"] * np.tan(np.radians(fov) / 2.0))
    frame_width_cm = 2.0 * distance * np.tan(np.radians(fov) / 2.0)
    rotation = _rotation(cam["yaw_deg"], cam["pitch_deg"], cam["roll_deg"])
    offset = np.array([cam["offset_fraction"][0] * frame_width_cm, cam["offset_fraction"][1] * frame_width_cm, 0.0])
    front = (np.abs(head.vertices[:, 0]) < 6.5) & (head.vertices[:, 1] < 1.0) & (head.vertices[:, 1] > -11.0) \
        & (head.vertices[:, 2] > -2.0)
    posed = head.posed(rotation, offset)
    posed.info["face_front_points"] = posed.vertices[front]
    settings = render_settings(spec, options, options.image_px, options.image_px, fov, distance)
    lighting = _lighting(spec["lighting"])
    t_head = time.perf_counter()
    result = render_head(posed, lighting, settings)
    t_render = time.perf_counter()
    image = result["image"].astype(np.float64)
    rows, cols = _face_box(posed, settings, options.image_px)
    depth = result["depth_cm"]
    on_head = (depth > 0) & (np.abs(depth - distance) < 40.0)
    face = np.zeros_like(on_head)
    face[rows, cols] = True
    face &= on_head
    if not face.any():
        raise RuntimeError(f"{spec['face_id']}: the face is not in the frame")
    photo, exposure = expose(image, face, spec, options)
    probe = ground_truth_probe(lighting, PROBE_GRID) * exposure
    t_done = time.perf_counter()
    clipped = float((photo[face] == 255).any(axis=-1).mean())
    meta = {"head": {k: v for k, v in head.info.items()}, "settings": {**asdict(settings)},
            "pose": {"rotation": rotation.round(8).tolist(), "translation_cm": offset.round(6).tolist()},
            "focal_px": result["focal_px"], "exposure": float(exposure), "face_clipped_fraction": round(clipped, 5),
            "face_box": [int(rows.start), int(rows.stop), int(cols.start), int(cols.stop)],
            "sky": _sun_of(probe, spec["lighting"]),
            "timings_s": {"head": round(t_head - t0, 3), "render": round(t_render - t_head, 3),
                          "probe_and_photo": round(t_done - t_render, 3)}}
    return {"photo": photo, "probe": probe.astype(np.float32), "meta": meta, "head": posed}


def _exif(focal_px: float):
    from f2l.synth.dataset import camera_exif

    exif = camera_exif(focal_px)
    exif[0x010F] = "f2l eval render-faces"
    exif[0x0110] = "Mitsuba 3 path tracer, pinhole"
    return exif


def _write_case(out: Path, spec: dict, options: RenderOptions, rendered: dict) -> None:
    from PIL import Image

    from f2l.io.atomic import atomic_path, write_text_atomic
    from f2l.io.exr import write_exr

    fid = spec["face_id"]
    for sub in ("photos", "png", "probes", "truth", "meta"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    image = Image.fromarray(rendered["photo"])
    exif = _exif(rendered["meta"]["focal_px"])
    with atomic_path(out / "photos" / f"{fid}.jpg") as tmp:
        image.save(tmp, format="JPEG", quality=95, exif=exif)
    with atomic_path(out / "png" / f"{fid}.png") as tmp:
        image.save(tmp, format="PNG")
    write_exr(out / "probes" / f"{fid}.exr", rendered["probe"], {"f2l_convention": "latlong +Y up, u=0.5 is -Z",
                                                                  "f2l_face_id": fid})
    head = rendered["head"]
    with atomic_path(out / "truth" / f"{fid}.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, vertices_cm=head.vertices.astype(np.float32), faces=head.faces.astype(np.int32),
                                normals=head.normals.astype(np.float32), part=head.part.astype(np.int8),
                                **rendered.get("truth_extra", {}))
    meta = {**spec, "options": asdict(options), **rendered["meta"]}
    write_text_atomic(out / "meta" / f"{fid}.json", json.dumps(meta, indent=1))


def render_faces(out: Path, n: int, seed: int = 0, options: RenderOptions = RenderOptions(), *,
                 start: int = 0, progress: ProgressCallback | None = None, session_size: int = 1) -> dict:
    """Render cases ``start .. start + n − 1`` into ``out`` (module docstring); resumable.

    A case that fails is recorded with its reason in the summary and ``render_status.json``; the
    others go on. ``progress``: a callback told of each case (:mod:`f2l.io.progress`).
    ``session_size`` K > 1: sessions of K photos under one light (:func:`draw_session_case`).
    """
    summary = {"seed": seed, **({"session_size": int(session_size)} if session_size > 1 else {})}
    return render_set(out, range(start, start + n), lambda index: draw_session_case(seed, index, options, session_size),
                      lambda spec: render_case(spec, options), options,
                      summary=summary, status_file="render_status.json", desc="render-faces", unit="face",
                      progress=progress)


def render_set(out: Path, indices, draw, render, options: RenderOptions, *, summary: dict, status_file: str,
               desc: str, unit: str, progress: ProgressCallback | None = None) -> dict:
    """Draw (``draw(index)``), render (``render(spec)``) and write every case of ``indices`` into
    ``out``; a case whose meta exists is skipped (resumable) and a case that fails is recorded
    with its reason in the summary and ``out/status_file``, the others going on. ``summary``
    holds the caller's own keys; ``faces_rendered`` counts the rendered photos' faces. ``progress``:
    a callback told of each case, written, skipped or failed (task ``desc``, counted in ``unit``)."""
    from f2l.io.atomic import write_text_atomic

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    bar = Progress(progress, desc, unit, len(indices))
    status, t0, rendered_s, faces = {}, time.perf_counter(), [], 0
    for index in indices:
        spec = draw(index)
        fid = spec["face_id"]
        if (out / "meta" / f"{fid}.json").is_file():
            status[fid] = "exists"
            bar.advance()
            continue
        t = time.perf_counter()
        try:
            rendered = render(spec)
            _write_case(out, spec, options, rendered)
            status[fid] = "ok"
            faces += len(rendered["meta"].get("faces", [None]))
            rendered_s.append(time.perf_counter() - t)
        except Exception as exc:  # noqa: BLE001 - one bad case never stops the set
            status[fid] = f"error: {type(exc).__name__}: {exc}"
        bar.advance()
    summary = {"out": str(out), "cases": len(status), **summary, "options": asdict(options),
               "ok": sum(v == "ok" for v in status.values()), "faces_rendered": faces,
               "skipped_existing": sum(v == "exists" for v in status.values()),
               "errors": {k: v for k, v in status.items() if v.startswith("error")},
               "elapsed_s": round(time.perf_counter() - t0, 2),
               "seconds_per_case": round(float(np.mean(rendered_s)), 2) if rendered_s else None}
    write_text_atomic(out / status_file, json.dumps({"summary": summary, "status": status}, indent=1))
    return summary
