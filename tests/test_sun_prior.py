"""The sun-elevation prior from a photo's capture time and place (runner + estimator search)."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from f2l.estimate.runner import capture_sun_prior
from f2l.io.capture import capture_for_elevation, capture_to_meta, solar_position
from f2l.lighting.grid import LatLongGrid


@pytest.mark.parametrize("elevation_deg", [10.0, 35.0, 69.0])
def test_capture_for_elevation_round_trip(elevation_deg):
    info = capture_for_elevation(math.radians(elevation_deg))
    assert math.degrees(solar_position(info)[0]) == pytest.approx(elevation_deg, abs=0.02)
    with pytest.raises(ValueError, match="does not reach"):
        capture_for_elevation(math.radians(89.9), latitude_deg=60.0)


def test_prior_from_meta_capture():
    meta = capture_to_meta(capture_for_elevation(math.radians(35.0)))
    prior, note = capture_sun_prior(SimpleNamespace(meta=meta, source_path=""), 0.05)
    assert prior is not None and prior[1] == 0.05
    assert math.degrees(prior[0]) == pytest.approx(35.0, abs=0.02)
    assert "elevation 35.0 deg from meta" in note


def test_no_prior_at_night_or_without_capture(tmp_path):
    night = {"capture": {"utc": "2024-12-21T00:00:00Z", "latitude_deg": 51.48, "longitude_deg": 0.0}}
    prior, note = capture_sun_prior(SimpleNamespace(meta=night, source_path=""), 0.05)
    assert prior is None and "below the horizon" in note
    prior, note = capture_sun_prior(SimpleNamespace(meta={}, source_path=str(tmp_path / "missing.jpg")), 0.05)
    assert prior is None and note == ""
    bad = {"capture": {"utc": "2024-06-21T08:00:00Z", "latitude_deg": 123.0, "longitude_deg": 0.0}}
    prior, note = capture_sun_prior(SimpleNamespace(meta=bad, source_path=""), 0.05)
    assert prior is None and "bad meta capture" in note


def test_photo_without_exif_gives_a_reason(tmp_path):
    from PIL import Image

    path = tmp_path / "plain.jpg"
    Image.new("RGB", (8, 8)).save(path)
    prior, note = capture_sun_prior(SimpleNamespace(meta={}, source_path=str(path)), 0.05)
    assert prior is None and note.startswith("sun prior: none (") and "plain.jpg" in note


def test_elevation_prior_restricts_the_search():
    from f2l.estimate import EstimatorConfig, FaceObservation
    from f2l.estimate.problem import FaceProblem
    from f2l.estimate.skin import skin_albedo_mean
    from f2l.models.registry import load_model
    from f2l.synth.render import make_synthetic_set

    grid = LatLongGrid()
    face = next(iter(make_synthetic_set(1, grid, 5, image_size=64, overcast_fraction=0.0)))
    obs = FaceObservation(face.normals, face.observed_rgb, face.mask, face.visibility_bits, grid)
    el0 = math.radians(face.meta["sky"]["sun_elevation_deg"])
    model = load_model("sunsky", grid)
    prob = FaceProblem(obs, model, EstimatorConfig(sun_elevation_prior=(el0, 0.05)))
    starts = prob.sun_search_starts(skin_albedo_mean(), 0.2)
    half_row = 0.5 * math.pi / grid.height
    elevations = np.array([c.elevation_rad for c in prob.search_candidates])
    assert np.all(np.abs(elevations - el0) <= max(3 * 0.05, math.radians(4.0)) + half_row)
    assert np.all(np.abs(starts[:, 6] - el0) <= max(3 * 0.05, math.radians(4.0)) + half_row)
    # and the objective's prior term pulls the elevation: 0 at el0, growing quadratically
    import torch

    p = torch.as_tensor(starts[:1]).repeat(2, 1)
    p[0, 6], p[1, 6] = el0, el0 + 0.1
    rho = torch.full((2, 3), 0.3, dtype=torch.float64)
    gnd = torch.full((2,), 0.2, dtype=torch.float64)
    with_prior = prob.objective(p, rho, gnd)[0]
    prob.cfg = EstimatorConfig()
    without = prob.objective(p, rho, gnd)[0]
    np.testing.assert_allclose((with_prior - without).numpy(), [0.0, 1e-3 * 0.5 * (0.1 / 0.05) ** 2], atol=1e-12)
