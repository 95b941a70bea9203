"""``f2l eval render-faces --framing half|full|group``: path-traced photos framed as people frame them.

The portrait framing (:mod:`f2l.render.dataset`) puts one head at 35–55% of a square frame. Real
outdoor photos are mostly wider; here each case draws, from its own seeded streams:

- a 3:2 frame (``image_px`` on its long side; a quarter of the cases upright, 2:3), a pinhole
  camera of 40–65° horizontal field of view;
- ``half``: one person, the head (16 cm wide) 12–25% of the long side; ``full``: one person,
  4–10%; ``group``: 2–5 people shoulder to shoulder (centres 34–48 cm apart, depths ±12%), each
  head 5–14% of the long side. The heads' widths in the photo put their faces at roughly 40 px
  and up for a long side of 1280 px;
- each person their own Anny adult (skin light to dark), yaw ±50°, pitch ±12°, roll ±6°, all
  in one scene, so heads shade each other under a low sun;
- lighting, skin material, exposure (a percentile of all the faces' brightest channel to 1.0),
  noise and 8-bit sRGB as :mod:`f2l.render.dataset`.

``shade_one`` (``--shade-one``): a dark board puts one person's face in its shadow on clear
skies (:mod:`f2l.render.occluder`; its draws ``shade`` from a stream of their own, the rest of the
case unchanged); meta gains ``shaded_person`` (an index of ``persons``, or null), ``occluder``
and ``shade_note``. The probe stays the sky's.

Written per case (ids ``pbr-<framing>-s<seed>-<index>``): ``photos/<id>.jpg``, ``png/<id>.png``,
``probes/<id>.exr`` (one light for every face of the photo), ``truth/<id>.npz`` (the scene's
merged mesh with each triangle's person) and ``meta/<id>.json`` (every draw, and ``faces``: per
person the true face box in photo px (x0, y0, x1, y1: cheek to cheek, chin to mid-forehead),
its width, pose and distance), written last: resumable like the portraits.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from f2l.io.progress import ProgressCallback
from f2l.render.dataset import PROBE_GRID, RenderOptions, _lighting, _rotation, _stream, _sun_of, expose, render_set, render_settings
from f2l.render.occluder import draw_shade, place_occluder

FRAMINGS = ("portrait", "half", "full", "group")
HEAD_WIDTH_CM = 16.0
# (people, head width as a fraction of the frame's long side)
FRAMING_DRAWS = {"half": ((1, 1), (0.12, 0.25)), "full": ((1, 1), (0.04, 0.10)), "group": ((2, 5), (0.05, 0.14))}
# the face box in the head's own frame (cm; eyes' midpoint at the origin, +Y up, +Z out of the face)
FACE_BOX_X_CM, FACE_BOX_Y_CM, FACE_BOX_Z_MIN_CM = 7.0, (-12.0, 6.0), -2.0


def framed_case_id(framing: str, seed: int, index: int) -> str:
    return f"pbr-{framing}-s{seed}-{index:05d}"


def draw_framed_case(framing: str, seed: int, index: int, options: RenderOptions = RenderOptions()) -> dict:
    """Every random choice of a framed case except the heads' own (JSON-ready)."""
    from f2l.render.dataset import draw_case

    if framing not in FRAMING_DRAWS:
        raise ValueError(f"framing must be one of {', '.join(FRAMING_DRAWS)}, got {framing!r}")
    base = draw_case(seed, index, options)  # lighting, material, exposure and noise draws
    rng = _stream(seed, index, 7)
    (lo_n, hi_n), (lo_f, hi_f) = FRAMING_DRAWS[framing]
    people = int(rng.integers(lo_n, hi_n + 1))
    upright = bool(rng.uniform() < 0.25)
    fov = float(rng.uniform(40.0, 65.0))
    fraction = float(np.exp(rng.uniform(np.log(lo_f), np.log(hi_f))))
    spacing = rng.uniform(34.0, 48.0, size=max(people - 1, 0))
    persons = []
    x = -float(spacing.sum()) / 2.0
    for i in range(people):
        persons.append({"x_cm": round(x, 3), "y_cm": round(float(rng.uniform(-6.0, 6.0)), 3),
                        "depth_scale": round(float(rng.uniform(0.88, 1.12)) if people > 1 else 1.0, 4),
                        "yaw_deg": round(float(rng.uniform(-50, 50)), 3), "pitch_deg": round(float(rng.uniform(-12, 12)), 3),
                        "roll_deg": round(float(rng.uniform(-6, 6)), 3),
                        "skin_tone": round(float(rng.uniform(0.0, 1.0)), 4)})
        if i < people - 1:
            x += float(spacing[i])
    shift = [float(rng.uniform(-0.2, 0.2)), float(rng.uniform(-0.15, 0.15))]  # the group's place in the frame
    camera = {**base["camera"], "fov_x_deg": round(fov, 4), "head_width_fraction": round(fraction, 5),
              "upright": upright, "shift_fraction": [round(v, 4) for v in shift]}
    spec = {**base, "face_id": framed_case_id(framing, seed, index), "framing": framing, "camera": camera,
            "persons": persons}
    if options.shade_one:
        spec["shade"] = draw_shade(seed, index)
    return spec


def _frame_size(long_px: int, upright: bool) -> tuple[int, int]:
    short = int(round(long_px * 2 / 3))
    return (short, long_px) if upright else (long_px, short)


def _face_corners(head) -> np.ndarray:
    """The face box's region of a head in its own frame: vertices cheek to cheek, chin to forehead."""
    v = head.vertices
    sel = (np.abs(v[:, 0]) < FACE_BOX_X_CM) & (v[:, 1] > FACE_BOX_Y_CM[0]) & (v[:, 1] < FACE_BOX_Y_CM[1]) \
        & (v[:, 2] > FACE_BOX_Z_MIN_CM)
    return sel


def _merge(heads) -> tuple:
    from f2l.render.heads import Head

    offsets = np.cumsum([0] + [len(h.vertices) for h in heads[:-1]])
    merged = Head(np.concatenate([h.vertices for h in heads]),
                  np.concatenate([h.faces + o for h, o in zip(heads, offsets)]),
                  np.concatenate([h.albedo for h in heads]), np.concatenate([h.part for h in heads]),
                  np.concatenate([h.normals for h in heads]), {})
    person = np.concatenate([np.full(len(h.faces), i, np.int16) for i, h in enumerate(heads)])
    return merged, person


def render_framed_case(spec: dict, options: RenderOptions) -> dict:
    """Render one framed case: the photo, the probe, the merged mesh and the per-face truth."""
    from f2l.render.heads import anny_head
    from f2l.render.scene import ground_truth_probe, render_head

    t0 = time.perf_counter()
    cam = spec["camera"]
    width_px, height_px = _frame_size(options.image_px, cam["upright"])
    long_px = max(width_px, height_px)
    fov = cam["fov_x_deg"]
    tan = np.tan(np.radians(fov) / 2.0)
    # the head is head_width_fraction of the long side: frame's long side in cm at the distance
    long_cm = HEAD_WIDTH_CM / cam["head_width_fraction"]
    width_cm = long_cm * width_px / long_px
    distance = width_cm / (2.0 * tan)
    height_cm = width_cm * height_px / width_px
    heads, faces_truth = [], []
    group_x = cam["shift_fraction"][0] * width_cm
    group_y = cam["shift_fraction"][1] * height_cm
    for i, person in enumerate(spec["persons"]):
        head = anny_head(_stream(spec["seed"], spec["index"], 100 + i), skin_tone=person["skin_tone"])
        rotation = _rotation(person["yaw_deg"], person["pitch_deg"], person["roll_deg"])
        z = distance * (1.0 - person["depth_scale"])  # farther people: negative z (the camera is at +z)
        offset = np.array([group_x + person["x_cm"], group_y + person["y_cm"], z])
        corners = _face_corners(head)
        posed = head.posed(rotation, offset)
        heads.append(posed)
        faces_truth.append({"corners": posed.vertices[corners], "person": i, "pose": person,
                            "distance_cm": float(distance - z), "forward": rotation[:, 2]})
    scene_head, person_of_face = _merge(heads)
    settings = render_settings(spec, options, width_px, height_px, fov, distance)
    lighting = _lighting(spec["lighting"])
    shade = _shade(spec, lighting, faces_truth, settings, distance) if options.shade_one else None
    t_head = time.perf_counter()
    occluders = [shade["occluder"]] if shade and shade["occluder"] else []
    result = render_head(scene_head, lighting, settings, occluders=occluders)
    t_render = time.perf_counter()
    image = result["image"].astype(np.float64)
    focal = result["focal_px"]
    face_pixels = np.zeros(image.shape[:2], bool)
    truths = []
    for truth in faces_truth:
        p = truth.pop("corners")
        truth.pop("forward")
        zc = distance - p[:, 2]
        col = width_px / 2 + focal * p[:, 0] / zc
        row = height_px / 2 - focal * p[:, 1] / zc
        box = [float(col.min()), float(row.min()), float(col.max()), float(row.max())]
        inside = not (box[2] < 0 or box[0] > width_px or box[3] < 0 or box[1] > height_px)
        c0, c1 = np.clip([int(box[0]), int(np.ceil(box[2]))], 0, width_px)
        r0, r1 = np.clip([int(box[1]), int(np.ceil(box[3]))], 0, height_px)
        face_pixels[r0:r1, c0:c1] = True
        truths.append({**truth, "box": [round(v, 2) for v in box], "width_px": round(box[2] - box[0], 2),
                       "in_frame": bool(inside and box[0] >= 0 and box[1] >= 0 and box[2] <= width_px
                                        and box[3] <= height_px)})
    depth = result["depth_cm"]
    face_pixels &= depth > 0
    if not face_pixels.any():
        raise RuntimeError(f"{spec['face_id']}: no face is in the frame")
    photo, exposure = expose(image, face_pixels, spec, options)
    probe = ground_truth_probe(lighting, PROBE_GRID) * exposure
    t_done = time.perf_counter()
    meta = {"settings": asdict(settings), "focal_px": focal, "exposure": float(exposure),
            "image_size": [width_px, height_px], "faces": truths, "sky": _sun_of(probe, spec["lighting"]),
            "timings_s": {"heads": round(t_head - t0, 3), "render": round(t_render - t_head, 3),
                          "probe_and_photo": round(t_done - t_render, 3)}}
    if shade is not None:
        meta.update(shade)
    return {"photo": photo, "probe": probe.astype(np.float32), "meta": meta, "head": scene_head,
            "truth_extra": {"person": person_of_face}}


def _project(points: np.ndarray, settings, distance: float):
    """(cols, rows, in front of the camera) of points (N, 3) in the photo of ``settings``."""
    focal = settings.width_px / (2.0 * np.tan(np.radians(settings.fov_x_deg) / 2.0))
    zc = distance - points[:, 2]
    safe = np.where(zc > 1.0, zc, 1.0)
    return (settings.width_px / 2 + focal * points[:, 0] / safe, settings.height_px / 2 - focal * points[:, 1] / safe,
            zc > 1.0)


def _shade(spec: dict, lighting, faces_truth: list[dict], settings, distance: float) -> dict:
    """The board of a ``shade_one`` case (f2l.render.occluder): none under an overcast sky."""
    from f2l.render.scene import ground_truth_probe

    sky = _sun_of(ground_truth_probe(lighting, PROBE_GRID), spec["lighting"])
    if sky["kind"] != "clear":
        return {"shaded_person": None, "occluder": None, "shade_note": "overcast"}
    boxes = []
    for truth in faces_truth:
        cols, rows, _ = _project(truth["corners"], settings, distance)
        boxes.append([float(cols.min()), float(rows.min()), float(cols.max()), float(rows.max())])
    centres = np.array([t["corners"].mean(axis=0) for t in faces_truth])
    forwards = np.array([t["forward"] for t in faces_truth])
    return place_occluder(spec["shade"], np.asarray(sky["sun_direction"]), centres, forwards, boxes,
                          lambda p: _project(p, settings, distance), (settings.width_px, settings.height_px))


def render_framed(out: Path, framing: str, n: int, seed: int = 0, options: RenderOptions = RenderOptions(), *,
                  start: int = 0, progress: ProgressCallback | None = None) -> dict:
    """Render framed cases ``start .. start + n − 1`` into ``out``; resumable; a failing case is
    recorded with its reason and the others go on. ``progress``: a callback told of each case
    (:mod:`f2l.io.progress`)."""
    return render_set(out, range(start, start + n), lambda index: draw_framed_case(framing, seed, index, options),
                      lambda spec: render_framed_case(spec, options), options,
                      summary={"framing": framing, "seed": seed}, status_file=f"render_status_{framing}.json",
                      desc=f"render-faces ({framing})", unit="photo", progress=progress)
