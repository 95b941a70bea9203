"""The example plugin's own tests, written against f2l's fixtures for plugin authors (docs/plugins.md).

Run after installing the plugin: ``pytest plugins/example_gradient_sun/tests``.
"""

from __future__ import annotations

import math

import numpy as np
import torch

GRID = (32, 64)


def test_registers_with_its_capabilities(f2l_check_model):
    model = f2l_check_model("gradient_sun", GRID)  # refused here if a declared capability is broken
    from f2l.models.capabilities import declared

    assert declared(model) == ["compact-sun", "sun-angles"]
    assert model.num_params == 9 and model.domain == "sky"


def test_sky_is_a_horizon_to_zenith_gradient_of_unit_mean(f2l_check_model):
    model = f2l_check_model("gradient_sun", GRID)
    grid = model.grid
    for ratio in (0.05, 1.0, 3.0, 20.0):
        p = torch.tensor([[1.0, 1, 1, 0, 0, 0, 0.5, 0.0, ratio]], dtype=torch.float64)
        sky = model.sky(p)[0, :, 1].numpy().reshape(grid.sky_rows, grid.width)
        sa = grid.solid_angles[: grid.sky_rows]
        assert math.isclose(float((sky * sa).sum() / sa.sum()), 1.0, rel_tol=2e-3)  # unit mean
        sin_e = np.sin(np.pi / 2 - grid.phi_rad[: grid.sky_rows])  # row centres' elevation
        want = (ratio + (1 - ratio) * sin_e) / (ratio + (1 - ratio) * sin_e[0])
        assert np.allclose(sky[:, 0] / sky[0, 0], want, rtol=1e-9)  # the gradient, row by row


def test_round_trip_recovers_its_own_sun(f2l_round_trip):
    cases = f2l_round_trip("gradient_sun", n=3, seed=1, grid=GRID, image_size=96)
    angles = [c["sun_angle_deg"] for c in cases]
    assert all(a is not None and a < 6.0 for a in angles), angles  # texels are 5.6 deg on 32 x 64
    for c in cases:  # the recovered probe is close to the one the face was rendered under
        assert c["metrics"]["Sky-dω MAE (l)"] < 0.05, c["metrics"]
        assert np.isfinite(c["estimate"].params).all()


def test_estimates_faces_it_did_not_make(f2l_synthetic_faces):
    from f2l.estimate import EstimatorConfig, estimate
    from f2l.testing import check_model

    model = check_model("gradient_sun", GRID)
    for case in f2l_synthetic_faces(n=2, grid=GRID, seed=3):
        res = estimate(case.observation, model, EstimatorConfig(threads=1))
        angle = math.degrees(math.acos(float(np.clip(res.sun_direction @ case.gt_sun_direction, -1, 1))))
        assert angle < 30.0  # a CIE sky with circumsolar glow is not a gradient: looser than its own
