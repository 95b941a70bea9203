"""Small synthetic clips for the video tests: f2l's own renderer (f2l.synth.render) with the head
turning under clear skies, one exposure for the whole clip, written as MP4."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from f2l.io.photo.exif import DIAGONAL_35MM_MM
from f2l.lighting.grid import LatLongGrid, direction_from_angles
from f2l.synth.render import FOV_DEG, render_face
from f2l.synth.skies import clear_sky

RENDER_GRID = LatLongGrid(32, 64)
ALBEDO = (0.55, 0.38, 0.30)
BACKDROPS = ((70, 90, 120), (60, 110, 60), (120, 100, 80))


def focal_35mm(size_px: int) -> float:
    """The 35 mm-equivalent focal length of f2l.synth's square camera of ``size_px``."""
    focal_px = size_px / 2.0 / math.tan(math.radians(FOV_DEG) / 2.0)
    return focal_px / math.hypot(size_px, size_px) * DIAGONAL_35MM_MM


def synth_clip(path: Path, suns_deg: list[tuple[float, float]], renders: int = 4, hold: int = 3,
               size_px: int = 160, fps: float = 24.0, yaw_range_deg: float = 25.0, power: list[float] | None = None,
               probes: list | None = None):
    """Write a clip: for each (elevation, azimuth) sun a segment of ``renders`` head poses (yaw
    from -range to +range), each held ``hold`` frames; ``power`` scales each segment's light (a
    cloud). Returns the truth: per frame its segment and sun direction (camera frame); ``probes``
    (a list) receives each segment's true probe (in the renderer's units, before exposure)."""
    import cv2

    from f2l.synth.render import _srgb_decode, _srgb_encode

    rng = np.random.default_rng(0)
    probes = [] if probes is None else probes
    frames, truth, scale = [], [], None
    for k, (el, az) in enumerate(suns_deg):
        probe = clear_sky(RENDER_GRID, math.radians(el), math.radians(az))
        probe = probe * (1.0 if power is None else power[k])
        probes.append(probe)
        for i in range(renders):
            yaw = -yaw_range_deg + 2 * yaw_range_deg * i / max(renders - 1, 1)
            face = render_face(RENDER_GRID, probe, rng, image_size=size_px, head_pose_deg=(yaw, 4.0, 0.0),
                               features=True, albedo=ALBEDO)
            own = face.meta["exposure_scale"]
            scale = own if scale is None else scale
            linear = _srgb_decode(face.photo_srgb.astype(np.float64) / 255.0) / own * scale
            image = np.clip(np.rint(_srgb_encode(np.clip(linear, 0, 1)) * 255), 0, 255).astype(np.uint8)
            background = (image.max(axis=2) == 0)[..., None]  # each shot its own backdrop
            image = np.where(background, np.asarray(BACKDROPS[k % len(BACKDROPS)], np.uint8), image)
            for _ in range(hold):
                frames.append(image)
                truth.append({"segment": k, "sun": direction_from_angles(math.radians(el), math.radians(az))})
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (size_px, size_px))
    for image in frames:
        writer.write(cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    writer.release()
    return truth


def sequence_folder(root: Path, suns_deg: list[tuple[float, float]], clip_id: str = "clip-s0-00000-cut", **options) -> Path:
    """A ``render-faces --sequence``-like folder of one synthetic clip: clips/, truth/, probes/."""
    import json

    from f2l.io.exr import write_exr

    for sub in ("clips", "truth", "probes"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    probes: list = []
    size_px = options.get("size_px", 160)
    truth = synth_clip(root / "clips" / f"{clip_id}.mp4", suns_deg, probes=probes, **options)
    focal_px = size_px / 2.0 / math.tan(math.radians(FOV_DEG) / 2.0)
    segments = []
    for k, probe in enumerate(probes):
        rel = f"probes/{clip_id}-seg{k}.exr"
        write_exr(root / rel, probe)
        frames = [i for i, t in enumerate(truth) if t["segment"] == k]
        segments.append({"segment": k, "first_frame": frames[0], "last_frame": frames[-1], "probe": rel,
                         "sky_kind": "clear", "sun_direction": [float(v) for v in truth[frames[0]]["sun"]]})
    fps = options.get("fps", 24.0)
    doc = {"clip_id": clip_id, "kind": "cut" if len(probes) > 1 else "static", "fps": fps, "frames": len(truth),
           "width_px": size_px, "height_px": size_px, "focal_px": focal_px,
           "change_frame": segments[1]["first_frame"] if len(segments) > 1 else None,
           "video": f"clips/{clip_id}.mp4", "segments": segments,
           "per_frame": [{"frame": i, "time_s": i / fps, "segment": t["segment"],
                          "sun_direction": [float(v) for v in t["sun"]]} for i, t in enumerate(truth)]}
    (root / "truth" / f"{clip_id}.json").write_text(json.dumps(doc))
    return root
