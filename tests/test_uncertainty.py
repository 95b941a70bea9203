"""The sun's uncertainty of compact-sun estimates (f2l.estimate.uncertainty): cone radii, faces
rendered under a known sun, and the estimates table's columns and EXR header."""

import doctest
import math

import numpy as np
import pyarrow.parquet as pq
import pytest

import f2l.estimate.uncertainty as unc
from f2l.estimate import EstimatorConfig, FaceObservation, estimate
from f2l.lighting.grid import LatLongGrid, direction_from_angles
from f2l.testing import check_model, model_probe

GRID = (32, 64)


def test_doctests():
    assert doctest.testmod(unc).failed == 0


def fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    y = 1 - 2 * i / n
    r = np.sqrt(1 - y * y)
    phi = i * math.pi * (3 - math.sqrt(5))
    return np.stack([r * np.cos(phi), y, r * np.sin(phi)], 1)


@pytest.mark.parametrize("kappa", [40.0, 200.0])
def test_a_von_mises_fisher_posterior_gives_its_closed_form_cone_radii(kappa):
    # residuals R = 1 + (1 - d.mu) kappa / tau: the posterior exp(-tau (R - 1)) is a vMF of
    # concentration kappa around mu, whose mass within theta is (1 - e^{-kappa (1 - cos theta)}) / (1 - e^{-2 kappa})
    mu = direction_from_angles(math.radians(30.0), math.radians(70.0))
    dirs = fibonacci_sphere(200_000)
    tau = 50.0
    totals = (1.0 + (1.0 - dirs @ mu) * kappa / tau)[:, None]
    w = unc.direction_posterior(totals, tau)
    r68, r90 = unc.cone_radii_deg(mu, dirs, w, sigma_deg=0.0)
    for q, r in ((0.68, r68), (0.90, r90)):
        expected = math.degrees(math.acos(1 + math.log(1 - q * (1 - math.exp(-2 * kappa))) / kappa))
        assert r == pytest.approx(expected, abs=0.3), q
    # the same posterior seen from 10 deg away needs wider cones to hold the same mass
    off = direction_from_angles(math.radians(40.0), math.radians(70.0))
    assert all(b > a for a, b in zip((r68, r90), unc.cone_radii_deg(off, dirs, w, sigma_deg=0.0)))


def test_one_mass_point_spread_by_the_lattice_gives_rayleigh_quantiles():
    c = np.array([0.0, 1.0, 0.0])
    r68, r90 = unc.cone_radii_deg(c, c[None], np.ones(1), sigma_deg=2.0)
    # |2-D Gaussian| of sigma 2: Rayleigh, quantile sigma sqrt(-2 ln(1 - q)) (32 fixed points: within 5%)
    assert r68 == pytest.approx(2.0 * math.sqrt(-2 * math.log(0.32)), rel=0.05)
    assert r90 == pytest.approx(2.0 * math.sqrt(-2 * math.log(0.10)), rel=0.05)


def test_a_flat_posterior_widens_the_cone_and_temperature_sharpens_it():
    dirs = fibonacci_sphere(4000)
    dirs = dirs[dirs[:, 1] > 0]
    c = direction_from_angles(math.radians(45.0), 0.0)
    totals = (1.0 + 0.05 * (1.0 - dirs @ c))[:, None]
    cones = [unc.cone_radii_deg(c, dirs, unc.direction_posterior(totals, t))[1] for t in (1.0, 100.0, 10_000.0)]
    assert cones[0] > cones[1] > cones[2]
    assert cones[0] > 45.0 and cones[2] < 10.0


def test_predicted_mae_is_the_documented_regression_floored_at_zero():
    f = unc.mae_features(45.0, 0.25, 0.04)
    assert f.tolist() == pytest.approx([1.0, 0.5, 0.25, 0.04])
    assert unc.predicted_mae_s(45.0, 0.25, 0.04) == pytest.approx(max(0.0, float(f @ np.array(unc.MAE_COEFFICIENTS))))
    assert unc.predicted_mae_s(45.0, 0.25, 0.04, coefficients=(-1.0, 0, 0, 0)) == 0.0


def test_calibrated_cones_are_the_documented_law():
    # beta = [ln 2, 1, -ln 2, 0] and k = (1.5, 3): r = k * 2 * p_90 * 2^-lit
    beta, k = (math.log(2.0), 1.0, -math.log(2.0), 0.0), (1.5, 3.0)
    assert unc.calibrated_cones_deg(5.0, 1.0, False, beta, k) == pytest.approx((7.5, 15.0))
    assert unc.calibrated_cones_deg(5.0, 0.0, True, beta, k) == pytest.approx((15.0, 30.0))
    assert unc.calibrated_cones_deg(500.0, 0.0, False, beta, k) == (180.0, 180.0)  # never past the antipode
    # the shipped constants: a face the sun lights less gets wider cones, and the 90% one is the wider
    lit, dark = unc.calibrated_cones_deg(10.0, 0.9, False), unc.calibrated_cones_deg(10.0, 0.1, False)
    assert dark[0] > lit[0] and dark[1] > lit[1] and lit[1] > lit[0]


def test_lit_fraction_counts_the_normals_facing_the_sun():
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    assert unc.lit_fraction(normals, np.array([0.0, 0.6, 0.8])) == 0.5
    assert unc.lit_fraction(normals[:0], np.array([0.0, 1.0, 0.0])) == 0.0


def face_under_sun(elevation_deg: float, azimuth_deg: float):
    """A frontal face rendered under a sunsky light whose sun is at (elevation, azimuth) (azimuth 0:
    -Z, behind the head; 180: +Z, towards the camera), and the true sun."""
    from f2l.synth.render import render_face

    model = check_model("sunsky", GRID)
    params = model.initial_points()[0].copy()
    params[model.sun_layout.elevation] = math.radians(elevation_deg)
    params[model.sun_layout.azimuth] = math.radians(azimuth_deg)
    grid = LatLongGrid(*GRID)
    probe = model_probe(model, params)
    face = render_face(grid, probe, np.random.default_rng(3), image_size=96, albedo=[0.6, 0.45, 0.35],
                       head_pose_deg=[0.0, 0.0, 0.0], threads=1)
    obs = FaceObservation(face.normals, face.observed_rgb, face.mask, face.visibility_bits, grid)
    return model, obs, model.sun_direction(params)


@pytest.fixture(scope="module")
def front_and_behind():
    cfg = EstimatorConfig(threads=1, skin_gloss=0.0)
    out = {}
    for name, (el, az) in {"front": (35.0, 150.0), "behind": (35.0, 10.0)}.items():
        model, obs, sun = face_under_sun(el, az)
        out[name] = (estimate(obs, model, cfg), sun, obs)
    return out


def test_a_face_under_a_known_sun_holds_it_in_its_90_percent_cone(front_and_behind):
    result, sun, obs = front_and_behind["front"]
    u = result.sun_uncertainty
    error = math.degrees(math.acos(min(1.0, float(result.sun_direction @ sun))))
    assert 0 < u.cone68_deg <= u.cone90_deg <= 180.0
    assert error <= u.cone90_deg
    assert u.num_pixels == int(np.count_nonzero(obs.mask))
    assert result.timings["uncertainty_s"] < 0.05  # reuses the search's scores: no refit


def test_a_sun_behind_the_head_gets_a_wider_cone_than_one_in_front(front_and_behind):
    front = front_and_behind["front"][0].sun_uncertainty
    behind = front_and_behind["behind"][0].sun_uncertainty
    assert behind.cone90_deg > front.cone90_deg
    assert behind.cone68_deg > front.cone68_deg


def test_a_model_without_a_compact_sun_has_no_uncertainty(front_and_behind):
    obs = front_and_behind["front"][2]
    assert estimate(obs, check_model("sh9", GRID), EstimatorConfig(threads=1)).sun_uncertainty is None


def test_the_estimates_row_and_the_exr_header_carry_the_cones_and_nulls_without_one(tmp_path, front_and_behind):
    from f2l.estimate.record import _base_row, write_result
    from f2l.io.exr import read_exr_with_metadata
    from f2l.io.schema import validate_table
    from f2l.io.tables import rows_to_table, write_table_atomic

    result = front_and_behind["front"][0]
    ok = _base_row({"face_id": "a", "source_path": "a.png", "grid_height": 32, "grid_width": 64}, "sunsky")
    write_result(ok, result, None, "", "sunsky", tmp_path, "a", "a", "")
    failed = _base_row({"face_id": "b", "source_path": "b.png"}, "sunsky")  # no estimate: nulls
    table = rows_to_table([ok, failed], "estimates")
    write_table_atomic(table, tmp_path / "estimates.parquet", "estimates")
    back = pq.read_table(tmp_path / "estimates.parquet")
    validate_table(back, "estimates", source="round trip")
    rows = back.to_pylist()
    u = result.sun_uncertainty
    assert rows[0]["sun_cone68_deg"] == u.cone68_deg and rows[0]["sun_cone90_deg"] == u.cone90_deg
    assert rows[0]["predicted_mae_s"] == u.predicted_mae_s
    assert rows[1]["sun_cone68_deg"] is None and rows[1]["sun_cone90_deg"] is None and rows[1]["predicted_mae_s"] is None
    _, header = read_exr_with_metadata(tmp_path / ok["probe_path"])
    assert float(header["f2l_sun_cone90_deg"]) == u.cone90_deg
    assert float(header["f2l_predicted_mae_s"]) == u.predicted_mae_s
