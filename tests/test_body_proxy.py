"""The neck-and-shoulders occluder of ``fit-faces --body-proxy`` (f2l.face.body)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from f2l.face.body import CHIN_CM, NECK, TORSO, body_proxy_canonical, elliptic_cylinder, posed_body_proxy
from f2l.face.fit import FaceFit, fit_face
from f2l.io.shards import unpack_visibility
from f2l.synth.render import pose_matrix
from tests.test_fit_faces import OPTIONS, grey_photo, synthetic_landmarks  # noqa: F401  (fixture)


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def test_cylinder_is_closed_and_outward():
    S = 32
    v, f = elliptic_cylinder((1.0, -2.0), (3.0, 2.0), 5.0, -1.0, segments=S)
    polygon_area = 0.5 * S * 3.0 * 2.0 * math.sin(2 * math.pi / S)
    assert _signed_volume(v, f) == pytest.approx(polygon_area * 6.0, rel=1e-12)  # > 0: outward
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all()  # closed: every edge shared by exactly two triangles


def test_proxy_sits_under_the_chin_with_average_adult_dimensions():
    v, f = body_proxy_canonical()
    neck_top = CHIN_CM[1] + NECK["top_above_chin_cm"]
    assert v[:, 1].max() == pytest.approx(neck_top)
    torso = v[v[:, 1] < CHIN_CM[1] - TORSO["top_below_chin_cm"] + 1e-9]
    assert torso[:, 0].max() == pytest.approx(TORSO["radius_cm"][0]) and torso[:, 0].min() == pytest.approx(-20.0)
    assert torso[:, 2].max() < CHIN_CM[2] + 2.0  # the chest front is about under the chin
    assert _signed_volume(v, f) > 0


def test_posed_proxy_follows_the_head_rigidly():
    from f2l.face.mesh import canonical_face_mesh

    canon = np.asarray(canonical_face_mesh()[0], dtype=np.float64)
    R = pose_matrix(15.0, -8.0, 4.0)
    t = np.array([1.0, -2.0, -45.0])
    head = canon @ R.T + t
    posed, _ = posed_body_proxy(head, canon, R)
    v, _ = body_proxy_canonical()
    np.testing.assert_allclose(posed, v @ R.T + t, atol=1e-9)


def test_fit_face_with_the_proxy_hides_the_ground_only(grey_photo):  # noqa: F811
    lm = synthetic_landmarks(0.0, 0.0, 0.0)
    exact = dataclasses.replace(OPTIONS, visibility_method="exact")  # adaptive refines where it sees edges
    plain = fit_face(grey_photo, lm, 0, exact)
    body = fit_face(grey_photo, lm, 0, dataclasses.replace(exact, body_proxy=True))
    assert isinstance(plain, FaceFit) and isinstance(body, FaceFit)
    np.testing.assert_array_equal(plain.pixel_rc, body.pixel_rc)  # the proxy adds no face pixel
    np.testing.assert_array_equal(plain.normals, body.normals)
    grid = OPTIONS.grid
    vp = unpack_visibility(plain.visibility_bits, grid.size).reshape(-1, grid.height, grid.width).astype(bool)
    vb = unpack_visibility(body.visibility_bits, grid.size).reshape(-1, grid.height, grid.width).astype(bool)
    assert not (vb & ~vp).any()  # an occluder only removes directions
    lower = slice(grid.sky_rows + 1, None)  # clearly below the horizon
    chin = plain.points[:, 1] < np.percentile(plain.points[:, 1], 10)  # the lowest tenth of the face
    lost = (vp[chin][:, lower].sum() - vb[chin][:, lower].sum()) / max(vp[chin][:, lower].sum(), 1)
    assert lost > 0.1  # the neck and chest hide a good share of the ground from the chin
    upper = slice(0, grid.sky_rows - 2)
    forehead = plain.points[:, 1] > np.percentile(plain.points[:, 1], 80)
    np.testing.assert_array_equal(vp[forehead][:, upper], vb[forehead][:, upper])  # the sky stays
    assert dataclasses.replace(OPTIONS, body_proxy=True).to_meta()["body_proxy"] is True  # recorded per face
