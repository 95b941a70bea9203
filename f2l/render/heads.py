"""Heads for the realistic face renderer: Anny bodies cropped to head, neck and shoulders.

``anny`` (PyPI, Apache-2.0 code, CC0 MakeHuman-based assets in its wheel) gives a whole body from
phenotype parameters (gender, age, muscle, weight, height, proportions in [0, 1]); its frame is
+Z up with the face looking along −Y, in metres. :func:`anny_head` draws a random adult, keeps
the top ``crop_cm`` (head, neck, shoulders: they cast shadows on the face and the chin), moves it
into f2l's camera frame (+Y up, the face looking along +Z toward the camera, cm, origin at the
midpoint of the eyes) and paints per-vertex albedo: skin, lips (Anny's UV lip mask), brows and
hair (placed from the eyes), a shirt below the neck, and separate eye and cavity parts.

:func:`canonical_head` is the ablation "MediaPipe's canonical head": f2l's own fitting template,
extruded to a closed head shape so it can stand in for Anny under the same renderer.
"""

from __future__ import annotations

import logging
import sys
import warnings
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

__all__ = ["Head", "anny_head", "canonical_head", "skin_albedo"]

# Linear Rec.709 albedo of light and dark skin (diffuse reflectance, roughly the range of
# measured facial albedo, e.g. the paper's skin-tone prior); a random tone interpolates in log.
SKIN_LIGHT = np.array([0.66, 0.47, 0.38])
SKIN_DARK = np.array([0.14, 0.08, 0.055])
PART_SKIN, PART_LIPS, PART_BROW, PART_HAIR, PART_SHIRT, PART_EYE, PART_CAVITY = range(7)
_log = logging.getLogger(__name__)


@dataclass
class Head:
    """A triangle mesh in f2l's camera frame (cm) with per-vertex albedo and part labels."""

    vertices: np.ndarray  # (V, 3) float64, cm
    faces: np.ndarray  # (F, 3) int64
    albedo: np.ndarray  # (V, 3) linear Rec.709
    part: np.ndarray  # (F,) int: PART_* of each triangle
    normals: np.ndarray  # (V, 3) unit shading normals (smooth, from the unsubdivided mesh)
    info: dict = field(default_factory=dict)

    def posed(self, rotation: np.ndarray, translation_cm) -> "Head":
        """The head rotated by ``rotation`` (3 × 3) about the eyes' midpoint, then translated."""
        r = np.asarray(rotation, dtype=np.float64)
        v = self.vertices @ r.T + np.asarray(translation_cm, dtype=np.float64)
        return Head(v, self.faces, self.albedo, self.part, self.normals @ r.T, dict(self.info))


def skin_albedo(tone: float) -> np.ndarray:
    """Skin albedo for ``tone`` in [0, 1] (0 light, 1 dark), log-interpolated."""
    t = float(np.clip(tone, 0.0, 1.0))
    return np.exp((1.0 - t) * np.log(SKIN_LIGHT) + t * np.log(SKIN_DARK))


def _without_cuda_driver_notice():
    """Warp (anny's kernels) writes "Warp CUDA warning: Could not find or load the NVIDIA CUDA
    driver…" to file descriptor 2 from native code when it starts on a machine without a GPU,
    which is every machine f2l renders on: that line goes to the debug log (``f2l --debug-log``);
    anything else written meanwhile still reaches the terminal."""
    from f2l.io.native_stderr import native_stderr_lines

    def handle(line: str, failed: bool) -> None:
        if "CUDA driver" in line and not failed:
            _log.debug("warp: %s", line.strip())
        else:
            print(line, file=sys.stderr)

    return native_stderr_lines(handle)


@lru_cache(maxsize=1)
def _anny_model():
    with warnings.catch_warnings(), _without_cuda_driver_notice():
        warnings.simplefilter("ignore")
        try:
            import warp

            warp.config.log_level = 40  # ERROR: no start-up banner or kernel-cache lines on stdout
            import anny
            from anny.face_segmentation import get_face_segmentation_mask
        except ImportError as exc:
            from f2l.render import RenderExtraMissing

            raise RenderExtraMissing(exc) from exc
        model = anny.Anny()

    faces = model.faces.numpy().astype(np.int64)
    labels = {}
    for name in ("head", "eye_front.L", "eye_front.R", "eye_back.L", "eye_back.R", "eye_cavity.L",
                 "eye_cavity.R", "mouth_cavity", "tongue", "hand.L", "hand.R"):
        labels[name] = get_face_segmentation_mask(model, [name]).numpy().astype(bool)
    uv = model.texture_coordinates.numpy()[model.face_texture_coordinate_indices.numpy()]  # (F, 3, 2)
    return model, faces, labels, uv


def require_anny() -> None:
    """Raise :class:`f2l.render.RenderExtraMissing` unless anny can be loaded."""
    _anny_model()


@lru_cache(maxsize=1)
def _lip_mask():
    from importlib import resources

    from PIL import Image

    _anny_model()  # anny is importable (or RenderExtraMissing)
    path = resources.files("anny").joinpath("data", "mpfb2", "textures", "mpfb_lips.jpg")
    with resources.as_file(path) as p:
        return np.asarray(Image.open(p).convert("L"), dtype=np.float32) / 255.0


def _sample_mask(mask: np.ndarray, uv: np.ndarray) -> np.ndarray:
    h, w = mask.shape
    col = np.clip((uv[:, 0] * w).astype(int), 0, w - 1)
    row = np.clip(((1.0 - uv[:, 1]) * h).astype(int), 0, h - 1)
    return mask[row, col]


def random_phenotype(rng: np.random.Generator) -> dict[str, float]:
    """Adults of either gender and varied build (Anny's phenotype parameters in [0, 1])."""
    return {"gender": float(rng.uniform(0, 1)), "age": float(rng.uniform(0.5, 0.95)),
            "muscle": float(rng.uniform(0.2, 0.8)), "weight": float(rng.uniform(0.15, 0.85)),
            "height": float(rng.uniform(0.3, 0.7)), "proportions": float(rng.uniform(0.3, 0.7))}


def _subdivide(vertices, faces, attributes: dict, part, times: int):
    import trimesh.remesh

    for _ in range(times):
        index = np.repeat(np.arange(len(faces)), 4)
        vertices, new_faces, attrs = trimesh.remesh.subdivide(vertices, faces, vertex_attributes=attributes,
                                                              return_index=False)
        attributes, faces, part = attrs, new_faces, part[index]
    return vertices, faces, attributes, part


def anny_head(rng: np.random.Generator, *, crop_cm: float = 42.0, subdivisions: int = 1,
              skin_tone: float | None = None) -> Head:
    """A random Anny adult cropped to head, neck and shoulders (module docstring)."""
    import torch

    model, faces, labels, corner_uv = _anny_model()
    phenotype = random_phenotype(rng)
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        out = model(phenotype_kwargs={k: torch.tensor([v]) for k, v in phenotype.items()})
    v_anny = out["vertices"][0].numpy().astype(np.float64)
    verts = np.stack([v_anny[:, 0], v_anny[:, 2], -v_anny[:, 1]], axis=1) * 100.0  # f2l frame, cm

    def centre(*names):
        sel = np.zeros(len(faces), bool)
        for n in names:
            sel |= labels[n]
        return verts[np.unique(faces[sel])].mean(axis=0)

    eyes = centre("eye_front.L", "eye_front.R")
    eye_l, eye_r = centre("eye_front.L"), centre("eye_front.R")
    top = verts[:, 1].max()
    keep = (verts[faces][:, :, 1] > top - crop_cm).all(axis=1) & ~labels["hand.L"] & ~labels["hand.R"]
    part = np.full(len(faces), PART_SKIN)
    for name in ("eye_front.L", "eye_front.R", "eye_back.L", "eye_back.R"):
        part[labels[name]] = PART_EYE
    for name in ("eye_cavity.L", "eye_cavity.R", "mouth_cavity", "tongue"):
        part[labels[name]] = PART_CAVITY
    head_faces = labels["head"]
    head_bottom = verts[np.unique(faces[head_faces])][:, 1].min()

    # per-vertex UV from any corner (the face region has no seams that matter for the masks)
    vertex_uv = np.zeros((len(verts), 2))
    vertex_uv[faces.reshape(-1)] = corner_uv.reshape(-1, 2)
    faces, part = faces[keep], part[keep]
    used = np.unique(faces)
    remap = np.full(len(verts), -1)
    remap[used] = np.arange(len(used))
    verts, faces, vertex_uv = verts[used] - eyes, remap[faces], vertex_uv[used]
    eye_l, eye_r, head_bottom = eye_l - eyes, eye_r - eyes, head_bottom - eyes[1]
    normals = _smooth_normals(verts, faces)
    verts, faces, attrs, part = _subdivide(verts, faces, {"uv": vertex_uv, "n": normals}, part, subdivisions)

    tone = float(rng.uniform(0, 1)) if skin_tone is None else float(skin_tone)
    skin = skin_albedo(tone) * rng.uniform(0.95, 1.05, 3)
    hair_colour = np.exp(rng.uniform(np.log(0.02), np.log(0.35))) * np.array([1.0, 0.8, 0.6])
    brow_colour = np.minimum(hair_colour, skin * 0.45)
    shirt = rng.uniform(0.04, 0.7, 3)
    eye_white, iris = np.array([0.55, 0.52, 0.5]), rng.uniform(0.02, 0.15) * np.array([1.0, 0.75, 0.5])
    vertex_part = _vertex_parts(faces, part, len(verts))
    albedo = np.tile(skin, (len(verts), 1))
    x, y, z = verts.T
    lips = _sample_mask(_lip_mask(), attrs["uv"]) > 0.5
    lips &= (np.abs(x) < 4.0) & (y < -3.0) & (y > -9.0) & (z > 0)  # guard against UV reuse elsewhere
    albedo[lips] = skin * np.array([0.85, 0.55, 0.55])
    brow_y0, brow_y1 = rng.uniform(1.4, 1.9), rng.uniform(2.4, 2.9)
    for eye in (eye_l, eye_r):
        dx = (x - eye[0]) * np.sign(eye[0])  # toward the temple is positive
        brow = (y > eye[1] + brow_y0 + 0.15 * dx) & (y < eye[1] + brow_y1 + 0.1 * dx) & (dx > -1.8) & (dx < 2.8) \
            & (z > eye[2] - 2.5)
        albedo[brow] = brow_colour
    has_hair = rng.uniform() < 0.8
    hairline = rng.uniform(5.5, 8.0)
    if has_hair:
        hair = (y > hairline) | ((y > -2.0) & (z < -7.0 + 0.3 * np.abs(x)))  # crown, and back and sides of the head
        hair &= y > head_bottom + 6.0
        albedo[hair] = hair_colour
    shirt_mask = y < head_bottom - rng.uniform(2.0, 5.0)
    albedo[shirt_mask] = shirt
    eye_vertices = vertex_part == PART_EYE
    albedo[eye_vertices] = eye_white
    iris_v = eye_vertices & (z > (eye_l[2] + 0.55))
    albedo[iris_v] = iris
    albedo[vertex_part == PART_CAVITY] = 0.03
    face_part = part.copy()
    face_part[(part == PART_SKIN) & shirt_mask[faces].all(axis=1)] = PART_SHIRT
    if has_hair:
        face_part[(part == PART_SKIN) & hair[faces].all(axis=1)] = PART_HAIR
    info = {"source": "anny", "phenotype": {k: round(v, 4) for k, v in phenotype.items()},
            "skin_tone": round(tone, 4), "skin_albedo": [round(float(c), 4) for c in skin],
            "hair": bool(has_hair), "triangles": int(len(faces))}
    normals = attrs["n"] / np.linalg.norm(attrs["n"], axis=1, keepdims=True)
    return Head(verts, faces, np.clip(albedo, 0.0, 1.0), face_part, normals, info)


def _smooth_normals(vertices, faces):
    import trimesh

    return np.asarray(trimesh.Trimesh(vertices, faces, process=False).vertex_normals, dtype=np.float64)


def _vertex_parts(faces, part, n_vertices):
    out = np.full(n_vertices, PART_SKIN)
    for p in (PART_CAVITY, PART_EYE):  # eyes win where they touch a cavity
        out[np.unique(faces[part == p])] = p
    return out


def canonical_head(rng: np.random.Generator, *, skin_tone: float | None = None) -> Head:
    """MediaPipe's canonical face (f2l's fitting template) closed into a head (ablation).

    The 468-vertex face surface is kept as the front; its boundary loop is extruded backwards
    18 cm and capped, so the face can self-shadow and has a silhouette. Albedo is skin only.
    """
    import trimesh

    from f2l.face.mesh import face_mesh

    mesh = face_mesh(subdivisions=1)
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)

    tm = trimesh.Trimesh(verts, faces, process=False)
    boundary = trimesh.grouping.group_rows(tm.edges_sorted, require_count=1)
    edges = tm.edges[boundary]
    back = verts.copy()
    back[:, 2] = verts[:, 2].min() - 18.0
    n = len(verts)
    side = np.concatenate([np.stack([edges[:, 1], edges[:, 0], edges[:, 0] + n], 1),
                           np.stack([edges[:, 1], edges[:, 0] + n, edges[:, 1] + n], 1)])
    all_verts = np.concatenate([verts, back])
    all_faces = np.concatenate([faces, side])
    # the back cap: a fan around the back centroid
    centre_index = len(all_verts)
    all_verts = np.concatenate([all_verts, back[np.unique(edges)].mean(axis=0, keepdims=True)])
    cap = np.stack([edges[:, 0] + n, edges[:, 1] + n, np.full(len(edges), centre_index)], 1)
    all_faces = np.concatenate([all_faces, cap])
    fixed = trimesh.Trimesh(all_verts, all_faces, process=False)
    trimesh.repair.fix_normals(fixed)
    eyes = verts[[33, 133, 362, 263]].mean(axis=0)  # Loop subdivision keeps the first 468 vertices
    tone = float(rng.uniform(0, 1)) if skin_tone is None else float(skin_tone)
    skin = skin_albedo(tone)
    v = np.asarray(fixed.vertices) - eyes
    f = np.asarray(fixed.faces)
    return Head(v, f, np.tile(skin, (len(v), 1)), np.full(len(f), PART_SKIN), _smooth_normals(v, f),
                {"source": "mediapipe-canonical", "skin_tone": round(tone, 4),
                 "skin_albedo": [round(float(c), 4) for c in skin], "triangles": int(len(f))})
