"""f2l.face.geometry, f2l.face.regions and fit.sky_visibility: exact geometry on constructed inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from f2l.face import geometry
from f2l.face.fit import sky_visibility
from f2l.face.regions import RIGHT_EYE, skin_regions
from f2l.io.shards import pack_visibility
from f2l.lighting.grid import LatLongGrid
from f2l.synth.render import pose_matrix, project_landmarks

FOCAL, HW, DISTANCE = 700.0, (256, 256), 60.0


@pytest.fixture(scope="module")
def canonical():
    from f2l.face.mesh import canonical_face_mesh

    return np.asarray(canonical_face_mesh()[0], dtype=np.float64)


def pinhole_landmarks(canon, pose_deg, offset=(0.0, 0.0), focal=FOCAL, hw=HW, distance=DISTANCE):
    """(vertices (468, 3) cm, landmarks (468, 3) px): the canonical mesh rotated about its mean by
    ``pose_matrix(*pose_deg)``, its mean at (offset, -distance), projected through the pinhole
    x = w/2 + f X/(-Z), y = h/2 - f Y/(-Z); z = -(Z - mean Z) f / distance (smaller = nearer)."""
    h, w = hw
    v = (canon - canon.mean(0)) @ pose_matrix(*pose_deg).T + np.array([*offset, -distance])
    z = -v[:, 2]
    lm = np.stack([w / 2 + focal * v[:, 0] / z, h / 2 - focal * v[:, 1] / z,
                   -(v[:, 2] - v[:, 2].mean()) * focal / distance], axis=1)
    return v, lm


def rotation_angle_deg(a, b):
    return math.degrees(Rotation.from_matrix(a @ b.T).magnitude())


# --- similarity fit and pose angles ----------------------------------------------------------

@pytest.mark.parametrize("seed", [0, 1, 2])
def test_similarity_fit_recovers_scale_rotation_translation(seed):
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(60, 3)) * [3.0, 2.0, 1.0]
    rot = Rotation.random(random_state=seed).as_matrix()
    scale, t = float(rng.uniform(0.2, 20.0)), rng.normal(size=3) * 50
    s, r, tt = geometry.similarity_fit(src, scale * src @ rot.T + t)
    assert s == pytest.approx(scale, abs=1e-9)
    np.testing.assert_allclose(r, rot, atol=1e-9)
    np.testing.assert_allclose(tt, t, atol=1e-9)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)


def test_similarity_fit_never_returns_a_reflection():
    rng = np.random.default_rng(5)
    src = rng.normal(size=(40, 3))
    mirrored = src * [-1.0, 1.0, 1.0]  # no rotation maps src onto it
    _, r, _ = geometry.similarity_fit(src, mirrored)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-9)


@pytest.mark.parametrize("ypr", [(0, 0, 0), (30, 0, 0), (0, -25, 0), (0, 0, 40),
                                 (-35, 12, -8), (48, -30, 20), (170, 10, -120)])
def test_pose_angles_invert_pose_matrix(ypr):
    assert geometry.pose_angles_deg(pose_matrix(*ypr)) == pytest.approx(ypr, abs=1e-9)


# --- reconstruction ---------------------------------------------------------------------------

@pytest.mark.parametrize("pose,offset", [((0.0, 0.0, 0.0), (0.0, 0.0)),
                                         ((18.0, -12.0, 7.0), (3.0, -2.0)),
                                         ((-35.0, 15.0, -10.0), (-4.0, 5.0))])
def test_rigid_reconstruction_recovers_pose_and_vertices(canonical, pose, offset):
    truth, lm = pinhole_landmarks(canonical, pose, offset)
    head = geometry.reconstruct_vertices(lm, FOCAL, HW, canonical, "rigid")
    assert rotation_angle_deg(head.rotation, pose_matrix(*pose)) < 0.05
    assert (head.yaw_deg, head.pitch_deg, head.roll_deg) == pytest.approx(pose, abs=0.05)
    assert head.vertices.shape == (468, 3)
    assert np.abs(head.vertices - truth).max() < 0.05
    assert head.distance_cm == pytest.approx(DISTANCE, abs=0.5)
    assert head.residual_cm < 0.01  # exact landmarks: the perspective fit reprojects them
    # weak perspective: px per cm at the face ≈ f / distance
    assert head.px_per_cm == pytest.approx(FOCAL / DISTANCE, rel=0.05)


@pytest.mark.parametrize("mode", ["canonical", "landmarks"])
def test_backprojected_modes_reproject_onto_the_landmarks(canonical, mode):
    pose = (20.0, -10.0, 5.0)
    _, lm = pinhole_landmarks(canonical, pose, (2.0, 1.0))
    head = geometry.reconstruct_vertices(lm, FOCAL, HW, canonical, mode)
    v = head.vertices
    assert (v[:, 2] < 0).all()  # in front of the camera
    z = -v[:, 2]
    reproj = np.stack([HW[1] / 2 + FOCAL * v[:, 0] / z, HW[0] / 2 - FOCAL * v[:, 1] / z], axis=1)
    np.testing.assert_allclose(reproj, lm[:, :2], atol=1e-6)
    # the weak-perspective similarity still finds the head pose and distance roughly
    assert rotation_angle_deg(head.rotation, pose_matrix(*pose)) < 3.0
    assert head.distance_cm == pytest.approx(DISTANCE, rel=0.05)


def test_reconstruct_rejects_unknown_depth_source(canonical):
    _, lm = pinhole_landmarks(canonical, (0, 0, 0))
    with pytest.raises(ValueError, match="depth_source"):
        geometry.reconstruct_vertices(lm, FOCAL, HW, canonical, "stereo")


# --- working view, rays, rasterisation --------------------------------------------------------

def test_working_view_round_trip_and_crop(canonical):
    _, lm = pinhole_landmarks(canonical, (15.0, 5.0, 10.0), (3.0, -1.0))
    view = geometry.working_view(lm, resolution=80, margin=0.08)
    assert view.resolution == 80 and view.step == pytest.approx(view.side / 80)
    rc = np.array([[0, 0], [0, 79], [79, 0], [40, 17], [79, 79]])
    xy = view.photo_xy(rc)
    np.testing.assert_allclose(xy[0], [view.x0 + 0.5 * view.step, view.y0 + 0.5 * view.step])
    np.testing.assert_allclose(view.to_working(xy), rc[:, ::-1] + 0.5, atol=1e-9)
    # all 468 landmarks inside the square crop, the long side padded by the margin on both ends
    w = view.to_working(lm)
    assert w.min() > 0 and w.max() < 80
    span = np.ptp(lm[:, :2], axis=0).max()
    assert view.side == pytest.approx(span * 1.16)
    long_axis = int(np.argmax(np.ptp(lm[:, :2], axis=0)))
    assert lm[:, long_axis].min() - (view.x0, view.y0)[long_axis] == pytest.approx(0.08 * span)
    meta = view.to_meta()
    assert meta == {"x0": view.x0, "y0": view.y0, "side": view.side, "resolution": 80}


def test_rays_for():
    h, w, f = 120, 200, 150.0
    xy = np.array([[w / 2, h / 2], [0.0, 0.0], [w, h], [130.0, 20.0]])
    d = geometry.rays_for(xy, f, (h, w))
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(d[0], [0.0, 0.0, -1.0], atol=1e-15)
    # direction ∝ ((x - cx)/f, -(y - cy)/f, -1): +X right, +Y up
    for (x, y), di in zip(xy, d):
        np.testing.assert_allclose(di / -di[2], [(x - w / 2) / f, -(y - h / 2) / f, -1.0], atol=1e-12)
    assert d[1, 0] < 0 and d[1, 1] > 0 and d[2, 0] > 0 and d[2, 1] < 0


SQUARE_V = np.array([[-1.0, -1.0, -10.0], [1.0, -1.0, -10.0], [1.0, 1.0, -10.0], [-1.0, 1.0, -10.0]])
SQUARE_F = np.array([[0, 1, 2], [0, 2, 3]])


def _rays_to(targets):
    d = np.asarray(targets, dtype=np.float64)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_rasterise_square():
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    inside = [[0.0, 0.0, -10.0], [0.3, -0.5, -10.0], [-0.9, 0.8, -10.0], [0.7, 0.2, -10.0]]
    outside = [[2.0, 0.0, -10.0], [0.0, -1.5, -10.0], [1.2, 1.2, -10.0], [0.0, 0.0, 1.0]]
    rays = _rays_to(inside + outside)
    hit, points, nrm = geometry.rasterise(SQUARE_V, SQUARE_F, normals, rays)
    assert hit.tolist() == [0, 1, 2, 3]
    np.testing.assert_allclose(points[:, 2], -10.0, atol=1e-4)
    np.testing.assert_allclose(points, inside, atol=1e-4)
    np.testing.assert_allclose(nrm, np.tile([0.0, 0.0, 1.0], (4, 1)), atol=1e-12)


def test_rasterise_drops_surfaces_facing_away():
    # the same square with normals pointing away from the camera: every hit fails MIN_FACING
    hit, points, nrm = geometry.rasterise(SQUARE_V, SQUARE_F, np.tile([0.0, 0.0, -1.0], (4, 1)),
                                          _rays_to([[0.0, 0.0, -10.0], [0.3, 0.3, -10.0]]))
    assert hit.size == 0 and points.shape == (0, 3) and nrm.shape == (0, 3)


# --- regions ----------------------------------------------------------------------------------

def test_skin_regions_on_a_frontal_face():
    lm = project_landmarks((0.0, 0.0, 0.0), 256)
    up = lm[10] - lm[152]
    up /= np.linalg.norm(up)
    pts = np.array([
        lm[list(RIGHT_EYE)].mean(0),  # eye: features
        lm[50], lm[280],              # cheeks: skin
        lm[10] + 6.0 * up,            # above the forehead top: border
        lm[10] - 0.05 * np.linalg.norm(lm[10] - lm[152]) * up,  # the hairline band: border
        [2.0, 2.0],                   # far outside the face: border
        lm[13],                       # between the lips: features
    ])
    reg = skin_regions(lm, pts)
    assert reg["features"].tolist() == [True, False, False, False, False, False, True]
    assert reg["skin"].tolist() == [False, True, True, False, False, False, False]
    assert reg["border"].tolist() == [False, False, False, True, True, True, False]
    # the three classes partition the points
    assert (reg["features"].astype(int) + reg["border"] + reg["skin"] == 1).all()


# --- sky visibility ---------------------------------------------------------------------------

def test_sky_visibility_fractions():
    grid = LatLongGrid(16, 32)
    n = grid.size
    rows = np.repeat(np.arange(grid.height), grid.width)
    vis = np.stack([np.ones(n, bool), np.zeros(n, bool), rows >= grid.height // 2,
                    rows < grid.height // 2]).astype(bool)
    got = sky_visibility(pack_visibility(vis), grid)
    np.testing.assert_allclose(got, [1.0, 0.0, 0.0, 1.0], atol=1e-12)
    # half the upper hemisphere's azimuths: half its solid angle
    cols = np.tile(np.arange(grid.width), grid.height)
    half = pack_visibility((cols < grid.width // 2)[None])
    assert sky_visibility(half, grid)[0] == pytest.approx(0.5, abs=1e-9)


# -- Loop subdivision as a sparse matrix -------------------------------------------------------
def _trimesh_loop(vertices, faces, iterations):
    from trimesh.remesh import subdivide_loop

    return subdivide_loop(np.asarray(vertices, float), np.asarray(faces), iterations=iterations)


@pytest.mark.parametrize("iterations", [1, 2])
def test_loop_matrix_matches_trimesh_on_the_open_face_mesh(canonical, iterations):
    from f2l.face.subdivision import loop_subdivision
    from f2l.face.mesh import canonical_face_mesh

    tri = np.asarray(canonical_face_mesh()[1])
    rng = np.random.default_rng(iterations)
    v = canonical + rng.normal(0.0, 0.3, canonical.shape)  # any positions: the map is linear
    s, f = loop_subdivision(tri, len(v), iterations)
    ref_v, ref_f = _trimesh_loop(v, tri, iterations)
    assert s.shape == (len(ref_v), len(v)) and np.array_equal(f, ref_f)
    np.testing.assert_allclose(s @ v, ref_v, rtol=0, atol=1e-12)
    # affine invariance: every row sums to one
    np.testing.assert_allclose(np.asarray(s.sum(axis=1)).ravel(), 1.0, atol=1e-12)
    assert loop_subdivision(tri, len(v), iterations)[0] is s  # cached per topology


def test_loop_matrix_matches_trimesh_on_a_closed_mesh():
    import trimesh

    from f2l.face.subdivision import loop_subdivision

    ico = trimesh.creation.icosphere(subdivisions=1)
    s, f = loop_subdivision(ico.faces, len(ico.vertices), 2)
    ref_v, ref_f = _trimesh_loop(ico.vertices, ico.faces, 2)
    assert np.array_equal(f, ref_f)
    np.testing.assert_allclose(s @ ico.vertices, ref_v, rtol=0, atol=1e-12)


def test_loop_matrix_handles_separate_bodies_and_refuses_non_manifold_edges():
    from f2l.face.subdivision import loop_subdivision

    tet = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    tf = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    v = np.concatenate([tet, tet + [5.0, 0.0, 0.0]]) + [0.0, 0.0, -20.0]
    f = np.concatenate([tf, tf + 4])
    s, sf = loop_subdivision(f, len(v), 2)
    ref_v, ref_f = _trimesh_loop(v, f, 2)
    assert np.array_equal(sf, ref_f)
    np.testing.assert_allclose(s @ v, ref_v, atol=1e-12)
    fan = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # three triangles on edge (0, 1)
    with pytest.raises(ValueError, match="non-manifold"):
        loop_subdivision(fan, 5, 1)


def test_rasterise_and_visibility_share_one_scene(canonical):
    from f2l.transport.visibility import scene_for

    v = canonical + [0.0, 0.0, -60.0]
    from f2l.face.mesh import canonical_face_mesh

    tri = np.asarray(canonical_face_mesh()[1])
    a = scene_for(v, tri)
    assert scene_for(v.copy(), tri.astype(np.int32)) is a  # equal mesh: reused
    b = scene_for(v + [0.0, 0.0, 1e-3], tri)  # moved: rebuilt
    assert b is not a
    # the rebuilt scene answers for the moved mesh: a ray through the mesh centre hits it
    centre = (v + [0.0, 0.0, 1e-3]).mean(0)
    hit = b.intersect(np.zeros((1, 3)), (centre / np.linalg.norm(centre))[None])
    assert hit["primID"][0] >= 0
