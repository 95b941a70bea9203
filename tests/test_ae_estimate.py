"""The shipped sky-autoencoder model: face estimation (f2l.estimate.latent through f2l.estimate.estimate) and
probe fits (fit-probe's ae / ae_ff), on skies of the autoencoder's own corpus generator."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from f2l_builtin_models.autoencoder.corpus import random_ae_sky
from f2l.estimate import EstimatorConfig, FaceObservation, estimate
from f2l.prior.build import fit_probes
from f2l.prior.fit_report import write_fit_report
from f2l.prior.probe_fit import fit_probe
from f2l.io.exr import write_exr
from f2l.lighting.grid import LatLongGrid, angles_from_direction
from f2l_builtin_models.ae import DEFAULT_WEIGHTS, AE

GRID = LatLongGrid(64, 128)


def _clear_sky(seed_from: int, kind: str = "clear", min_elevation: float = 15.0, max_elevation: float = 60.0):
    """The first corpus sky of ``kind`` with the sun between the given elevations, from seed ``seed_from``."""
    for seed in range(seed_from, seed_from + 500):
        probe, info = random_ae_sky(GRID, np.random.default_rng(seed))
        if info["kind"] == kind and min_elevation <= info["sun_elevation_deg"] <= max_elevation:
            return probe, info
    raise AssertionError("no such sky")


def _azimuth_error_deg(a: float, b: float) -> float:
    return abs(math.degrees((a - b + math.pi) % (2 * math.pi) - math.pi))


@pytest.fixture(scope="module")
def model(monkeypatch_module=None):
    assert DEFAULT_WEIGHTS.is_file(), "shipped weights missing: make ae-weights"
    return AE(GRID)


@pytest.fixture(scope="module")
def face_under_corpus_sky():
    from f2l.synth.render import render_face

    probe, info = _clear_sky(1000)
    sun = np.asarray(info["sun_direction"])
    face = render_face(GRID, probe, np.random.default_rng(4), image_size=96, head_pose_deg=(5.0, -10.0, 0.0),
                       sun_direction=sun, sky_info=info)
    return face, info


def test_clear_sky_probe_puts_its_sun_where_asked():
    from f2l_builtin_models.autoencoder.corpus import clear_sky_probe
    from f2l.metrics.lighting import sun_direction

    for elevation_deg, azimuth_deg in ((5.0, -120.0), (40.0, 30.0), (85.0, 170.0)):
        probe = clear_sky_probe(GRID, math.radians(elevation_deg), math.radians(azimuth_deg), turbidity=4.0)
        assert probe.dtype == np.float32 and np.all(np.isfinite(probe)) and probe.min() >= 0
        el, az = angles_from_direction(sun_direction(probe, GRID))
        assert abs(math.degrees(el) - elevation_deg) < 1.5
        assert _azimuth_error_deg(az, math.radians(azimuth_deg)) < 1.5 / max(math.cos(el), 0.1)


def test_search_ladder_decodes_to_suns_at_every_elevation(model):
    """The search's ladder codes (encoded cloudless skies, sun every 3 deg) decode to suns at their
    elevations: the decoder, not only the encoder, covers the whole range."""
    from f2l_builtin_models.ae import LADDER_ELEVATIONS_DEG, LADDER_TURBIDITIES

    codes = model.ladder_codes()
    assert codes.shape == (len(LADDER_ELEVATIONS_DEG) * len(LADDER_TURBIDITIES), 63)
    assert model.search_codes().shape[0] == codes.shape[0] + 24  # 8 GMM components x 3 points first
    for i, code in enumerate(codes):
        params = np.concatenate([[0.0], code, [0.0]])
        el, az = angles_from_direction(model.sun_direction(params))
        want = LADDER_ELEVATIONS_DEG[i // len(LADDER_TURBIDITIES)]
        assert abs(math.degrees(el) - want) < (2.0 if want < 3 else 1.0), (want, math.degrees(el))
        assert _azimuth_error_deg(az, 0.0) < 1.0 / max(math.cos(el), 0.05)


def test_estimate_recovers_the_sun_azimuth_of_a_corpus_sky(model, face_under_corpus_sky):
    face, info = face_under_corpus_sky
    obs = FaceObservation(face.normals, face.observed_rgb, face.mask, face.visibility_bits, GRID)
    res = estimate(obs, model, EstimatorConfig(threads=2))
    assert res.params.shape == (65,) and res.param_names[0] == "z00_log_exposure"
    assert res.probe.shape == (64, 128, 3) and np.isfinite(res.probe).all() and res.probe.min() >= 0
    # the ground bounce is the estimator's: constant below the horizon, rho_g E_h / pi
    assert np.allclose(res.probe[32:], res.probe[40, 7], rtol=1e-5) and 0 < res.ground_albedo < 1
    assert np.all((res.albedo > 0) & (res.albedo <= 1))
    _, est_az = angles_from_direction(res.sun_direction)
    assert _azimuth_error_deg(float(est_az), math.radians(info["sun_azimuth_deg"])) < 20.0
    # phi_sun (the last parameter) is where the decoded sun was turned to
    assert _azimuth_error_deg(res.params[-1], math.radians(info["sun_azimuth_deg"])) < 25.0
    assert res.timings["starts"] >= 1 and res.iterations > 0


def test_an_ae_estimate_carries_sun_cones_holding_the_true_sun(model, face_under_corpus_sky):
    face, info = face_under_corpus_sky
    obs = FaceObservation(face.normals, face.observed_rgb, face.mask, face.visibility_bits, GRID)
    res = estimate(obs, model, EstimatorConfig(threads=2))
    u = res.sun_uncertainty
    assert u is not None and 0 < u.cone68_deg < u.cone90_deg <= 180.0
    error = math.degrees(math.acos(min(1.0, float(np.asarray(res.sun_direction) @ np.asarray(info["sun_direction"])))))
    assert error <= u.cone90_deg
    assert u.num_pixels == int(np.count_nonzero(face.mask)) and not u.overcast_fit
    assert u.predicted_mae_s >= 0 and res.timings["uncertainty_s"] < 0.05  # the search's scores: no refit


def test_a_search_candidate_s_sun_turns_with_its_azimuth_roll(model):
    """Candidate (k, j) is code k's cached sky rolled by j half-blocks: its sun is the rolled sky's
    brightest texel, and turning the candidate turns its sun about +Y by the search's azimuth step."""
    import f2l.estimate.latent as latent
    from f2l.lighting.grid import angles_from_direction

    n = 256
    obs = FaceObservation(np.tile([[0.0, 0.0, 1.0]], (n, 1)), np.full((n, 3), 0.2), np.ones(n, bool),
                          np.zeros((n, GRID.size // 8), np.uint8), GRID)
    prob = latent.LatentSkyProblem(obs, model, EstimatorConfig(threads=1))
    codes, skies = prob.candidate_skies()
    K, A = len(codes), 2 * prob.nbc
    suns = latent.candidate_sun_directions(prob, (K, A)).reshape(K, A, 3)
    lum = np.array([0.2126, 0.7152, 0.0722])
    for k, j in ((0, 0), (1, 5), (K - 1, A - 1)):
        sky = prob.rotated_candidates([k], [j])[0].numpy()  # (3, rows, W)
        r, c = np.unravel_index(np.argmax(np.tensordot(lum, sky, 1)), sky.shape[1:])
        assert np.allclose(suns[k, j], GRID.directions_flat[r * GRID.width + c])
        el0, az0 = angles_from_direction(suns[k, 0])
        el, az = angles_from_direction(suns[k, j])
        assert el == pytest.approx(el0)
        assert _azimuth_error_deg(float(az), float(az0) + prob.search_azimuth(j)) < 1e-6


def test_fit_probe_gives_the_feed_forward_and_the_optimised_fit(model):
    probe, info = _clear_sky(2000)
    fit = fit_probe(probe, model, max_iter=25)
    ff = fit.variants["ae_ff"]
    assert fit.loss <= ff.loss + 1e-9  # the optimisation starts at the feed-forward code
    true_az = math.radians(info["sun_azimuth_deg"])
    assert _azimuth_error_deg(ff.params[-1], true_az) < 3.0  # phi_sun of AE_FF: the probe's sun azimuth
    for f in (ff, fit):
        assert f.probe.shape == (64, 128, 3) and np.isfinite(f.probe).all()
        _, az = angles_from_direction(f.sun_direction)
        assert _azimuth_error_deg(float(az), true_az) < 5.0
    # the exposure is carried through: a 1000x brighter probe gives z_0 + log(1000)
    ff2 = fit_probe(probe * 1000.0, model, max_iter=0).variants["ae_ff"]
    assert math.isclose(ff2.params[0] - ff.params[0], math.log(1000.0), rel_tol=1e-6)
    assert np.allclose(ff2.params[1:], ff.params[1:], atol=1e-3)


def test_fit_probe_report_has_ae_and_ae_ff_rows(model, tmp_path):
    probe, _ = _clear_sky(3000)
    write_exr(tmp_path / "sky.exr", probe)
    records = fit_probes([tmp_path / "sky.exr"], model, max_iter=10)
    assert records[0].status == "ok", records[0].message
    assert set(records[0].extra["variants"]) == {"ae_ff"}
    summary = write_fit_report(records, model, tmp_path / "report")
    fits = [row["model"] for row in summary["metrics"]]
    assert fits == ["ae", "ae_ff"]
    assert "| ae_ff | 1 |" in summary["markdown"] and "Sun-dω MAE (l)" in summary["markdown"]
    header = (tmp_path / "report" / "fit_probe.csv").read_text().splitlines()[0]
    assert "ae_ff Full-dω MAE (l)" in header and "z00_log_exposure" in header


def test_radiance_on_another_grid_keeps_the_energy(model):
    coarse = AE(LatLongGrid(32, 64))
    p = torch.as_tensor(model.initial_points()[:2])
    fine = model.radiance(p).reshape(2, 64, 128, 3).numpy()
    small = coarse.radiance(p).reshape(2, 32, 64, 3).numpy()
    e_fine = np.einsum("bhwc,hw->bc", fine, GRID.solid_angles)
    e_small = np.einsum("bhwc,hw->bc", small, LatLongGrid(32, 64).solid_angles)
    assert np.allclose(e_fine, e_small, rtol=1e-4)


def test_clipped_pixels_reach_the_latent_sky_fit(model, face_under_corpus_sky):
    """ae reads a face's partly clipped pixels as sunsky does: clipped channels as lower bounds."""
    import torch

    from f2l.estimate.latent import LatentSkyProblem
    from f2l.estimate import EstimatorConfig, FaceObservation

    face, _ = face_under_corpus_sky
    rgb = np.asarray(face.observed_rgb, np.float64)
    bright = rgb.max(1) >= np.percentile(rgb.max(1), 85)
    observed = rgb / np.percentile(rgb.max(1), 85)
    observed[bright] = np.minimum(observed[bright] * np.array([1.4, 1.0, 0.8]), 1.0)  # red clips first
    obs = FaceObservation(face.normals, observed, np.asarray(face.mask) & ~bright, face.visibility_bits, GRID)
    prob = LatentSkyProblem(obs, model, EstimatorConfig())
    assert prob.clip is not None and prob.clip["bound"].any() and not prob.clip["bound"].all()
    assert LatentSkyProblem(obs, model, EstimatorConfig(clipped_bounds=False)).clip is None
    dark = torch.zeros(1, 3, prob.rows, prob.width)
    cost = float(prob.clipped_term(dark, torch.ones(1, 3), torch.zeros(1)))
    np.testing.assert_allclose(cost, float(prob.clip["target"].sum()), rtol=1e-3)  # all short by their value


def test_cached_search_codes_and_skies_do_not_depend_on_the_thread_count():
    """The ladder codes and decoded search skies are cached once per process; float32 kernels round
    differently with 1 or 2 threads, so they are computed single-threaded whatever came before."""
    import f2l.estimate.latent as latent
    import f2l_builtin_models.ae as ae_module

    before = torch.get_num_threads()
    grid = LatLongGrid(64, 128)
    n = 512
    obs = FaceObservation(np.tile([[0.0, 0.0, 1.0]], (n, 1)), np.full((n, 3), 0.2), np.ones(n, bool),
                          np.zeros((n, grid.size // 8), np.uint8), grid)
    out = []
    try:
        for threads in (2, 1):
            ae_module._LADDER_CACHE.clear()
            latent._SEARCH_CACHE.clear()
            torch.set_num_threads(threads)
            model = AE(grid)
            codes, skies = latent.LatentSkyProblem(obs, model, EstimatorConfig(threads=threads)).candidate_skies()
            out.append((model.ladder_codes().copy(), codes.copy(), skies.clone()))
    finally:
        torch.set_num_threads(before)
    assert np.array_equal(out[0][0], out[1][0]) and np.array_equal(out[0][1], out[1][1])
    assert torch.equal(out[0][2], out[1][2])
    assert torch.get_num_threads() == before
