"""The sun's elevation profile of compact-sun models (EstimatorConfig.sun_elevation_profile_deg)."""

import math

import numpy as np
import pytest

from f2l.estimate import EstimatorConfig, estimate
from f2l.estimate.sun_profile import posterior_weights
from f2l.metrics import evaluate_pair
from f2l.testing import check_model, synthetic_faces

GRID = (32, 64)


def test_posterior_weights_favour_the_lowest_objective_and_ignore_non_finite_values():
    totals = np.array([0.100, 0.101, 0.110, np.nan, np.inf])
    w = posterior_weights(totals, 100.0)
    assert w.sum() == pytest.approx(1.0)
    assert w[0] > w[1] > w[2] > 0 and w[3] == 0 and w[4] == 0
    # relative excess: 1% above the minimum weighs exp(-1) of it at temperature 100
    assert w[1] / w[0] == pytest.approx(math.exp(-1.0), rel=1e-9)
    assert np.allclose(posterior_weights(totals[:3], 0.0), 1 / 3)  # no temperature: a plain mean
    assert posterior_weights(totals[:3], 1e6)[0] == pytest.approx(1.0)  # very cold: the minimum alone


def sun_error_deg(result, case) -> float:
    cos = float(np.dot(result.sun_direction, case.gt_sun_direction))
    return math.degrees(math.acos(min(1.0, cos)))


@pytest.fixture(scope="module")
def faces():
    return synthetic_faces(3, grid=GRID, seed=5)


def test_on_faces_the_model_describes_the_profile_keeps_or_improves_the_fit(faces):
    model = check_model("sunsky", GRID)
    # Lambertian own renders: the model describes them without the skin's gloss
    on = EstimatorConfig(threads=1, skin_gloss=0.0)
    off = EstimatorConfig(threads=1, skin_gloss=0.0, sun_elevation_profile_deg=())
    assert on.sun_elevation_profile_deg  # on by default for sun models
    assert not any(c.overcast for c in faces)
    for case in faces:
        a, b = estimate(case.observation, model, on), estimate(case.observation, model, off)
        assert np.isfinite(a.probe).all() and a.probe.min() >= 0
        pins = len(on.sun_elevation_profile_deg)
        if a.timings["sun_core"] > 0:  # a sunny fit: the fit and its pinned copies were scored
            assert a.timings["profile_s"] > 0
            assert pins <= len(a.start_losses) <= pins + 1 and np.isfinite(a.start_losses).all()
            assert a.loss == pytest.approx(min(a.start_losses))
            assert a.loss <= b.loss * (1 + 1e-9)  # the MAP is never worse than the fit alone
        # own renders: the data decide the elevation and the posterior is sharp; where the free fit
        # stalled short of the minimum (one of these faces: 2.8 deg off), a pinned copy finds it
        assert sun_error_deg(a, case) <= sun_error_deg(b, case) + 0.25
        # (2.5: the 10.5-deg sun reads 2.3 deg off since the prior prefers no elevation; the prior's old
        # modes at 8 and 14 deg had put it 1.0 deg off. A texel of this 32 x 64 grid is 5.6 deg.)
        assert sun_error_deg(a, case) < 2.5
        ma = evaluate_pair(a.probe, case.gt_probe, model.grid, overcast=case.overcast, gt_sun_dir=case.gt_sun_direction,
                           est_sun_dir=a.sun_direction)
        mb = evaluate_pair(b.probe, case.gt_probe, model.grid, overcast=case.overcast, gt_sun_dir=case.gt_sun_direction,
                           est_sun_dir=b.sun_direction)
        assert ma["MAE (s)"] <= mb["MAE (s)"] * 1.05 + 1e-3


def test_a_flat_profile_hedges_toward_the_mean_of_the_pinned_suns(faces):
    """At temperature 0 every pinned copy weighs the same: the reported sun is their mean
    direction, between the lowest and the highest pin, and the probe their mixture (finite)."""
    model = check_model("sunsky", GRID)
    case = next(c for c in faces if not c.overcast)
    cfg = EstimatorConfig(threads=1, sun_profile_temperature=0.0, sun_elevation_profile_deg=(10.0, 30.0, 50.0, 70.0))
    r = estimate(case.observation, model, cfg)
    assert r.timings["sun_core"] > 0
    elevation = math.degrees(math.asin(r.sun_direction[1]))
    assert 10.0 < elevation < 70.0
    assert np.isfinite(r.probe).all() and r.probe.min() >= 0


def test_the_highlight_k_s_reported_is_the_chosen_copys_when_a_pinned_copy_wins(monkeypatch):
    """With the sun's highlight on (sun_specular), the reported k_s follows the start that wins,
    also when that is the last pinned copy (it used to index past the copies' k_s)."""
    import f2l.estimate.sun_profile as profile
    from f2l.estimate import FaceObservation
    from f2l.estimate.problem import SPECULAR_LEVELS
    from f2l.lighting.grid import LatLongGrid
    from f2l.synth.render import make_synthetic_set

    grid = LatLongGrid(*GRID)
    real = profile.pinned_copies

    def last_copy_wins(*args, **kwargs):
        out = real(*args, **kwargs)
        if out is not None:
            totals = out[3].copy()
            totals[-1] = 0.5 * np.nanmin(totals)
            out = (*out[:3], totals)
        return out

    monkeypatch.setattr(profile, "pinned_copies", last_copy_wins)
    face = next(iter(make_synthetic_set(1, grid, 3, image_size=96, overcast_fraction=0.0, specular=0.3, threads=1,
                                        sun_elevation_range_deg=(20.0, 50.0))))
    obs = FaceObservation(face.normals, face.observed_rgb, face.mask, face.visibility_bits, grid, points=face.points)
    r = estimate(obs, check_model("sunsky", GRID), EstimatorConfig(threads=1, sun_specular=True))
    assert r.loss == pytest.approx(min(r.start_losses)) and r.loss == r.start_losses[-1]
    levels = [level * EstimatorConfig().sun_specular_max for level in SPECULAR_LEVELS]
    assert r.specular_ks is not None and min(abs(r.specular_ks - v) for v in levels) < 1e-9
