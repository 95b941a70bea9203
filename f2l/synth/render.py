"""Synthetic face photos rendered under known light probes (the project's test/demo data).

Geometry: MediaPipe's canonical face mesh (cm), Loop-subdivided twice (~7k vertices), rotated
about its bounding-box centre by the head pose R = R_y(yaw) R_x(pitch) R_z(roll) (degrees,
right-handed about the world axes, +Y up, +Z toward the camera) and placed with that centre at
(0, 0, -FACE_DISTANCE_CM). Camera: a pinhole at the origin looking along -Z with a vertical
field of view of FOV_DEG, square images; pixel (row, col) has the ray

    d ~ ((2 (col + 0.5) / S - 1) tan(fov/2), -(2 (row + 0.5) / S - 1) tan(fov/2), -1),

so the world frame is the camera frame and probes need no rotation.

Shading (paper §3): s = albedo ⊙ (T l), T[p, w] = (1/pi) V(p, w) max(0, <n_p, w>) dw, with V the
binary mesh visibility of :func:`f2l.transport.visibility.compute_visibility` and l the probe
flattened row-major (L, 3). Optional gloss (``gloss``): the GGX microfacet highlight of the whole
probe with the same visibility, uncoloured by the skin (:func:`f2l.synth.gloss.glossy_highlight`),
added to every face pixel. Optional legacy specular: normalised Blinn-Phong toward the sun,
k_s (m + 8) / (8 pi) <n, h>^m <n, w_sun> E_sun V_sun (one shadow ray), added untinted.

Photo: linear image × exposure_scale (the 98th percentile of the face's linear values maps to
0.85) + Gaussian noise (added before quantisation), sRGB-encoded, clipped and rounded to 8 bits.
Background pixels show a blurred probe along their ray. The record's observed linear RGB is the
inverse sRGB of the 8-bit values (quantised and clipped like a real photo); gt_probe = probe ×
exposure_scale is in the same units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterator

import numpy as np

from f2l.lighting.grid import LatLongGrid
from f2l.face.mesh import face_mesh
from f2l.synth.gloss import SkinGloss

FOV_DEG = 19.0  # face (~16 x 18 cm at 60 cm) fills ~half the frame: N ~ 8-9k px at 128^2
FACE_DISTANCE_CM = 60.0
POSE_RANGE_DEG = 20.0
EXPOSURE_PERCENTILE = 98.0
EXPOSURE_TARGET = 0.85
MIN_FACING = 0.1  # keep pixels with <n, -d> > MIN_FACING
SPECULAR_SHININESS = 40.0
BACKGROUND_BLUR_TEXELS = 1.5


@dataclass
class SyntheticFace:
    """One synthetic face photo and its ground truth.

    photo_srgb (S, S, 3) uint8; pixel_rc (N, 2) int32 (row, col) of the face pixels; points
    (N, 3) float32 cm and normals (N, 3) float32 unit, world = camera frame; observed_rgb (N, 3)
    float32 linear (inverse sRGB of the 8-bit photo); mask (N,) bool (not clipped, not
    near-black); visibility_bits (N, ceil(L/8)) uint8 packed little-endian over row-major texels;
    gt_probe (H, W, 3) float32 in the units of observed_rgb; albedo (3,) linear; clean_rgb (N, 3)
    float32 the exposure-scaled noise-free linear shading before quantisation; vertices (V, 3)
    float64 cm and faces (F, 3) int64 of the posed mesh used for rasterisation and visibility.
    """

    photo_srgb: np.ndarray
    pixel_rc: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    observed_rgb: np.ndarray
    mask: np.ndarray
    visibility_bits: np.ndarray
    visibility_method: str
    gt_probe: np.ndarray
    albedo: np.ndarray
    meta: dict
    vertices: np.ndarray
    faces: np.ndarray
    clean_rgb: np.ndarray
    grid: LatLongGrid = field(default_factory=LatLongGrid)

    @property
    def num_pixels(self) -> int:
        return int(len(self.pixel_rc))


# ---------------------------------------------------------------------------------------------
# Geometry helpers
# ---------------------------------------------------------------------------------------------
def pose_matrix(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """R = R_y(yaw) R_x(pitch) R_z(roll), right-handed rotations about the world axes."""
    y, p, r = (math.radians(float(a)) for a in (yaw_deg, pitch_deg, roll_deg))
    cy, sy, cp, sp, cr, sr = math.cos(y), math.sin(y), math.cos(p), math.sin(p), math.cos(r), math.sin(r)
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    return ry @ rx @ rz


def camera_rays(image_size: int, fov_deg: float = FOV_DEG) -> np.ndarray:
    """Unit ray directions (S, S, 3) of a pinhole at the origin looking along -Z."""
    s = int(image_size)
    t = math.tan(math.radians(fov_deg) / 2.0)
    c = (np.arange(s) + 0.5) / s * 2.0 - 1.0
    x = np.broadcast_to(c[None, :] * t, (s, s))
    y = np.broadcast_to(-c[:, None] * t, (s, s))
    d = np.stack([x, y, -np.ones((s, s))], axis=-1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def posed_face_mesh(head_pose_deg, subdivisions: int = 2):
    """(vertices (V, 3) float64 cm, faces (F, 3) int64, vertex normals (V, 3)) in the camera frame."""
    mesh = face_mesh(subdivisions)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    n = np.asarray(mesh.vertex_normals, dtype=np.float64)
    centre = 0.5 * (v.min(0) + v.max(0))
    R = pose_matrix(*head_pose_deg)
    v = (v - centre) @ R.T + np.array([0.0, 0.0, -FACE_DISTANCE_CM])
    n = n @ R.T
    return v, np.asarray(mesh.faces, dtype=np.int64), n


def _rasterise(vertices, faces, rays):
    """Primary rays from the origin (embreex INTERSECT). Returns (hit mask (S,S), primID,
    barycentric (u, v) per pixel) with P = (1-u-v) v0 + u v1 + v v2."""
    from embreex.mesh_construction import TriangleMesh
    from embreex.rtcore_scene import EmbreeScene

    scene = EmbreeScene()
    _mesh = TriangleMesh(  # noqa: F841  (keep the geometry alive while the scene is used)
        scene, np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(faces, np.int32)
    )
    d = np.ascontiguousarray(rays.reshape(-1, 3), dtype=np.float32)
    o = np.zeros_like(d)
    res = scene.run(o, d, output=1)
    return res["primID"].astype(np.int64), res["u"].astype(np.float64), res["v"].astype(np.float64)


def _shadow_rays(vertices, faces, origins, direction) -> np.ndarray:
    """Boolean (n,): True where origins + t direction (t > 0) hits the mesh."""
    from embreex.mesh_construction import TriangleMesh
    from embreex.rtcore_scene import EmbreeScene

    scene = EmbreeScene()
    _mesh = TriangleMesh(  # noqa: F841
        scene, np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(faces, np.int32)
    )
    o = np.ascontiguousarray(origins, np.float32)
    d = np.ascontiguousarray(np.broadcast_to(direction, o.shape), np.float32)
    return scene.run(o, d, query="OCCLUDED") != -1


def _transport_matmul(vis_bits, normals, grid: LatLongGrid, l_flat, threads: int = 2):
    """T @ l (N, 3) float64, T[p, w] = (1/pi) V max(0, <n, w>) dw (f2l.transport.Transport)."""
    from f2l.transport import Transport

    T = Transport(vis_bits, normals, grid, threads=threads)
    return np.asarray(T.matmul(np.asarray(l_flat, dtype=np.float64), dtype=np.float64))


def _blurred_probe_lookup(grid: LatLongGrid, probe: np.ndarray, directions: np.ndarray):
    """Probe blurred by a Gaussian (BACKGROUND_BLUR_TEXELS, wrapping in azimuth), sampled
    bilinearly along ``directions`` (..., 3)."""
    from scipy.ndimage import gaussian_filter, map_coordinates

    blurred = np.stack(
        [
            gaussian_filter(
                probe[..., c].astype(np.float64), BACKGROUND_BLUR_TEXELS, mode=("nearest", "wrap")
            )
            for c in range(probe.shape[-1])
        ],
        axis=-1,
    )
    uv = grid.direction_to_uv(directions.reshape(-1, 3))
    col = uv[:, 0] * grid.width - 0.5
    row = uv[:, 1] * grid.height - 0.5
    # pad one column on each side for periodic interpolation
    padded = np.concatenate([blurred[:, -1:], blurred, blurred[:, :1]], axis=1)
    out = np.stack(
        [map_coordinates(padded[..., c], [row, col + 1.0], order=1, mode="nearest") for c in range(3)],
        axis=-1,
    )
    return out.reshape(directions.shape[:-1] + (3,))


def _srgb_encode(x: np.ndarray) -> np.ndarray:
    import colour

    return np.asarray(colour.cctf_encoding(np.clip(x, 0.0, 1.0), function="sRGB"))


def _srgb_decode(x: np.ndarray) -> np.ndarray:
    import colour

    return np.asarray(colour.cctf_decoding(x, function="sRGB"))


def _sun_from_probe(grid: LatLongGrid, probe: np.ndarray, cap_deg: float = 5.0):
    """(direction of the brightest texel, RGB irradiance of the cap of ``cap_deg`` around it)."""
    lum = probe[: grid.sky_rows] @ np.array([0.2126, 0.7152, 0.0722])
    r, c = np.unravel_index(np.argmax(lum), lum.shape)
    d = grid.directions[r, c]
    cap = (grid.directions @ d) > math.cos(math.radians(cap_deg))
    e = np.einsum("hwc,hw->c", probe.astype(np.float64), cap * grid.solid_angles)
    return d, e


def project_landmarks(head_pose_deg, image_size: int, fov_deg: float = FOV_DEG) -> np.ndarray:
    """The 468 canonical landmarks under the head pose, projected to continuous photo pixels
    (x right, y down) of the synthetic camera; (468, 2)."""
    from f2l.face.mesh import canonical_face_mesh

    v = np.asarray(canonical_face_mesh()[0], dtype=np.float64)
    sub = np.asarray(face_mesh(2).vertices, dtype=np.float64)  # posed_face_mesh centres on this
    centre = 0.5 * (sub.min(0) + sub.max(0))
    v = (v - centre) @ pose_matrix(*head_pose_deg).T + np.array([0.0, 0.0, -FACE_DISTANCE_CM])
    f = (image_size / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    return np.stack([image_size / 2.0 + f * v[:, 0] / -v[:, 2],
                     image_size / 2.0 - f * v[:, 1] / -v[:, 2]], axis=1)


# Albedos of the painted features (linear RGB).
SCLERA_ALBEDO = (0.55, 0.52, 0.50)
IRIS_ALBEDO = (0.06, 0.04, 0.03)
BROW_ALBEDO = (0.05, 0.035, 0.025)
NOSTRIL_ALBEDO = (0.02, 0.012, 0.01)
LIP_TINT = (1.05, 0.55, 0.55)  # multiplies the skin albedo


def paint_features(skin_albedo: np.ndarray, landmarks_xy: np.ndarray, pix_xy: np.ndarray):
    """Per-pixel albedo (M, 3): skin, with eyes (sclera and an iris disc of 0.42 × the eye's
    width), brows, lips and nostrils painted from the undilated feature polygons."""
    from matplotlib.path import Path

    from f2l.face import regions

    xy = np.asarray(landmarks_xy, dtype=np.float64)
    out = np.tile(np.asarray(skin_albedo, dtype=np.float64), (len(pix_xy), 1))

    def inside(idx):
        poly = xy[list(idx)]
        return Path(poly).contains_points(pix_xy)

    out[inside(regions.LIPS_OUTER)] *= np.array(LIP_TINT)
    for brow in (regions.RIGHT_BROW, regions.LEFT_BROW):
        out[inside(brow)] = BROW_ALBEDO
    for nostril in (regions.RIGHT_NOSTRIL, regions.LEFT_NOSTRIL):
        poly = regions._by_angle(xy[list(nostril)])
        out[Path(poly).contains_points(pix_xy)] = NOSTRIL_ALBEDO
    for eye in (regions.RIGHT_EYE, regions.LEFT_EYE):
        in_eye = inside(eye)
        out[in_eye] = SCLERA_ALBEDO
        corners = xy[[eye[0], eye[8]]]
        centre = xy[list(eye)].mean(0)
        radius = 0.21 * float(np.linalg.norm(corners[1] - corners[0]))
        out[in_eye & (np.linalg.norm(pix_xy - centre, axis=1) < radius)] = IRIS_ALBEDO
    return out


# ---------------------------------------------------------------------------------------------
# Rendering
# ---------------------------------------------------------------------------------------------
def render_face(
    grid: LatLongGrid,
    probe: np.ndarray,
    rng: np.random.Generator,
    image_size: int = 128,
    albedo=None,
    head_pose_deg=None,
    specular: float = 0.0,
    noise_sigma: float = 0.0,
    visibility_method: str = "adaptive",
    sun_direction=None,
    threads: int = 2,
    sky_info: dict | None = None,
    features: bool = False,
    gloss: SkinGloss | None = None,
) -> SyntheticFace:
    """Render the canonical face under ``probe`` (H, W, 3 linear radiance on ``grid``).

    Random draws from ``rng``, in order: pose (yaw, pitch, roll ~ U[-20, 20] deg) unless
    ``head_pose_deg`` is given, albedo (``f2l.estimate.skin.sample_skin_albedo``) unless given,
    then the noise. ``gloss`` (:class:`f2l.synth.gloss.SkinGloss`, None = Lambertian skin) adds
    the GGX highlight of the whole probe and is recorded in ``meta['gloss']`` (roughness, f0); it
    draws nothing from ``rng``, so a face with and without it differs only by the highlight.
    ``specular`` = k_s of an extra Blinn-Phong sun highlight (0 = none); its sun is
    ``sun_direction`` or the probe's brightest sky texel. ``sky_info`` is copied into
    ``meta['sky']``. ``features`` paints eyes (sclera and iris), brows, lips and nostrils into
    the albedo (:func:`paint_features`), so that a face detector finds the photo; the record's
    mask then keeps only skin (:func:`f2l.face.regions.skin_regions` on the true landmarks) and
    ``meta['landmarks_xy']`` holds the 468 true landmark positions (continuous photo pixels).
    """
    probe = np.asarray(probe, dtype=np.float32)
    if probe.shape != (grid.height, grid.width, 3):
        raise ValueError(f"probe shape {probe.shape} does not match grid {grid.shape}")
    if head_pose_deg is None:
        head_pose_deg = rng.uniform(-POSE_RANGE_DEG, POSE_RANGE_DEG, size=3)
    head_pose_deg = [float(a) for a in head_pose_deg]
    if albedo is None:
        from f2l.estimate.skin import sample_skin_albedo

        albedo = sample_skin_albedo(rng, 1)[0]
    albedo = np.asarray(albedo, dtype=np.float64).reshape(3)

    vertices, faces, vnormals = posed_face_mesh(head_pose_deg)
    rays = camera_rays(image_size)
    prim, bu, bv = _rasterise(vertices, faces, rays)
    d_flat = rays.reshape(-1, 3)
    hit = prim >= 0
    idx = np.nonzero(hit)[0]
    tri = faces[prim[idx]]
    w = np.stack([1.0 - bu[idx] - bv[idx], bu[idx], bv[idx]], axis=1)
    points = np.einsum("nk,nkc->nc", w, vertices[tri])
    normals = np.einsum("nk,nkc->nc", w, vnormals[tri])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    # Grazing hits (<n, -d> <= MIN_FACING) are shaded for the photo but left out of the record.
    facing = np.einsum("nc,nc->n", normals, -d_flat[idx]) > MIN_FACING

    from f2l.transport import compute_visibility

    vis_all = compute_visibility(
        vertices, faces, points, normals, grid, method=visibility_method, threads=threads,
        pixel_rc=np.stack(np.divmod(idx, image_size), axis=1),
    )
    l_flat = probe.reshape(-1, 3).astype(np.float64)
    albedo_px = np.broadcast_to(albedo, (len(idx), 3))
    landmarks_xy = skin = None
    if features:
        landmarks_xy = project_landmarks(head_pose_deg, image_size)
        pix_xy = np.stack([idx % image_size + 0.5, idx // image_size + 0.5], axis=1)
        albedo_px = paint_features(albedo, landmarks_xy, pix_xy)
        from f2l.face.regions import skin_regions

        skin = skin_regions(landmarks_xy, pix_xy)["skin"]
    shading = albedo_px * _transport_matmul(vis_all, normals, grid, l_flat, threads)
    if gloss is not None:
        from f2l.synth.gloss import glossy_highlight

        shading = shading + glossy_highlight(normals, points, vis_all, grid, probe, gloss.roughness, gloss.f0,
                                             dtype=np.float32)

    if specular > 0.0:
        sun_dir, e_sun = _sun_from_probe(grid, probe)
        if sun_direction is not None:
            sun_dir = np.asarray(sun_direction, dtype=np.float64)
            sun_dir = sun_dir / np.linalg.norm(sun_dir)
        n_dot_l = normals @ sun_dir
        h = sun_dir[None, :] - d_flat[idx]
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        n_dot_h = np.maximum(np.einsum("nc,nc->n", normals, h), 0.0)
        offset = 1e-4 * float(np.linalg.norm(vertices.max(0) - vertices.min(0)))
        lit = (n_dot_l > 0) & ~_shadow_rays(vertices, faces, points + offset * normals, sun_dir)
        m = SPECULAR_SHININESS
        spec = specular * (m + 8.0) / (8.0 * math.pi) * n_dot_h**m * np.maximum(n_dot_l, 0.0) * lit
        shading = shading + spec[:, None] * e_sun[None, :]

    # exposure: the 98th percentile of the recorded face pixels' linear values -> 0.85
    p98 = float(np.percentile(shading[facing], EXPOSURE_PERCENTILE)) if facing.any() else 0.0
    exposure_scale = EXPOSURE_TARGET / p98 if p98 > 0 else 1.0

    image = _blurred_probe_lookup(grid, probe, rays).reshape(-1, 3)
    image[idx] = shading
    image *= exposure_scale
    if noise_sigma > 0:
        image = image + rng.normal(0.0, float(noise_sigma), size=image.shape)
    photo = np.round(_srgb_encode(image) * 255.0).astype(np.uint8).reshape(image_size, image_size, 3)

    # the record: camera-facing face pixels only
    if skin is not None:
        skin = skin[facing]
    idx, points, normals, shading = idx[facing], points[facing], normals[facing], shading[facing]
    vis_bits = np.ascontiguousarray(vis_all[facing])
    pixel_rc = np.stack(np.divmod(idx, image_size), axis=1).astype(np.int32)
    face_codes = photo.reshape(-1, 3)[idx]
    observed = _srgb_decode(face_codes.astype(np.float64) / 255.0)
    mask = ~(face_codes == 255).any(axis=1) & ~(face_codes <= 2).all(axis=1)
    if skin is not None:
        mask &= skin

    sky = dict(sky_info) if sky_info is not None else {}
    focal_px = (image_size / 2.0) / math.tan(math.radians(FOV_DEG) / 2.0)
    meta = dict(
        pose_deg=dict(yaw=head_pose_deg[0], pitch=head_pose_deg[1], roll=head_pose_deg[2]),
        albedo=[float(a) for a in albedo],
        exposure_scale=float(exposure_scale),
        sky=sky,
        image_size=int(image_size),
        fov_deg=FOV_DEG,
        focal_px=float(focal_px),
        face_distance_cm=FACE_DISTANCE_CM,
        specular=float(specular),
        noise_sigma=float(noise_sigma),
        num_pixels=int(len(idx)),
        num_grazing=int((~facing).sum()),
        num_masked=int(mask.sum()),
        grid=[grid.height, grid.width],
    )
    if gloss is not None:
        meta["gloss"] = gloss.to_meta()
    if landmarks_xy is not None:
        meta["landmarks_xy"] = np.round(landmarks_xy, 3).tolist()
    return SyntheticFace(
        photo_srgb=photo,
        pixel_rc=pixel_rc,
        points=points.astype(np.float32),
        normals=normals.astype(np.float32),
        observed_rgb=observed.astype(np.float32),
        mask=mask,
        visibility_bits=vis_bits,
        visibility_method=visibility_method,
        gt_probe=(probe.astype(np.float64) * exposure_scale).astype(np.float32),
        albedo=albedo,
        meta=meta,
        vertices=vertices,
        faces=faces,
        clean_rgb=(shading * exposure_scale).astype(np.float32),
        grid=grid,
    )


GLOSS_SPAWN_KEY = 1  # the gloss generator's seed: SeedSequence(face seed's entropy, spawn_key + (1,))


def _drawn_gloss(face_seed: np.random.SeedSequence) -> SkinGloss:
    from f2l.synth.gloss import sample_skin_gloss

    seq = np.random.SeedSequence(face_seed.entropy, spawn_key=tuple(face_seed.spawn_key) + (GLOSS_SPAWN_KEY,))
    return sample_skin_gloss(np.random.default_rng(seq))


def make_synthetic_set(
    n: int,
    grid: LatLongGrid,
    seed: int,
    image_size: int = 128,
    overcast_fraction: float = 0.25,
    specular: float = 0.0,
    noise_sigma: float = 0.0,
    visibility_method: str = "adaptive",
    threads: int = 2,
    albedo=None,
    sun_elevation_range_deg: tuple[float, float] | None = None,
    features: bool = False,
    gloss: bool | SkinGloss = False,
) -> Iterator[SyntheticFace]:
    """Yield ``n`` synthetic faces, each under a :func:`~f2l.synth.skies.random_sky`.

    Face i uses ``np.random.default_rng(SeedSequence(seed).spawn(n)[i])`` (independent of n for
    the first faces), drawing the sky first, then pose, albedo (unless ``albedo`` fixes one for
    every face) and noise; meta gains ``index`` and ``seed``. ``sun_elevation_range_deg``
    (min, max) restricts the clear skies' sun elevation (None: the default [5, 80] deg); it
    rescales one draw, so the random stream, and with the default range the output, is unchanged.
    ``gloss``: False (the library default) renders Lambertian skin, the estimator's own forward
    model; True gives every face (clear or overcast) glossy skin with roughness and F0 drawn by
    :func:`f2l.synth.gloss.sample_skin_gloss` from a generator of its own (GLOSS_SPAWN_KEY under
    the face's seed), so sky, pose, albedo and noise are those of the Lambertian face; a
    :class:`~f2l.synth.gloss.SkinGloss` gives every face that gloss.
    """
    from f2l.synth.skies import SUN_ELEVATION_RANGE_DEG, check_elevation_range, random_sky

    elev_range = check_elevation_range(
        SUN_ELEVATION_RANGE_DEG if sun_elevation_range_deg is None else sun_elevation_range_deg
    )

    children = np.random.SeedSequence(int(seed)).spawn(int(n))
    for i, child in enumerate(children):
        rng = np.random.default_rng(child)
        face_gloss = gloss if isinstance(gloss, SkinGloss) else (_drawn_gloss(child) if gloss else None)
        probe, info = random_sky(
            grid, rng, overcast_fraction=overcast_fraction, sun_elevation_range_deg=elev_range
        )
        sun_dir = info.get("sun_direction")
        face = render_face(
            grid,
            probe,
            rng,
            image_size=image_size,
            albedo=albedo,
            specular=specular if info["kind"] == "clear" else 0.0,
            noise_sigma=noise_sigma,
            visibility_method=visibility_method,
            sun_direction=sun_dir,
            threads=threads,
            sky_info=info,
            features=features,
            gloss=face_gloss,
        )
        face.meta["index"] = i
        face.meta["seed"] = int(seed)
        yield face


__all__ = [
    "SyntheticFace",
    "render_face",
    "make_synthetic_set",
    "pose_matrix",
    "camera_rays",
    "posed_face_mesh",
    "FOV_DEG",
    "FACE_DISTANCE_CM",
]
