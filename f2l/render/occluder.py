"""``f2l eval render-faces --framing group --shade-one``: one person of a group photo in an occluder's shadow.

A dark disc (a board held up toward the sun) is put on the line from one person's face toward the
sun, so that face is in full shadow and the others keep their sun. Its draws come from the case's
own stream 8 (:func:`draw_shade`), so a shaded set is the plain set's people, camera and light,
bit for bit, plus the board:

- ``pick`` in [0, 1): which of the persons it may shade (in order) is shaded;
- ``distance_cm`` 50–100 from the face's centre toward the sun, ``diameter_cm`` 40–60.

A person may be shaded (:func:`place_occluder`) when the sky is clear, the sun lights the face
(sun · the face's forward direction > :data:`MIN_SUN_ON_FACE`), nobody else's head is within the
board's shadow cylinder (or the board) on the sun's side of them (:data:`HEAD_RADIUS_CM` on
top of the board's radius), and the board, seen from the camera, covers no face box (padded by
:data:`BOX_PAD`). None may (the sun near the camera's back, say): nothing is shaded and the case
says why. The board may still show elsewhere in the photo (``in_frame``).
"""

from __future__ import annotations

import numpy as np

MIN_SUN_ON_FACE = 0.15
HEAD_RADIUS_CM = 13.0
BOX_PAD = 0.15
RIM_POINTS = 48
SHADE_STREAM = 8


def draw_shade(seed: int, index: int) -> dict:
    """The board's draws of case ``index`` (JSON-ready), from their own stream."""
    rng = np.random.default_rng([int(seed), int(index), SHADE_STREAM])
    return {"pick": round(float(rng.uniform()), 6), "distance_cm": round(float(rng.uniform(50.0, 100.0)), 3),
            "diameter_cm": round(float(rng.uniform(40.0, 60.0)), 3)}


def disc_points(center: np.ndarray, normal: np.ndarray, radius: float, n: int = RIM_POINTS) -> np.ndarray:
    """The disc's centre and ``n`` points of its rim, (n + 1, 3)."""
    normal = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    a = np.cross(normal, [0.0, 1.0, 0.0] if abs(normal[1]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    rim = center + radius * (np.cos(t)[:, None] * a + np.sin(t)[:, None] * b)
    return np.concatenate([np.asarray(center, np.float64)[None], rim])


def _overlaps(a, b) -> bool:
    return not (a[2] < b[0] or b[2] < a[0] or a[3] < b[1] or b[3] < a[1])


def _padded(box) -> list[float]:
    x0, y0, x1, y1 = box
    px, py = BOX_PAD * (x1 - x0), BOX_PAD * (y1 - y0)
    return [x0 - px, y0 - py, x1 + px, y1 + py]


def place_occluder(shade: dict, sun: np.ndarray, centres: np.ndarray, forwards: np.ndarray, boxes: list,
                   project, frame: tuple[int, int]) -> dict:
    """Where the board goes (module docstring): ``{"shaded_person": i or None, "occluder": {center_cm,
    normal, radius_cm, in_frame} or None, "shade_note": why not / which persons could be}``.

    ``sun`` unit (toward the sun), ``centres`` (P, 3) the faces' centres (cm), ``forwards`` (P, 3)
    where they look, ``boxes`` their face boxes in the photo (x0, y0, x1, y1), ``project(points)``
    -> (cols, rows, in_front) in the photo, ``frame`` (width, height) px."""
    sun = np.asarray(sun, np.float64) / np.linalg.norm(sun)
    radius, distance = shade["diameter_cm"] / 2.0, shade["distance_cm"]
    candidates, boards, why = [], {}, []
    for k, centre in enumerate(np.asarray(centres, np.float64)):
        if float(forwards[k] @ sun) <= MIN_SUN_ON_FACE:
            why.append(f"{k}: the sun does not light the face")
            continue
        v = np.asarray(centres, np.float64) - centre
        along = v @ sun
        perp = np.linalg.norm(v - along[:, None] * sun, axis=1)
        blocked = [j for j in range(len(v)) if j != k and along[j] < distance + HEAD_RADIUS_CM
                   and perp[j] < radius + HEAD_RADIUS_CM]
        if blocked:
            why.append(f"{k}: person {blocked[0]} would be in its shadow")
            continue
        points = disc_points(centre + distance * sun, sun, radius)
        cols, rows, front = project(points)
        if front.all():
            seen = [float(cols.min()), float(rows.min()), float(cols.max()), float(rows.max())]
            covers = [j for j, box in enumerate(boxes) if _overlaps(seen, _padded(box))]
            in_frame = _overlaps(seen, [0.0, 0.0, float(frame[0]), float(frame[1])])
        elif front.any():  # across the camera's plane: no bound in the photo
            covers, in_frame = list(range(len(boxes))), True
        else:  # behind the camera
            covers, in_frame = [], False
        if covers:
            why.append(f"{k}: the board would cover face {covers[0]} in the photo")
            continue
        candidates.append(k)
        boards[k] = {"center_cm": [round(float(c), 4) for c in points[0]], "normal": [round(float(c), 6) for c in sun],
                     "radius_cm": radius, "in_frame": bool(in_frame)}
    if not candidates:
        return {"shaded_person": None, "occluder": None, "shade_note": "; ".join(why) or "no person"}
    k = candidates[min(int(shade["pick"] * len(candidates)), len(candidates) - 1)]
    return {"shaded_person": k, "occluder": boards[k], "shade_note": f"candidates {candidates}"}
