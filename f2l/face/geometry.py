"""Per-photo face geometry from 478 landmarks: a metric mesh in the camera frame, rasterised.

Camera: a pinhole at the origin looking along -Z (f2l's world = camera frame, +Y up), focal
length ``focal_px`` and principal point at the photo centre. Photo coordinates are continuous
(x right, y down, pixel centres at +0.5); the ray of (x, y) is
``((x - cx) / f, -(y - cy) / f, -1)``.

Reconstruction (``reconstruct_vertices``), three ``depth_source`` modes. MediaPipe's landmarks
are perspective image positions plus a relative depth z in the same pixel scale (smaller =
nearer). The weak-perspective shape S = (x, -y, -z) is aligned to the canonical mesh C (cm) by
a similarity transform (Umeyama): S ≈ s R C + t, so s is pixels per cm at the face, R the head
pose, and the face lies at depth d = f / s (the canonical face's size is assumed).

* ``"rigid"`` (default): C itself, posed by a perspective fit of (R, t) to the 2D landmarks
  (Huber reprojection loss): MediaPipe's own face-geometry model. Per-person shape is ignored;
  2D landmark noise (~1-2% of the face) averages out instead of bending the normals.
* ``"canonical"``: each landmark back-projected along its pixel's ray to the depth
  d - (R C_i)_z (per-person outline, mean-face relief).
* ``"landmarks"``: the same with MediaPipe's own relative depth (S_z,i - mean S_z) / s.

Measured on synthetic photos of the canonical face (``make eval-fit-faces``), the median normal
error on the skin mask is about 1.8° / 4.7° / 6.1° for the three modes. The 468-vertex mesh
(MediaPipe's 898-triangle topology) is Loop-subdivided for normals that are smooth at the pixel
scale.

The working view (``working_view``) is a square crop around the landmarks, resampled to
``resolution`` × ``resolution`` pixels; its pixel (r, c) looks through photo point
``(x0 + (c + 0.5) k, y0 + (r + 0.5) k)`` with k = side / resolution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

NUM_MESH_LANDMARKS = 468
DEPTH_SOURCES = ("landmarks", "canonical", "rigid")
MIN_FACING = 0.1  # keep pixels whose normal faces the camera: <n, -d> > MIN_FACING


@dataclass(frozen=True)
class HeadFit:
    """Landmarks lifted to 3D: vertices (468, 3) cm in the camera frame, the head rotation R
    (canonical → camera), pose angles in degrees (R = R_y(yaw) R_x(pitch) R_z(roll)), the
    centroid distance in cm, the scale in px/cm and the alignment residual (RMS, in cm)."""

    vertices: np.ndarray
    rotation: np.ndarray
    yaw_deg: float
    pitch_deg: float
    roll_deg: float
    distance_cm: float
    px_per_cm: float
    residual_cm: float


@dataclass(frozen=True)
class WorkingView:
    """A square crop of the photo resampled to ``resolution`` px (see the module docstring)."""

    x0: float
    y0: float
    side: float
    resolution: int

    @property
    def step(self) -> float:
        return self.side / self.resolution

    def photo_xy(self, rc: np.ndarray) -> np.ndarray:
        """Photo coordinates (M, 2) of working pixel centres (M, 2) (row, col)."""
        rc = np.asarray(rc, dtype=np.float64)
        return np.stack([self.x0 + (rc[:, 1] + 0.5) * self.step,
                         self.y0 + (rc[:, 0] + 0.5) * self.step], axis=1)

    def to_working(self, xy: np.ndarray) -> np.ndarray:
        """Photo coordinates (M, 2) → continuous working coordinates (x, y)."""
        xy = np.asarray(xy, dtype=np.float64)[:, :2]
        return (xy - np.array([self.x0, self.y0])) / self.step

    def to_meta(self) -> dict:
        return {"x0": float(self.x0), "y0": float(self.y0), "side": float(self.side),
                "resolution": int(self.resolution)}


def rays_for(xy: np.ndarray, focal_px: float, image_hw: tuple[int, int]) -> np.ndarray:
    """Unit camera rays (M, 3) through photo points (M, 2)."""
    h, w = image_hw
    xy = np.asarray(xy, dtype=np.float64)
    d = np.stack([(xy[:, 0] - w / 2.0) / focal_px, -(xy[:, 1] - h / 2.0) / focal_px,
                  -np.ones(len(xy))], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def similarity_fit(source: np.ndarray, target: np.ndarray):
    """Umeyama: (s, R, t) minimising ||target - (s R source + t)||² over rotations R."""
    mu_s, mu_t = source.mean(0), target.mean(0)
    a, b = source - mu_s, target - mu_t
    u, sig, vt = np.linalg.svd(b.T @ a / len(a))
    d = np.ones(3)
    d[2] = np.sign(np.linalg.det(u @ vt)) or 1.0
    rot = u @ np.diag(d) @ vt
    scale = float((sig * d).sum() / (a**2).sum(1).mean())
    return scale, rot, mu_t - scale * rot @ mu_s


def pose_angles_deg(rot: np.ndarray) -> tuple[float, float, float]:
    """(yaw, pitch, roll) in degrees with R = R_y(yaw) R_x(pitch) R_z(roll)."""
    pitch = math.asin(float(np.clip(-rot[1, 2], -1.0, 1.0)))
    yaw = math.atan2(float(rot[0, 2]), float(rot[2, 2]))
    roll = math.atan2(float(rot[1, 0]), float(rot[1, 1]))
    return math.degrees(yaw), math.degrees(pitch), math.degrees(roll)


def reconstruct_vertices(landmarks_px: np.ndarray, focal_px: float, image_hw: tuple[int, int],
                         canonical_cm: np.ndarray, depth_source: str = "rigid") -> HeadFit:
    """Lift the 468 mesh landmarks (x, y, z px) to camera-frame vertices in cm."""
    if depth_source not in DEPTH_SOURCES:
        raise ValueError(f"depth_source must be one of {DEPTH_SOURCES}, got {depth_source!r}")
    lm = np.asarray(landmarks_px, dtype=np.float64)[:NUM_MESH_LANDMARKS]
    canon = np.asarray(canonical_cm, dtype=np.float64)
    shape_px = np.stack([lm[:, 0], -lm[:, 1], -lm[:, 2]], axis=1)
    s, rot, t = similarity_fit(canon, shape_px)
    residual = float(np.sqrt(((shape_px - (s * canon @ rot.T + t)) ** 2).sum(1).mean()) / s)
    if depth_source == "landmarks":
        rel_depth = (shape_px[:, 2] - shape_px[:, 2].mean()) / s
    else:
        posed = canon @ rot.T
        rel_depth = posed[:, 2] - posed[:, 2].mean()
    distance = float(focal_px) / s
    h, w = image_hw
    if depth_source == "rigid":
        rot, centre = rigid_pose(lm[:, :2], canon, rot, distance, focal_px, image_hw)
        vertices = (canon - canon.mean(0)) @ rot.T + centre
        resid = _project(vertices, focal_px, image_hw) - lm[:, :2]
        yaw, pitch, roll = pose_angles_deg(rot)
        return HeadFit(vertices=vertices, rotation=rot, yaw_deg=yaw, pitch_deg=pitch,
                       roll_deg=roll, distance_cm=float(-centre[2]), px_per_cm=float(s),
                       residual_cm=float(np.sqrt((resid**2).sum(1).mean()) * -centre[2] / focal_px))
    depth = distance - rel_depth  # > 0, along -Z
    x = (lm[:, 0] - w / 2.0) / focal_px * depth
    y = -(lm[:, 1] - h / 2.0) / focal_px * depth
    vertices = np.stack([x, y, -depth], axis=1)
    yaw, pitch, roll = pose_angles_deg(rot)
    return HeadFit(vertices=vertices, rotation=rot, yaw_deg=yaw, pitch_deg=pitch, roll_deg=roll,
                   distance_cm=distance, px_per_cm=float(s), residual_cm=residual)


def _project(points: np.ndarray, focal_px: float, image_hw) -> np.ndarray:
    h, w = image_hw
    z = -points[:, 2]
    return np.stack([w / 2.0 + focal_px * points[:, 0] / z,
                     h / 2.0 - focal_px * points[:, 1] / z], axis=1)


def rigid_pose(landmarks_xy: np.ndarray, canonical_cm: np.ndarray, rot0: np.ndarray,
               distance0: float, focal_px: float, image_hw):
    """Perspective pose of the canonical face (metric size kept): (R, centroid) minimising the
    landmarks' reprojection error (Huber, scipy ``least_squares``), from a weak-perspective start."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    c = canonical_cm - canonical_cm.mean(0)
    xy = landmarks_xy[:NUM_MESH_LANDMARKS]
    h, w = image_hw
    centre_xy = xy.mean(0)
    t0 = np.array([(centre_xy[0] - w / 2.0) / focal_px * distance0,
                   -(centre_xy[1] - h / 2.0) / focal_px * distance0, -distance0])
    x0 = np.concatenate([Rotation.from_matrix(rot0).as_rotvec(), t0])

    def residual(x):
        pts = c @ Rotation.from_rotvec(x[:3]).as_matrix().T + x[3:]
        return (_project(pts, focal_px, image_hw) - xy).ravel()

    scale_px = float(np.ptp(xy, axis=0).max())
    sol = least_squares(residual, x0, loss="huber", f_scale=0.01 * scale_px, x_scale="jac")
    return Rotation.from_rotvec(sol.x[:3]).as_matrix(), sol.x[3:]


def subdivided_mesh(vertices: np.ndarray, faces: np.ndarray, subdivisions: int = 2):
    """Loop-subdivided mesh: (vertices (V, 3) float64, faces (F, 3) int64, unit vertex normals
    (V, 3) oriented toward the camera side of the face). The subdivision is a cached sparse
    matrix per topology (:mod:`f2l.face.subdivision`); trimesh's (which splits the mesh into
    bodies) for a non-manifold one."""
    import trimesh

    from f2l.face.subdivision import loop_subdivision

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if subdivisions:
        try:
            s, f = loop_subdivision(f, len(v), int(subdivisions))
            v = s @ v
        except ValueError:
            v, f = trimesh.remesh.subdivide_loop(v, f, iterations=int(subdivisions))
    mesh = trimesh.Trimesh(vertices=v, faces=f, process=False)
    n = np.asarray(mesh.vertex_normals, dtype=np.float64)
    f = np.asarray(f, dtype=np.int64)
    # the canonical winding makes normals point out of the face; the lift keeps handedness, so
    # they face the camera; flip if a degenerate fit turned the mesh inside out
    if np.einsum("ij,ij->i", n, -v).mean() < 0:
        f, n = f[:, ::-1].copy(), -n
    return v, f, n


def working_view(landmarks_px: np.ndarray, resolution: int, margin: float = 0.08) -> WorkingView:
    """The square crop around the 468 mesh landmarks, ``margin`` × its side added on each side."""
    xy = np.asarray(landmarks_px, dtype=np.float64)[:NUM_MESH_LANDMARKS, :2]
    lo, hi = xy.min(0), xy.max(0)
    side = float((hi - lo).max()) * (1.0 + 2.0 * margin)
    centre = (lo + hi) / 2.0
    return WorkingView(x0=float(centre[0] - side / 2), y0=float(centre[1] - side / 2), side=side,
                       resolution=int(resolution))


def rasterise(vertices: np.ndarray, faces: np.ndarray, vertex_normals: np.ndarray,
              rays: np.ndarray):
    """Primary rays from the camera centre (embreex INTERSECT).

    Returns (hit_index (M,) into ``rays``, points (M, 3), unit normals (M, 3)) for the rays that
    hit the mesh with the interpolated normal facing the camera by more than MIN_FACING.
    """
    from f2l.transport.visibility import scene_for

    d = np.ascontiguousarray(rays, dtype=np.float32)
    res = scene_for(vertices, faces).intersect(np.zeros_like(d), d)
    prim = res["primID"].astype(np.int64)
    idx = np.nonzero(prim >= 0)[0]
    bu, bv = res["u"][idx].astype(np.float64), res["v"][idx].astype(np.float64)
    tri = faces[prim[idx]]
    w = np.stack([1.0 - bu - bv, bu, bv], axis=1)
    points = np.einsum("nk,nkc->nc", w, vertices[tri])
    normals = np.einsum("nk,nkc->nc", w, vertex_normals[tri])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    facing = np.einsum("nc,nc->n", normals, -rays[idx]) > MIN_FACING
    return idx[facing], points[facing], normals[facing]
