"""The sun models' skin-prior weight (EstimatorConfig.sun_albedo_prior_weight)."""

import dataclasses

import numpy as np
import pytest

from f2l.estimate import EstimatorConfig, FaceObservation, estimate
from f2l.estimate.skin import skin_albedo_mean
from f2l.lighting.grid import LatLongGrid
from f2l.models.registry import load_model

GRID = LatLongGrid(32, 64)
# a light measured-skin-like albedo, less red than the prior's ColorChecker skin (R/G ~1.8-2.2)
SKIN = np.array([0.55, 0.38, 0.30])


def _faces(n: int = 2):
    from f2l.synth.render import make_synthetic_set

    for face in make_synthetic_set(n, GRID, 5, image_size=80, overcast_fraction=0.0, threads=1, albedo=SKIN,
                                   sun_elevation_range_deg=(25.0, 55.0)):
        yield FaceObservation(face.normals, face.observed_rgb, face.mask, face.visibility_bits, GRID)


def test_the_prior_skin_is_redder_than_this_face():
    mean = skin_albedo_mean()
    assert mean[0] / mean[1] > 1.6 > SKIN[0] / SKIN[1]


def test_a_weaker_skin_prior_lets_the_data_and_the_sky_prior_set_the_colour():
    """On faces whose skin is less red than the prior's, the default weight (1e-4) lands the skin's
    R/G nearer the truth than the general albedo_prior_weight (1e-3, ``None``); the weight applies
    to sun models only."""
    model = load_model("sunsky", GRID)
    default = dataclasses.replace(EstimatorConfig(), threads=1)
    assert default.sun_albedo_prior_weight == pytest.approx(1e-4) and default.albedo_prior_weight == pytest.approx(1e-3)
    strong = dataclasses.replace(default, sun_albedo_prior_weight=None)
    true_rg = SKIN[0] / SKIN[1]
    err = {"default": [], "strong": []}
    for obs in _faces():
        for name, cfg in (("default", default), ("strong", strong)):
            rho = estimate(obs, model, cfg).albedo
            err[name].append(abs(np.log(rho[0] / rho[1] / true_rg)))
    assert np.mean(err["default"]) < np.mean(err["strong"])
    assert all(np.isfinite(v) for v in err["default"] + err["strong"])


def test_other_models_keep_the_general_weight():
    from f2l.estimate.problem import FaceProblem

    obs = next(_faces(1))
    cfg = dataclasses.replace(EstimatorConfig(), threads=1, sun_albedo_prior_weight=0.5)
    assert FaceProblem(obs, load_model("sunsky", GRID), cfg).albedo_prior_weight == 0.5
    assert FaceProblem(obs, load_model("sh9", GRID), cfg).albedo_prior_weight == cfg.albedo_prior_weight


def test_the_shipped_skin_albedo_gmm_is_the_fit():
    """f2l/data/skin_albedo_gmm.json holds what fit_skin_albedo_gmm() gives (exactly on the machine
    that wrote it; to rounding elsewhere)."""
    from f2l.estimate.skin import GMM_FILE, fit_skin_albedo_gmm, skin_albedo_gmm

    assert GMM_FILE.is_file()
    shipped, fresh = skin_albedo_gmm(), fit_skin_albedo_gmm()
    for key in ("weights", "means", "covariances"):
        np.testing.assert_allclose(shipped[key], fresh[key], rtol=1e-9, atol=1e-12)
