"""A neck-and-shoulders occluder posed with the fitted head (``fit-faces --body-proxy``, default on).

The fitted mesh is MediaPipe's face mask only, so every face pixel sees the whole lower
hemisphere. A real person's neck, shoulders and chest hide much of it: the ground, which
reflects the sun, and a low sun itself. On the true geometry of the independent evaluation set
(``make eval-real``), adding the true body below the chin to the fitted mesh's visibility
lowered sunsky's mean sun error on both parts (docs/experiments/accuracy_issue16.md "What each change bought"). This module
stands in for that body with two closed elliptic cylinders of average adult dimensions (not
fitted to any renderer's body).

Canonical frame of MediaPipe's face model, in cm: +Y up, +Z towards the viewer; the chin
(landmark 152) lies at (0, -9.4, 4.3). Dimensions from adult anthropometry (both sexes averaged,
rounded; e.g. NASA-STD-3000 / ANSUR II tables):

- neck: circumference about 36 cm, so radius 5.7 cm; its axis is 7 cm behind the chin tip; it
  runs from 2 cm above the chin (inside the jaw) to 10 cm below it, into the torso;
- torso: biacromial breadth about 40 cm and chest depth about 23 cm, so semi-axes 20 x 11.5 cm;
  its front is roughly under the chin. The top (a flat cap standing in for the shoulders, whose
  slope runs from the trapezius at about 5 cm to the acromion at about 9 cm below the chin) is
  7 cm below the chin, and it runs 45 cm down.

The body is posed rigidly with the head (the head's rotation and translation), which assumes the
head is not turned on the body. ``visibility`` uses the proxy as an occluder only: it never adds
face pixels and never changes a normal.
"""

from __future__ import annotations

import numpy as np

CHIN_CM = np.array([0.0, -9.40, 4.26])  # canonical landmark 152
NECK = {"radius_cm": (5.7, 5.7), "axis_behind_chin_cm": 7.0, "top_above_chin_cm": 2.0, "bottom_below_chin_cm": 10.0}
TORSO = {"radius_cm": (20.0, 11.5), "axis_behind_chin_cm": 10.0, "top_below_chin_cm": 7.0, "length_cm": 45.0}
SEGMENTS = 32


def elliptic_cylinder(centre_xz, radii_xz, y_top: float, y_bottom: float, segments: int = SEGMENTS):
    """A closed elliptic cylinder with a vertical axis: vertices (2S + 2, 3), faces (4S, 3),
    outward-wound (counter-clockwise seen from outside)."""
    a = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    x = centre_xz[0] + radii_xz[0] * np.cos(a)
    z = centre_xz[1] + radii_xz[1] * np.sin(a)
    top = np.stack([x, np.full(segments, y_top), z], 1)
    bottom = np.stack([x, np.full(segments, y_bottom), z], 1)
    caps = np.array([[centre_xz[0], y_top, centre_xz[1]], [centre_xz[0], y_bottom, centre_xz[1]]])
    vertices = np.concatenate([top, bottom, caps])
    i = np.arange(segments)
    j = (i + 1) % segments
    ct, cb = 2 * segments, 2 * segments + 1
    side = np.concatenate([np.stack([i, j, segments + i], 1), np.stack([j, segments + j, segments + i], 1)])
    cap_top = np.stack([np.full(segments, ct), j, i], 1)
    cap_bottom = np.stack([np.full(segments, cb), segments + i, segments + j], 1)
    return vertices, np.concatenate([side, cap_top, cap_bottom]).astype(np.int64)


def body_proxy_canonical() -> tuple[np.ndarray, np.ndarray]:
    """Neck and torso cylinders in the canonical frame (cm): vertices (V, 3), faces (F, 3)."""
    chin_y, chin_z = CHIN_CM[1], CHIN_CM[2]
    neck = elliptic_cylinder((0.0, chin_z - NECK["axis_behind_chin_cm"]), NECK["radius_cm"],
                             chin_y + NECK["top_above_chin_cm"], chin_y - NECK["bottom_below_chin_cm"])
    top = chin_y - TORSO["top_below_chin_cm"]
    torso = elliptic_cylinder((0.0, chin_z - TORSO["axis_behind_chin_cm"]), TORSO["radius_cm"],
                              top, top - TORSO["length_cm"])
    return (np.concatenate([neck[0], torso[0]]),
            np.concatenate([neck[1], torso[1] + len(neck[0])]))


def posed_body_proxy(head_vertices: np.ndarray, canonical_vertices: np.ndarray,
                     rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The proxy in the camera frame, posed like the head: x_cam = R x_canonical + t, with t the
    mean offset between the head's camera-frame vertices and its rotated canonical ones."""
    R = np.asarray(rotation, dtype=np.float64)
    canon = np.asarray(canonical_vertices, dtype=np.float64)[: len(head_vertices)]
    t = (np.asarray(head_vertices, dtype=np.float64) - canon @ R.T).mean(0)
    v, f = body_proxy_canonical()
    return v @ R.T + t, f


def with_body_proxy(vertices: np.ndarray, faces: np.ndarray, head_vertices: np.ndarray,
                    canonical_vertices: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The face mesh (vertices, faces) with the posed proxy appended (for visibility only)."""
    pv, pf = posed_body_proxy(head_vertices, canonical_vertices, rotation)
    return np.concatenate([vertices, pv]), np.concatenate([faces, pf + len(vertices)])
