"""Loop subdivision as a cached sparse matrix: fine vertices = S @ coarse vertices.

Loop subdivision is linear in the vertex positions, and every photo's face mesh shares one
topology (MediaPipe's canonical triangles), so the map is built once per topology and each fit
costs one sparse product (~1 ms) instead of a full subdivision (~60 ms with trimesh).

The rules and the vertex/face order are those of :func:`trimesh.remesh.subdivide_loop` (its own
edge helpers are used, so the orders match; :func:`tests.test_face_geometry` checks the result
against trimesh to rounding):

* odd (edge) vertex: interior edge (v0, v1) with opposite vertices v2, v3:
  3/8 (v0 + v1) + 1/8 (v2 + v3); boundary edge: (v0 + v1) / 2;
* even vertex with k neighbours: interior: (1 - k β) v + β Σ neighbours,
  β = (40 - (3 + 2 cos(2π/k))²) / (64 k) (Loop's weight); a vertex on the boundary:
  3/4 v + 1/8 Σ (its neighbours that lie on the boundary);
* each triangle is split into four; new vertices are [even..., odd...].

Non-manifold meshes (an edge shared by more than two faces) are not handled here
(:func:`loop_subdivision` raises ``ValueError``); several separate bodies are.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import scipy.sparse as sp

__all__ = ["loop_subdivision"]


def _one_level(faces: np.ndarray, num_vertices: int):
    """(S (V' x V) CSR, new faces (4F, 3)) for one Loop step over ``faces``."""
    from trimesh import graph, grouping
    from trimesh.geometry import faces_to_edges

    edges, edges_face = faces_to_edges(faces, return_index=True)
    edges.sort(axis=1)
    unique, inverse = grouping.unique_rows(edges)
    edge_inter = np.sort(grouping.group_rows(edges, require_count=2), axis=1)
    edge_bound = grouping.group_rows(edges, require_count=1)
    if len(edge_inter) * 2 + len(edge_bound) != len(edges):
        raise ValueError("non-manifold mesh: an edge is shared by more than two faces")

    bound_mask = np.zeros(len(edges), dtype=bool)
    bound_mask[edge_bound] = True
    bound_mask = bound_mask[unique]
    inter_mask = ~bound_mask
    pair = np.zeros(len(edges), dtype=np.int64)
    pair[edge_inter[:, 0]] = edge_inter[:, 1]
    pair[edge_inter[:, 1]] = edge_inter[:, 0]
    face1 = edges_face[unique]
    face2 = edges_face[pair[unique]]
    ue = edges[unique]  # (E, 2)
    num_edges = len(ue)

    # odd vertices: rows num_vertices + e
    rows, cols, vals = [], [], []
    eb = np.nonzero(bound_mask)[0]
    for j in (0, 1):
        rows.append(eb), cols.append(ue[eb, j]), vals.append(np.full(len(eb), 0.5))
    ei = np.nonzero(inter_mask)[0]
    e = ue[ei]
    f0, f1 = faces[face1[ei]], faces[face2[ei]]
    v2 = f0[~(f0[:, :, None] == e[:, None, :]).any(-1)]
    v3 = f1[~(f1[:, :, None] == e[:, None, :]).any(-1)]
    for c, w in ((e[:, 0], 0.375), (e[:, 1], 0.375), (v2, 0.125), (v3, 0.125)):
        rows.append(ei), cols.append(c), vals.append(np.full(len(ei), w))
    odd = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                        shape=(num_edges, num_vertices))

    # even vertices
    nbr_lists = graph.neighbors(edges=ue, max_index=num_vertices)
    k = np.array([len(n) for n in nbr_lists], dtype=np.float64)
    owner = np.repeat(np.arange(num_vertices), k.astype(np.int64))
    nbr = np.concatenate([np.asarray(n, dtype=np.int64) for n in nbr_lists]) if len(owner) else \
        np.zeros(0, np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        beta = (40.0 - (2.0 * np.cos(2 * np.pi / k) + 3) ** 2) / (64 * k)
    beta = np.nan_to_num(beta)
    on_bound = np.zeros(num_vertices, dtype=bool)
    on_bound[np.unique(ue[~inter_mask])] = True
    keep = ~on_bound[owner] | on_bound[nbr]  # boundary vertices: boundary neighbours only
    w_nbr = np.where(on_bound[owner], 0.125, beta[owner])
    w_self = np.where(on_bound, 0.75, 1.0 - k * beta)
    even = sp.csr_matrix(
        (np.concatenate([w_nbr[keep], w_self]),
         (np.concatenate([owner[keep], np.arange(num_vertices)]),
          np.concatenate([nbr[keep], np.arange(num_vertices)]))),
        shape=(num_vertices, num_vertices))

    odd_idx = inverse.reshape((-1, 3)) + num_vertices
    new_faces = np.column_stack([
        faces[:, 0], odd_idx[:, 0], odd_idx[:, 2],
        odd_idx[:, 0], faces[:, 1], odd_idx[:, 1],
        odd_idx[:, 2], odd_idx[:, 1], faces[:, 2],
        odd_idx[:, 0], odd_idx[:, 1], odd_idx[:, 2],
    ]).reshape((-1, 3))
    return sp.vstack([even, odd]).tocsr(), new_faces


@lru_cache(maxsize=8)
def _cached(faces_bytes: bytes, num_faces: int, num_vertices: int, iterations: int):
    faces = np.frombuffer(faces_bytes, dtype=np.int64).reshape(num_faces, 3)
    s = sp.identity(num_vertices, format="csr")
    for _ in range(iterations):
        step, faces = _one_level(faces, s.shape[0])
        s = (step @ s).tocsr()
    faces.setflags(write=False)
    return s, faces


def loop_subdivision(faces: np.ndarray, num_vertices: int, iterations: int):
    """(S (V_fine x num_vertices) CSR float64, fine faces (F * 4**iterations, 3) int64, read-only)
    for ``iterations`` Loop steps of the triangle list ``faces`` (cached per topology)."""
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"faces must be (F, 3), got {f.shape}")
    return _cached(f.tobytes(), len(f), int(num_vertices), int(iterations))
