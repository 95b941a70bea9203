"""A video's head: its shape fitted once, its transport cached in the head's own frame.

f2l's face geometry (``depth_source="rigid"``, :mod:`f2l.face.geometry`) is MediaPipe's
canonical face posed rigidly by the landmarks: every frame's mesh is ``R (C - c̄) + centre`` for
one shape ``C``. Its self-occlusion is therefore a property of the head alone. It is ray-cast once,
per vertex of the Loop-subdivided canonical mesh, for every texel of the lighting grid in the
HEAD's frame (:class:`HeadTransport`). A frame's face pixels then read their visibility from the
table instead of casting rays (:meth:`HeadTransport.visibility`):

* the pixel's surface point ``p`` (camera frame) is taken into the head's frame,
  ``q = Rᵀ (p − centre)``, and reads the row of the nearest vertex of the head-frame mesh;
* the camera grid's texel direction ``w_j`` is taken into the head's frame, ``Rᵀ w_j``, and reads
  the column of the nearest head-grid texel;
* the result is ANDed with the pixel's own front hemisphere ``<n, w_j> > 0`` (the convention of
  :func:`f2l.transport.compute_visibility`).

The table's error is the two nearest-neighbour lookups: a shadow edge moves by at most about half a
texel (1.4° on 64 × 128) and half a vertex spacing (~2 mm at two subdivisions). Measured against
ray casting per frame in ``docs/experiments/video_estimate.md``.
"""

from __future__ import annotations

import functools
import hashlib
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from f2l.lighting.grid import LatLongGrid

__all__ = ["HeadTransport", "cached_head_transport", "head_transport"]

FRONTAL_DISTANCE_CM = 60.0
TABLE_VERSION = 2  # bump when the table's construction changes (the disk cache's key holds it)


@dataclass
class HeadTransport:
    """Per-vertex visibility of the canonical head, in the head's frame.

    ``vertices`` (V, 3) cm, centred canonical mesh subdivided as the fit subdivides, ``normals``
    (V, 3) its unit vertex normals; ``visible`` (V, L) bool over ``grid``'s texels in the head's
    frame; ``build_s`` the ray casting's time."""

    grid: LatLongGrid
    vertices: np.ndarray
    normals: np.ndarray
    visible: np.ndarray
    build_s: float

    def __post_init__(self) -> None:
        from scipy.spatial import cKDTree

        self._tree = cKDTree(self.vertices)
        self._table = None

    def columns(self, rotation: np.ndarray) -> np.ndarray:
        """(L,) head-grid texel read by each camera-grid texel for a head turned by ``rotation``
        (camera = R · head)."""
        dirs = self.grid.directions_flat @ np.asarray(rotation, np.float64)  # rows: Rᵀ w_j
        rows, cols = self.grid.direction_to_texel(dirs)
        return (np.asarray(rows) * self.grid.width + np.asarray(cols)).astype(np.int64)

    def visibility(self, points: np.ndarray, normals: np.ndarray, rotation: np.ndarray,
                   centre: np.ndarray) -> np.ndarray:
        """Packed visibility bits (N, ceil(L/8)) of camera-frame surface ``points`` with ``normals``
        on a head posed by ``rotation`` and ``centre`` (module docstring)."""
        from f2l.transport.visibility import front_mask

        import torch

        rot = np.asarray(rotation, np.float64)
        q = (np.asarray(points, np.float64) - np.asarray(centre, np.float64)) @ rot
        _, vert = self._tree.query(q)
        if self._table is None:  # torch's index_select gathers bytes several times faster than numpy's
            self._table = torch.from_numpy(np.ascontiguousarray(self.visible).view(np.uint8))
        cols = torch.from_numpy(self.columns(rot))
        table = self._table.index_select(0, torch.from_numpy(np.asarray(vert, np.int64))).index_select(1, cols)
        seen = table.numpy().view(bool) & front_mask(np.asarray(normals, np.float64), self.grid)
        return np.packbits(seen, axis=1, bitorder="little")

    def for_fit(self):
        """The ``visibility`` callable of :func:`f2l.face.fit.fit_face` (its ``head`` a HeadFit)."""
        def visibility(points, normals, head):
            centre = head.vertices.mean(0)
            return self.visibility(points, normals, head.rotation, centre)

        return visibility


def head_transport(grid: LatLongGrid = LatLongGrid(), subdivisions: int = 2, method: str = "adaptive",
                   threads: int = 2) -> HeadTransport:
    """Ray-cast the canonical head's per-vertex visibility on ``grid`` (head frame; once a person)."""
    from f2l.face import geometry
    from f2l.face.mesh import canonical_face_mesh
    from f2l.transport.visibility import compute_visibility, unpack_bits

    t0 = time.perf_counter()
    canon, tri, _ = canonical_face_mesh()
    centred = np.asarray(canon, np.float64)[: geometry.NUM_MESH_LANDMARKS]
    centred = centred - centred.mean(0)
    # posed frontal before a camera at the origin, as a fit poses it (the normals' orientation
    # test looks from the camera), then centred again
    front = np.array([0.0, 0.0, -FRONTAL_DISTANCE_CM])
    v, f, vn = geometry.subdivided_mesh(centred + front, tri, subdivisions)
    v = v - front
    bits = compute_visibility(v, f, v, vn, grid, method=method, threads=threads)
    visible = unpack_bits(bits, grid.size).astype(bool)
    return HeadTransport(grid=grid, vertices=np.asarray(v, np.float64), normals=np.asarray(vn, np.float64),
                         visible=visible, build_s=time.perf_counter() - t0)


def cache_dir() -> Path:
    """Where head tables are kept: ``$F2L_CACHE_DIR`` or ``~/.cache/f2l``."""
    root = os.environ.get("F2L_CACHE_DIR")
    return Path(root) if root else Path.home() / ".cache" / "f2l"


def _table_key(grid: LatLongGrid, subdivisions: int, method: str) -> str:
    from f2l.face.mesh import canonical_face_mesh

    canon, tri, _ = canonical_face_mesh()
    h = hashlib.sha256()
    for part in (np.ascontiguousarray(canon, np.float64), np.ascontiguousarray(tri, np.int64)):
        h.update(part.tobytes())
    h.update(f"{grid.height}x{grid.width}:{subdivisions}:{method}:{TABLE_VERSION}".encode())
    return h.hexdigest()[:20]


@functools.lru_cache(maxsize=4)
def cached_head_transport(grid: LatLongGrid = LatLongGrid(), subdivisions: int = 2,
                          method: str = "adaptive") -> HeadTransport:
    """:func:`head_transport`, kept on disk (:func:`cache_dir`, keyed by the mesh, grid, subdivision
    and method) and in the process: a clip pays the ray casting once per machine."""
    from f2l.transport.visibility import unpack_bits

    path = cache_dir() / "heads" / f"head-{_table_key(grid, subdivisions, method)}.npz"
    if path.exists():
        try:
            with np.load(path) as data:
                visible = unpack_bits(data["bits"], grid.size).astype(bool)
                return HeadTransport(grid=grid, vertices=data["vertices"], normals=data["normals"], visible=visible,
                                     build_s=0.0)
        except (OSError, ValueError, KeyError):
            pass  # a damaged cache file is rebuilt
    table = head_transport(grid, subdivisions, method)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp.npz")
        np.savez_compressed(tmp, vertices=table.vertices, normals=table.normals,
                            bits=np.packbits(table.visible, axis=1, bitorder="little"))
        os.replace(tmp, path)
    except OSError:
        pass  # a read-only home still estimates, at the table's cost per process
    return table
