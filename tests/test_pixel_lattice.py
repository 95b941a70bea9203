"""Visibility reuse across the photo's pixel lattice (f2l.transport.pixel_lattice)."""

from __future__ import annotations

import numpy as np
import pytest

from f2l.dev.bench import visibility_error
from f2l.lighting.grid import LatLongGrid
from f2l.transport import compute_visibility, unpack_bits, visibility_stats
from f2l.transport.pixel_lattice import plan_lattice

GRID = LatLongGrid(64, 128)


def full_lattice(rows: int, cols: int) -> np.ndarray:
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    return np.column_stack([r.ravel(), c.ravel()])


@pytest.mark.parametrize("levels", [1, 2])
def test_plan_covers_every_pixel_once_with_sources_at_lattice_distance(levels):
    rc = full_lattice(9, 11)
    plan = plan_lattice(rc, levels)
    stride = 1 << levels
    seen = np.zeros(len(rc), int)
    seen[plan.anchors] += 1
    assert np.all(rc[plan.anchors] % stride == 0) or levels > 0  # border pixels may be anchors
    known = np.zeros(len(rc), bool)
    known[plan.anchors] = True
    for k, (pixels, sources) in enumerate(plan.steps):
        h = stride >> (k + 1)
        seen[pixels] += 1
        assert known[sources].all(), "a source must be computed before it is used"
        d = np.abs(rc[sources] - rc[pixels][:, None, :])  # (m, 4, 2)
        assert np.all(d.max(axis=2) == h) and np.all(d.min(axis=2) <= h)
        assert np.all(rc[pixels] % h == 0)
        known[pixels] = True
    assert np.all(seen == 1)
    # interior lattice: exactly the multiples of the stride are anchors
    interior = np.all((rc >= 0) & (rc <= [8, 8]), axis=1)
    assert set(np.nonzero(interior & np.all(rc % stride == 0, axis=1))[0]) <= set(plan.anchors)
    assert plan.num_interpolated == len(rc) - len(plan.anchors)


def test_plan_promotes_border_pixels_and_handles_holes():
    rc = full_lattice(4, 4)  # row 3 and column 3 lack a source beyond the border
    plan = plan_lattice(rc, 1)
    anchors = {tuple(x) for x in rc[plan.anchors]}
    assert {(0, 0), (0, 2), (2, 0), (2, 2)} <= anchors
    assert (3, 1) in anchors and (1, 3) in anchors and (3, 3) in anchors
    assert (1, 1) not in anchors and (0, 1) not in anchors
    holed = rc[~np.all(rc == [2, 2], axis=1)]  # (2, 2) missing: its dependants become anchors
    anchors = {tuple(x) for x in holed[plan_lattice(holed, 1).anchors]}
    assert {(1, 1), (2, 1), (1, 2)} <= anchors


def test_plan_rejects_bad_lattices():
    with pytest.raises(ValueError, match="repeated"):
        plan_lattice(np.array([[0, 0], [0, 0]]))
    with pytest.raises(ValueError, match="non-negative"):
        plan_lattice(np.array([[0, -1]]))
    with pytest.raises(ValueError, match="integer"):
        plan_lattice(np.zeros((3, 2)))
    assert len(plan_lattice(full_lattice(3, 3), 0).anchors) == 9
    with pytest.raises(ValueError, match="pixel_rc"):
        compute_visibility(np.eye(3), np.array([[0, 1, 2]]), np.zeros((2, 3)),
                           np.tile([0.0, 0.0, 1.0], (2, 1)), GRID, pixel_rc=np.zeros((3, 2), int))


def test_reuse_is_exact_under_a_large_flat_occluder():
    """Points on y = 0 under the square |x|, |z| < 1 at y = 1: every shadow is a convex region far
    wider than the lattice step, so agreeing sources are always right."""
    v = np.array([[-1.0, 1.0, -1.0], [1.0, 1.0, -1.0], [1.0, 1.0, 1.0], [-1.0, 1.0, 1.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    rc = full_lattice(15, 15)
    xz = (rc - 7) * 0.09 + 0.0031
    points = np.column_stack([xz[:, 1], np.zeros(len(rc)), xz[:, 0]])
    normals = np.tile([0.0, 1.0, 0.0], (len(rc), 1))
    exact = compute_visibility(v, f, points, normals, GRID, method="exact", offset=0.0)
    plain, s_plain = visibility_stats(v, f, points, normals, GRID, offset=0.0)
    lattice, s_lat = visibility_stats(v, f, points, normals, GRID, offset=0.0, pixel_rc=rc,
                                      max_lattice_step=1.0)  # shadows >> the step here
    assert s_lat["cells"]["reused_pixels"] > 0.6 * len(rc)
    assert s_lat["total_rays"] < 0.6 * s_plain["total_rays"]
    plan = plan_lattice(rc)
    mids = np.concatenate([p for p, _ in plan.steps])
    # reused pixels are as exact as their sources: where the plain adaptive pass is exact,
    # so is the lattice
    be = unpack_bits(exact, GRID.size)
    bl = unpack_bits(lattice, GRID.size)
    bp = unpack_bits(plain, GRID.size)
    assert 0.2 < 1.0 - be[:, GRID.directions_flat[:, 1] > 0].mean() < 0.6  # a real shadow
    assert (bl == be).mean() >= (bp == be).mean() - 1e-4
    assert (bl[mids] == be[mids]).mean() >= 0.995


def test_reuse_on_a_face_is_near_exact():
    from f2l.synth.render import make_synthetic_set

    face = next(make_synthetic_set(1, GRID, seed=3, image_size=96))  # ~4.9k face pixels
    args = (face.vertices, face.faces, face.points, face.normals, GRID)
    exact = compute_visibility(*args, method="exact")
    plain, s_plain = visibility_stats(*args)
    lattice, s_lat = visibility_stats(*args, pixel_rc=face.pixel_rc)
    assert s_lat["lattice"]["levels"] == 1 and s_lat["lattice"]["step_rel"] < 0.012
    err_plain = visibility_error(plain, exact, face.normals, GRID)
    err_lat = visibility_error(lattice, exact, face.normals, GRID)
    assert s_lat["total_rays"] < 0.65 * s_plain["total_rays"]
    assert err_lat["bits_differ"] < 5e-4
    assert err_lat["sunny_rel_error"] < 2e-3
    assert err_lat["pixels_over_1pct"] < 0.005
    assert err_plain["sunny_rel_error"] < 1e-4


def test_reuse_is_refused_on_a_coarse_lattice():
    from f2l.synth.render import make_synthetic_set

    face = next(make_synthetic_set(1, GRID, seed=3, image_size=48))
    args = (face.vertices, face.faces, face.points, face.normals, GRID)
    plain, _ = visibility_stats(*args)
    lattice, stats = visibility_stats(*args, pixel_rc=face.pixel_rc)
    assert stats["lattice"]["levels"] == 0 and stats["lattice"]["step_rel"] > 0.012
    assert stats["rays"]["reuse"] == 0
    assert np.array_equal(lattice, plain)
