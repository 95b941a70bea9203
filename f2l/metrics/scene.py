"""The fixed evaluation scene of the rendering metrics "(s)" (Calian et al. 2018, §5.1).

Everything below is part of the evaluation protocol (``docs/metrics.md``); changing any constant
changes the reported numbers. World frame and probe conventions are those of
:mod:`f2l.lighting.grid` (+Y up, the camera looks along -Z, +X is the camera's right).

Geometry
--------
* **Sphere**: centre ``c = (0, 1, 0)``, radius 1, resting on the plane at the origin; Lambertian,
  albedo 0.8 (grey). Ray-traced as ``trimesh.creation.icosphere(subdivisions=4)`` (5120 faces,
  vertices on the unit sphere) translated to ``c``. A primary hit point is projected onto the
  analytic sphere, ``p = c + n`` with the smooth normal ``n = (hit - c) / |hit - c|``.
* **Ground plane**: ``y = 0``, normal +Y, the square ``|x|, |z| <= 1000`` as two triangles;
  Lambertian, albedo 0.3. It is effectively infinite: from any sphere point every texel centre
  below the horizon hits it for grids up to ``H = 512`` rows.
* **Camera**: pinhole, ``96 x 96`` pixels, square, vertical = horizontal field of view 40°.
  Centre of projection ``e = c + 5 (0, sin 15°, cos 15°) = (0, 2.2941, 4.8296)``: 5 units from
  the sphere centre, 15° above it, on the +Z side, looking at ``c`` (so it looks along -Z like
  the face camera; the probe's centre column lies straight ahead). Basis: forward
  ``f = -(0, sin 15°, cos 15°)``, right ``r = (1, 0, 0)``, up ``u = (0, cos 15°, -sin 15°)``.
  Pixel ``(i, j)`` (row ``i`` from the top, column ``j`` from the left) is sampled by one ray
  through its centre, direction ``∝ f + a r + b u`` with
  ``a = (2 (j + 0.5) / 96 - 1) tan 20°``, ``b = (1 - 2 (i + 0.5) / 96) tan 20°``.
  Rays that hit neither mesh are background (``mask = False``); with these numbers that is the
  sky above the horizon, the top ~12 rows.

Transport (direct light only, no inter-reflection)
--------------------------------------------------
For every scene pixel ``p`` (surface point ``x_p``, normal ``n_p``, albedo ``ρ_p``) and texel ``ω``
of the probe's :class:`~f2l.lighting.grid.LatLongGrid` (texel-centre direction, solid angle
``dΩ``)::

    T[p, ω] = (ρ_p / π) V(x_p, ω) max(0, <n_p, ω>) dΩ_ω,      I_p = Σ_ω T[p, ω] l(ω)  (per channel)

i.e. outgoing radiance = ``ρ / π`` × irradiance. ``V`` is binary: 1 if the ray
``x_p + ε n_p + t ω`` (t > 0, ``ε = 1e-4``) hits no triangle (Embree ``OCCLUDED`` query, one ray
per pixel and front-facing texel centre). This gives the sphere's cast shadow on the plane and
the plane's blocking of the lower hemisphere for sphere points (the attached shadow is the
``max(0, ·)``; the convex sphere never occludes itself). Rays that provably miss every triangle
are not traced (V = 1): from sphere points, texels with ``ω_y >= 0`` (the plane lies below, the
inscribed sphere mesh behind); from plane points, texels outside the cone around ``c - x_p`` of
half-angle ``asin(1 / |c - x_p|)`` plus 0.01 rad (the mesh lies inside the unit sphere).

The dense ``float32`` matrix ``T`` (scene pixels × texels, ~8,000 × 8,192 ≈ 260 MB on the default
grid) is built once per grid size and cached in-process (:func:`evaluation_scene`).

References
----------
- Calian, Lalonde, Gotardo, Simon, Matthews, Mitchell. "From Faces to Outdoor Light Probes."
  Computer Graphics Forum (Eurographics) 37(2), 2018 (§5.1: the scene of the rendering metrics "(s)").
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from f2l.lighting.grid import LatLongGrid

__all__ = [
    "IMAGE_SIZE",
    "FOV_DEG",
    "CAMERA_ELEVATION_DEG",
    "CAMERA_DISTANCE",
    "SPHERE_CENTRE",
    "SPHERE_RADIUS",
    "SPHERE_ALBEDO",
    "PLANE_ALBEDO",
    "PLANE_HALF_EXTENT",
    "RAY_OFFSET",
    "EvaluationScene",
    "evaluation_scene",
    "render_scene",
]

IMAGE_SIZE = 96
FOV_DEG = 40.0
CAMERA_ELEVATION_DEG = 15.0
CAMERA_DISTANCE = 5.0
SPHERE_CENTRE = (0.0, 1.0, 0.0)
SPHERE_RADIUS = 1.0
SPHERE_SUBDIVISIONS = 4
SPHERE_ALBEDO = 0.8
PLANE_ALBEDO = 0.3
PLANE_HALF_EXTENT = 1000.0
RAY_OFFSET = 1e-4
_CONE_MARGIN_RAD = 0.01
_MAX_RAYS_PER_CALL = 1 << 20

_SPHERE_ID = 0
_PLANE_ID = 1


@dataclass(frozen=True)
class EvaluationScene:
    """The evaluation scene on one probe grid.

    ``mask`` (h, w) marks scene pixels; the ``P = mask.sum()`` scene pixels are in row-major order
    of the image. ``points``/``normals`` (P, 3) float64, ``albedo`` and ``is_sphere`` (P,), and
    ``transport`` (P, L) float32 with ``I = transport @ probe.reshape(L, 3)``.

    >>> scene = evaluation_scene(LatLongGrid(8, 16))  # a small grid: quick to build
    >>> scene.image_shape, scene.transport.shape, scene.points.shape
    ((96, 96), (7968, 128), (7968, 3))
    >>> float(np.abs(scene.render_pixels(np.zeros((8, 16, 3)))).max())  # no light, no image
    0.0
    """

    grid: LatLongGrid
    mask: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    is_sphere: np.ndarray
    transport: np.ndarray

    @property
    def image_shape(self) -> tuple[int, int]:
        return self.mask.shape

    def render_pixels(self, probe: np.ndarray) -> np.ndarray:
        """Radiance of the scene pixels, (P, 3) float32 (or (..., P, 3) for (..., H, W, 3))."""
        probe = np.asarray(probe, dtype=np.float32)
        H, W = self.grid.shape
        if probe.shape[-3:] != (H, W, 3):
            raise ValueError(f"probe shape {probe.shape} does not match grid {H}x{W}x3")
        lead = probe.shape[:-3]
        flat = probe.reshape(-1, H * W, 3)
        out = np.stack([self.transport @ f for f in flat])
        return out.reshape(*lead, -1, 3)

    def render(self, probe: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image (..., h, w, 3) float32 (background = 0) and mask (h, w) bool."""
        pix = self.render_pixels(probe)
        img = np.zeros(pix.shape[:-2] + self.mask.shape + (3,), dtype=np.float32)
        img[..., self.mask, :] = pix
        return img, self.mask.copy()


def camera_rays() -> tuple[np.ndarray, np.ndarray]:
    """Camera centre (3,) and unit ray directions (IMAGE_SIZE, IMAGE_SIZE, 3), float64.

    >>> eye, rays = camera_rays()
    >>> np.round(eye, 4).tolist(), rays.shape  # 5 units from the sphere's centre, 15° above it
    ([0.0, 2.2941, 4.8296], (96, 96, 3))
    >>> bool(np.allclose(np.linalg.norm(rays, axis=-1), 1.0)), bool((rays[..., 2] < 0).all())  # along -Z
    (True, True)
    """
    c = np.asarray(SPHERE_CENTRE, dtype=np.float64)
    el = math.radians(CAMERA_ELEVATION_DEG)
    back = np.array([0.0, math.sin(el), math.cos(el)])
    eye = c + CAMERA_DISTANCE * back
    fwd = -back
    right = np.array([1.0, 0.0, 0.0])
    up = np.cross(right, fwd)  # (0, cos el, -sin el)
    t = math.tan(math.radians(FOV_DEG) / 2.0)
    n = IMAGE_SIZE
    s = (np.arange(n, dtype=np.float64) + 0.5) / n
    a = (2.0 * s - 1.0) * t  # columns, left -> right
    b = (1.0 - 2.0 * s) * t  # rows, top -> bottom
    d = fwd[None, None, :] + a[None, :, None] * right + b[:, None, None] * up
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return eye, d


def _build_embree():
    import trimesh
    from embreex.mesh_construction import TriangleMesh
    from embreex.rtcore_scene import EmbreeScene

    scene = EmbreeScene()
    sph = trimesh.creation.icosphere(subdivisions=SPHERE_SUBDIVISIONS, radius=SPHERE_RADIUS)
    verts = (np.asarray(sph.vertices) + np.asarray(SPHERE_CENTRE)).astype(np.float32)
    TriangleMesh(scene, verts, np.asarray(sph.faces, dtype=np.int32))  # geomID 0
    e = PLANE_HALF_EXTENT
    pv = np.array([[-e, 0, -e], [e, 0, -e], [e, 0, e], [-e, 0, e]], dtype=np.float32)
    TriangleMesh(scene, pv, np.array([[0, 2, 1], [0, 3, 2]], dtype=np.int32))  # geomID 1
    return scene


def _trace_occluded(scene, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Boolean 'occluded' for each ray (float32 inputs), chunked and threaded."""
    n = origins.shape[0]
    out = np.zeros(n, dtype=bool)
    if n == 0:
        return out
    chunks = [(i, min(i + _MAX_RAYS_PER_CALL, n)) for i in range(0, n, _MAX_RAYS_PER_CALL)]

    def work(se):
        s, e = se
        r = scene.run(origins[s:e], dirs[s:e], query="OCCLUDED")
        out[s:e] = r != -1

    workers = max(1, min(len(chunks), os.cpu_count() or 1))
    if workers == 1:
        for se in chunks:
            work(se)
    else:
        with ThreadPoolExecutor(workers) as ex:
            list(ex.map(work, chunks))
    return out


def _build(grid: LatLongGrid) -> EvaluationScene:
    scene = _build_embree()
    eye, d = camera_rays()
    n = IMAGE_SIZE
    dflat = d.reshape(-1, 3)
    hit = scene.run(
        np.repeat(eye[None].astype(np.float32), n * n, axis=0),
        dflat.astype(np.float32),
        output=1,
    )
    geom = hit["geomID"]
    mask_flat = geom >= 0
    mask = mask_flat.reshape(n, n)
    t = hit["tfar"].astype(np.float64)[mask_flat]
    g = geom[mask_flat]
    x = eye[None] + t[:, None] * dflat[mask_flat]
    c = np.asarray(SPHERE_CENTRE, dtype=np.float64)
    is_sphere = g == _SPHERE_ID
    normals = np.zeros_like(x)
    nv = x[is_sphere] - c
    normals[is_sphere] = nv / np.linalg.norm(nv, axis=1, keepdims=True)
    normals[~is_sphere] = (0.0, 1.0, 0.0)
    x[is_sphere] = c + SPHERE_RADIUS * normals[is_sphere]
    x[~is_sphere, 1] = 0.0
    albedo = np.where(is_sphere, SPHERE_ALBEDO, PLANE_ALBEDO)

    omega = np.asarray(grid.directions_flat)  # (L, 3)
    lower = np.nonzero(omega[:, 1] < 0.0)[0]
    upper = np.nonzero(omega[:, 1] > 0.0)[0]
    origins = x + RAY_OFFSET * normals
    # unshadowed transport (ρ/π) max(0, <n, ω>) dΩ, float32
    T = normals.astype(np.float32) @ omega.T.astype(np.float32)
    np.maximum(T, 0.0, out=T)
    T *= grid.solid_angles_flat.astype(np.float32)[None, :]
    T *= (albedo / np.pi).astype(np.float32)[:, None]
    # candidate rays (those that can hit a triangle); all others have V = 1
    rays_p, rays_l = [], []
    sph_idx = np.nonzero(is_sphere)[0]
    if sph_idx.size:  # sphere points: only downward directions can reach the plane
        bi, li = np.nonzero(T[np.ix_(sph_idx, lower)] > 0.0)
        rays_p.append(sph_idx[bi])
        rays_l.append(lower[li])
    pl_idx = np.nonzero(~is_sphere)[0]
    if pl_idx.size:  # plane points: only directions in the cone around the sphere
        to_c = c[None] - origins[pl_idx]
        dist = np.linalg.norm(to_c, axis=1)
        half = np.arcsin(np.clip(SPHERE_RADIUS / dist, 0.0, 1.0)) + _CONE_MARGIN_RAD
        cosang = (to_c / dist[:, None]).astype(np.float32) @ omega[upper].T.astype(np.float32)
        bi, li = np.nonzero(cosang >= np.cos(np.minimum(half, np.pi)).astype(np.float32)[:, None])
        rays_p.append(pl_idx[bi])
        rays_l.append(upper[li])
    rp = np.concatenate(rays_p) if rays_p else np.zeros(0, np.int64)
    rl = np.concatenate(rays_l) if rays_l else np.zeros(0, np.int64)
    occ = _trace_occluded(scene, origins[rp].astype(np.float32), omega[rl].astype(np.float32))
    T[rp[occ], rl[occ]] = 0.0

    for arr in (mask, x, normals, albedo, is_sphere, T):
        arr.setflags(write=False)
    return EvaluationScene(grid, mask, x, normals, albedo, is_sphere, T)


@lru_cache(maxsize=2)
def _cached(height: int, width: int) -> EvaluationScene:
    return _build(LatLongGrid(height, width))


def evaluation_scene(grid: LatLongGrid) -> EvaluationScene:
    """The evaluation scene with its transport on ``grid`` (built once, cached in-process).

    >>> grid = LatLongGrid(8, 16)
    >>> evaluation_scene(grid) is evaluation_scene(grid)
    True
    """
    return _cached(grid.height, grid.width)


def render_scene(
    probe: np.ndarray, grid: LatLongGrid | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Render the evaluation scene under ``probe`` (H, W, 3) (or (..., H, W, 3)).

    Returns ``(image, mask)``: image (96, 96, 3) float32 linear radiance ``I_p = Σ_ω T[p, ω] l(ω)``
    with background pixels set to 0, and mask (96, 96) bool (True = scene surface).
    ``grid`` defaults to ``LatLongGrid(H, W)`` from the probe's shape.

    >>> image, mask = render_scene(np.ones((8, 16, 3)))  # uniform light on a small grid
    >>> image.shape, image.dtype, mask.shape
    ((96, 96, 3), dtype('float32'), (96, 96))
    >>> bool(mask[:12].any()), float(image[~mask].max())  # the top rows are background (0)
    (False, 0.0)
    >>> image2, _ = render_scene(2.0 * np.ones((8, 16, 3)))
    >>> bool(np.allclose(image2, 2.0 * image))  # rendering is linear in the probe
    True
    """
    probe = np.asarray(probe)
    if grid is None:
        grid = LatLongGrid(probe.shape[-3], probe.shape[-2])
    return evaluation_scene(grid).render(probe)
