"""The other heads of a photo as occluders (f2l.estimate.neighbours): the cone a sphere covers from a
point, the head sphere fitted to a face's points, and faces side by side shading each other."""

from __future__ import annotations

import math

import numpy as np

from f2l.estimate.neighbours import head_sphere, occluded_bits, with_neighbours
from f2l.estimate.observation import FaceObservation
from f2l.lighting.grid import LatLongGrid

GRID = LatLongGrid(32, 64)


def _unpack(bits):
    return np.unpackbits(bits, axis=1, bitorder="little", count=GRID.size).astype(bool)


def test_a_sphere_covers_exactly_the_cone_of_its_angular_radius():
    centre, radius = np.array([10.0, 0.0, 0.0]), 4.0  # seen from the origin: a cone of asin(0.4) about +X
    hit = _unpack(occluded_bits(np.zeros((1, 3)), [(centre, radius)], GRID.directions_flat))[0]
    angle = np.degrees(np.arccos(np.clip(GRID.directions_flat @ np.array([1.0, 0.0, 0.0]), -1, 1)))
    edge = math.degrees(math.asin(0.4))
    assert hit[angle < edge - 0.01].all() and not hit[angle > edge + 0.01].any()
    assert hit.sum() > 10
    # a point inside the sphere is not shaded by it (it is not a neighbour's head there)
    assert not _unpack(occluded_bits(centre[None], [(centre, radius)], GRID.directions_flat)).any()


def _face(centre_x: float, n: int = 400, seed: int = 0) -> FaceObservation:
    """A flat disc-shaped face 14 units wide at x = centre_x, z = -250, facing the camera (+Z), every
    texel visible (as if the face were a point on a pole: only the neighbours can occlude)."""
    rng = np.random.default_rng(seed)
    r, a = 7.0 * np.sqrt(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n)
    xy = np.column_stack([r * np.cos(a), r * np.sin(a)])
    points = np.column_stack([xy[:, 0] + centre_x, xy[:, 1], np.full(n, -250.0)]).astype(np.float32)
    normals = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (n, 1))
    bits = np.packbits(np.ones((n, GRID.size), bool), axis=1, bitorder="little")
    return FaceObservation(normals, np.full((n, 3), 0.3, np.float32), np.ones(n, bool), bits, GRID, f"f{centre_x}", points)


def test_the_head_sphere_sits_behind_the_face_and_is_as_wide_as_a_head():
    centre, radius = head_sphere(_face(0.0))
    assert 7.5 < radius < 9.0  # 0.6 x a 14-unit face
    assert abs(centre[0]) < 0.5 and abs(centre[1]) < 0.5 and -260.0 < centre[2] < -254.0  # behind the face (-Z)


def test_faces_side_by_side_shade_each_other_and_a_face_alone_is_unchanged():
    left, right = _face(-20.0, seed=1), _face(20.0, seed=2)
    (l2, r2), shares = with_neighbours([left, right], [0, 0])
    assert all(0.0 < s < 0.2 for s in shares)
    cleared = _unpack(left.visibility_bits) & ~_unpack(l2.visibility_bits)
    assert not (_unpack(l2.visibility_bits) & ~_unpack(left.visibility_bits)).any()  # bits are only cleared
    d = GRID.directions_flat[cleared.any(0)]
    assert (d[:, 0] > 0.5).all()  # the left face loses sky towards its right-hand neighbour only
    (alone,), (share,) = with_neighbours([left], [0])
    assert alone is left and share == 0.0
    (a, b), shares = with_neighbours([left, right], [0, 1])  # different photos: no shadows
    assert a is left and b is right and shares == [0.0, 0.0]
    (a, b), shares = with_neighbours([left, _face(-18.0, seed=3)], [0, 0])  # overlapping heads: not two heads
    assert a is left and shares == [0.0, 0.0]
