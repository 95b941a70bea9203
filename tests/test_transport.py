"""Visibility ray casting and the compact transport operator T (f2l.transport)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from f2l.dev.bench_transport import sample_pixels, sunny_sky, synthetic_head
from f2l.lighting.grid import LatLongGrid
from f2l.transport import Transport, compute_visibility, unpack_bits, visibility_stats

GRID = LatLongGrid(64, 128)


def analytic_T(normals: np.ndarray, grid: LatLongGrid) -> np.ndarray:
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    return np.maximum(0.0, n @ grid.directions_flat.T) * grid.solid_angles_flat / np.pi


def bits_of(vis: np.ndarray, grid: LatLongGrid) -> np.ndarray:
    return unpack_bits(vis, grid.size).astype(bool)


@pytest.fixture(scope="module")
def sphere():
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    v = np.asarray(mesh.vertices)
    idx = np.random.default_rng(0).choice(len(v), 500, replace=False)
    points = v[idx]
    normals = points / np.linalg.norm(points, axis=1, keepdims=True)
    return v, np.asarray(mesh.faces), points, normals


@pytest.fixture(scope="module")
def head():
    v, f = synthetic_head(subdivisions=3)
    points, normals = sample_pixels(v, f, 400, seed=1)
    exact = compute_visibility(v, f, points, normals, GRID, method="exact")
    return v, f, points, normals, exact


def two_boxes():
    """A ground slab with a tall box standing on it; points on the slab's top face next to it."""
    ground = trimesh.creation.box(extents=[4.0, 0.2, 4.0])
    ground.apply_translation([0.0, -0.1, 0.0])
    tower = trimesh.creation.box(extents=[0.6, 1.5, 0.6])
    tower.apply_translation([0.0, 0.75, 0.0])
    mesh = trimesh.util.concatenate([ground, tower])
    rng = np.random.default_rng(3)
    xz = rng.uniform(-1.2, 1.2, size=(600, 2))
    xz = xz[np.max(np.abs(xz), axis=1) > 0.35][:300]  # outside the tower's footprint
    points = np.column_stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]])
    normals = np.tile([0.0, 1.0, 0.0], (len(points), 1))
    return np.asarray(mesh.vertices), np.asarray(mesh.faces), points, normals


# -- layout -------------------------------------------------------------------------------------
def test_packing_layout_little_endian_row_major():
    grid = LatLongGrid(4, 8)
    normals = np.array([[0.0, 1.0, 0.0], [0.3, -0.2, 0.9]])
    points = np.zeros((2, 3))
    # no occluder: visible == front-facing
    vis = compute_visibility(np.zeros((0, 3)), np.zeros((0, 3), int), points, normals, grid)
    assert vis.dtype == np.uint8 and vis.shape == (2, 4)
    cos = normals / np.linalg.norm(normals, axis=1, keepdims=True) @ grid.directions_flat.T
    for i in range(2):
        for j in range(grid.size):
            row, col = divmod(j, grid.width)
            assert np.allclose(grid.directions_flat[j], grid.directions[row, col])
            assert ((vis[i, j // 8] >> (j % 8)) & 1) == int(cos[i, j] > 0)
    # zenith-facing pixel: exactly the upper two rows (texels 0..15) -> bytes 0xFF 0xFF 0 0
    assert vis[0].tolist() == [255, 255, 0, 0]
    # a single set bit selects a single texel column of T
    bits = np.zeros((1, 4), np.uint8)
    bits[0, 1] = 1 << 3  # texel 11 = row 1, col 3
    T = Transport(bits, normals[:1], grid).dense(np.float64)
    assert np.nonzero(T[0])[0].tolist() == [11]
    assert T[0, 11] == pytest.approx(analytic_T(normals[:1], grid)[0, 11], rel=1e-12)


# -- convex: no occlusion ------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["exact", "adaptive"])
def test_convex_sphere_is_unoccluded(sphere, method):
    v, f, points, normals = sphere
    vis = compute_visibility(v, f, points, normals, GRID, method=method)
    cos = normals @ GRID.directions_flat.T
    clear = np.abs(cos) > 1e-9
    assert np.array_equal(bits_of(vis, GRID)[clear], (cos > 0)[clear])
    t = Transport(vis, normals, GRID)
    ones = t.matmul(np.ones(GRID.size), dtype=np.float64)
    assert np.all(np.abs(ones - 1.0) < 0.01)
    assert np.allclose(t.row_sums(), ones)
    dense = t.dense(np.float64)
    ref = analytic_T(normals, GRID)
    assert np.allclose(dense, ref, rtol=1e-9, atol=1e-12 * ref.max())
    assert np.allclose(t.dense(np.float32), ref, rtol=2e-6, atol=1e-7 * ref.max())
    assert np.allclose(t.visible_fraction(), 1.0)


def test_from_mesh_and_sizes(sphere):
    v, f, points, normals = sphere
    t = Transport.from_mesh(v, f, points[:50], normals[:50], GRID, method="adaptive")
    assert t.num_pixels == 50 and t.grid == GRID and t.shape == (50, GRID.size)
    assert t.vis_bits.shape == (50, GRID.size // 8)
    assert t.nbytes == 50 * GRID.size // 8 + 50 * 3 * 8
    assert np.allclose(t @ np.ones(GRID.size), 1.0, atol=0.01)


# -- known occluder ----------------------------------------------------------------------------
def quad_scene():
    """Points on the plane y = 0 facing +Y under the square |x|, |z| < 1 at height y = 1."""
    v = np.array([[-1.0, 1.0, -1.0], [1.0, 1.0, -1.0], [1.0, 1.0, 1.0], [-1.0, 1.0, 1.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    xs = np.linspace(-0.6, 0.6, 7) + 0.007
    points = np.array([[x, 0.0, z] for x in xs for z in xs])
    normals = np.tile([0.0, 1.0, 0.0], (len(points), 1))
    d = GRID.directions_flat
    up = d[:, 1] > 0
    t_hit = 1.0 / np.where(up, d[:, 1], 1.0)
    hx = points[:, 0:1] + t_hit * d[:, 0]
    hz = points[:, 2:3] + t_hit * d[:, 2]
    margin = np.minimum(1.0 - np.abs(hx), 1.0 - np.abs(hz))  # > 0: the ray hits the quad
    expected = up & (margin < 0)
    return v, f, points, normals, expected, np.abs(margin[:, up]).min()


def test_quad_occluder_exact_is_bit_exact():
    v, f, points, normals, expected, min_margin = quad_scene()
    assert min_margin > 1e-4  # no texel centre grazes the quad's edge (float32 rays)
    vis = compute_visibility(v, f, points, normals, GRID, method="exact", offset=0.0)
    got = bits_of(vis, GRID)
    assert 0.2 < (~got & (GRID.directions_flat[:, 1] > 0)).mean() < 0.6  # a real shadow
    assert np.array_equal(got, expected)


def test_quad_occluder_adaptive():
    v, f, points, normals, expected, _ = quad_scene()
    vis, stats = visibility_stats(v, f, points, normals, GRID, method="adaptive", offset=0.0)
    got = bits_of(vis, GRID)
    front = GRID.directions_flat[:, 1] > 0
    assert (got[:, front] == expected[:, front]).mean() >= 0.995
    assert not got[:, ~front].any()
    assert stats["total_rays"] < 0.5 * stats["exact_rays"]


# -- adaptive vs exact on concave meshes -----------------------------------------------------------
def shading_error(vis_a, vis_e, normals, grid, sky):
    se = Transport(vis_e, normals, grid).matmul(sky, dtype=np.float64)
    sa = Transport(vis_a, normals, grid).matmul(sky, dtype=np.float64)
    return np.linalg.norm(sa - se) / np.linalg.norm(se), se


def test_adaptive_matches_exact_on_head(head):
    v, f, points, normals, exact = head
    adaptive = compute_visibility(v, f, points, normals, GRID, method="adaptive")
    be, ba = bits_of(exact, GRID), bits_of(adaptive, GRID)
    front = normals @ GRID.directions_flat.T > 0
    occluded_front = front & ~be
    assert occluded_front.sum() > 0.01 * front.sum(), "the head must shadow itself for this test"
    assert (be == ba).mean() >= 0.99
    assert (be[front] == ba[front]).mean() >= 0.99
    sky = sunny_sky(GRID, elevation_rad=np.radians(20.0), azimuth_rad=np.radians(70.0))
    sun = int(np.argmax(sky[:, 0]))
    assert (front[:, sun] & ~be[:, sun]).sum() >= 4  # some pixels in the sun's cast shadow
    err, _ = shading_error(adaptive, exact, normals, GRID, sky)
    assert err < 0.02


def test_adaptive_matches_exact_on_two_boxes():
    v, f, points, normals = two_boxes()
    exact = compute_visibility(v, f, points, normals, GRID, method="exact")
    adaptive = compute_visibility(v, f, points, normals, GRID, method="adaptive")
    be, ba = bits_of(exact, GRID), bits_of(adaptive, GRID)
    front = GRID.directions_flat[:, 1] > 0
    assert 0.02 < 1 - be[:, front].mean() < 0.5
    assert (be[:, front] == ba[:, front]).mean() >= 0.99
    sky = sunny_sky(GRID, elevation_rad=np.radians(30.0), azimuth_rad=np.radians(-40.0))
    err, _ = shading_error(adaptive, exact, normals, GRID, sky)
    assert err < 0.02


def test_threads_and_odd_factor_are_consistent(head):
    v, f, points, normals, exact = head
    a1 = compute_visibility(v, f, points[:100], normals[:100], GRID, threads=1, chunk_pixels=32)
    a2 = compute_visibility(v, f, points[:100], normals[:100], GRID, threads=2, chunk_pixels=32)
    assert np.array_equal(a1, a2)
    e2 = compute_visibility(v, f, points[:100], normals[:100], GRID, method="exact", threads=2,
                            chunk_pixels=32)
    assert np.array_equal(e2, exact[:100])
    grid = LatLongGrid(18, 36)  # factor 4 does not divide 18 -> 3 (6 x 12 cells)
    _, stats = visibility_stats(v, f, points[:50], normals[:50], grid, method="adaptive")
    assert stats["coarse_factor"] == 3
    ea = bits_of(compute_visibility(v, f, points[:50], normals[:50], grid, method="exact"), grid)
    aa = bits_of(compute_visibility(v, f, points[:50], normals[:50], grid), grid)
    assert (ea == aa).mean() >= 0.99


def test_bad_inputs_raise():
    with pytest.raises(ValueError):
        compute_visibility(np.zeros((3, 3)), np.array([[0, 1, 5]]), np.zeros((1, 3)),
                           np.ones((1, 3)), GRID)
    with pytest.raises(ValueError):
        compute_visibility(np.zeros((3, 3)), np.array([[0, 1, 2]]), np.zeros((2, 3)),
                           np.ones((1, 3)), GRID)
    with pytest.raises(ValueError):
        compute_visibility(np.zeros((3, 3)), np.array([[0, 1, 2]]), np.zeros((1, 3)),
                           np.ones((1, 3)), GRID, method="fast")
    with pytest.raises(ValueError):
        Transport(np.zeros((2, 5), np.uint8), np.ones((2, 3)), GRID)


# -- operator products -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def random_transport():
    grid = LatLongGrid(16, 32)
    rng = np.random.default_rng(7)
    normals = rng.normal(size=(300, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    front = normals @ grid.directions_flat.T > 0
    # visibility: front-facing, minus a random 'occluder' blob of directions per pixel
    blob = rng.normal(size=(300, 3))
    blob /= np.linalg.norm(blob, axis=1, keepdims=True)
    bits = front & (np.einsum("nk,lk->nl", blob, grid.directions_flat) < 0.6)
    vis = np.packbits(bits, axis=1, bitorder="little")
    return Transport(vis, normals, grid, chunk_pixels=64, threads=2), bits


def test_products_match_dense(random_transport):
    t, bits = random_transport
    grid = t.grid
    rng = np.random.default_rng(0)
    dense = t.dense(np.float64)
    ref = bits * analytic_T(t.normals, grid)
    assert np.allclose(dense, ref, rtol=1e-12, atol=1e-15)
    assert np.allclose(t.dense(rows=slice(10, 20)), ref[10:20], rtol=1e-5, atol=1e-8)
    assert np.allclose(t.dense(rows=[5, 3, 250]), ref[[5, 3, 250]], rtol=1e-5, atol=1e-8)

    def close(a, b):  # float32 sums of L = 512 texels: ~sqrt(L) * 2^-24 = 1.4e-6 in any order (measured <= 3e-7)
        return np.linalg.norm(a - b) <= 1e-5 * np.linalg.norm(b)

    l = rng.gamma(1.0, size=(grid.size, 3))
    assert close(t.matmul(l), ref @ l)
    assert close(t.matmul(l, dtype=np.float64), ref @ l)
    assert t.matmul(l[:, 0]).shape == (300,)
    basis = rng.normal(size=(grid.size, 25))
    assert close(t.project(basis), ref @ basis)
    g = rng.normal(size=(300, 2))
    assert close(t.rmatmul(g), ref.T @ g)
    lower = ~grid.upper_mask
    assert close(t.row_sums(lower), ref[:, lower.reshape(-1)].sum(1))
    assert close(t.row_sums(), ref.sum(1))
    frac = t.visible_fraction()
    full = analytic_T(t.normals, grid).sum(1)
    assert np.allclose(frac, ref.sum(1) / full)
    assert np.allclose(t.visible_fraction(weighted=False),
                       bits.sum(1) / (t.normals @ grid.directions_flat.T > 0).sum(1))


def test_back_facing_bits_are_ignored_or_cleared(random_transport):
    t, bits = random_transport
    noisy = np.packbits(np.ones_like(bits), axis=1, bitorder="little")
    t2 = Transport(noisy, t.normals, t.grid)
    assert np.all(t2.dense() >= 0)  # clamped cosine
    t3 = Transport(noisy, t.normals, t.grid, clear_back_facing=True)
    assert np.all(noisy == 255)  # cleared on a copy
    front = t.normals @ t.grid.directions_flat.T > 0
    assert np.array_equal(bits_of(t3.vis_bits, t.grid), front)
    l = np.random.default_rng(1).random((t.grid.size, 3))
    assert np.allclose(t3.matmul(l, dtype=np.float64), t2.dense(np.float64) @ l)


def test_lowrank_is_near_optimal(random_transport):
    t, _ = random_transport
    dense = t.dense(np.float64)
    s = np.linalg.svd(dense, compute_uv=False)
    k = 20
    optimal = np.sqrt((s[k:] ** 2).sum())
    u, vt = t.lowrank(k, seed=0)
    assert u.shape == (300, k) and vt.shape == (k, t.grid.size) and u.dtype == np.float32
    assert np.linalg.norm(dense - u @ vt) <= 1.1 * optimal
    u2, vt2 = t.lowrank(k, seed=0)
    assert np.array_equal(u, u2)  # seeded
    uc, vtc = t.lowrank(k, seed=0, max_dense_bytes=0)  # chunked randomized SVD
    assert np.linalg.norm(dense - uc @ vtc) <= 1.1 * optimal

