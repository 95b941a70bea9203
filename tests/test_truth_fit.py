"""eval-real's model-family oracles (f2l.evaluation.truth_fit): a model fitted to the true probe itself,
as fitted and with its sun moved 5°, cached per case; and the probe fit's guard against a run that
diverges (f2l.prior.probe_fit.minimise_restarted)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from f2l.prior.probe_fit import minimise_restarted
from f2l.lighting.grid import LatLongGrid
from f2l.metrics.lighting import angle_deg
from f2l.evaluation.eval_report import summary_table
from f2l.evaluation.evaluate import _truth_fit_rows
from f2l.evaluation.truth_fit import FIT_SUFFIX, MOVED_SUFFIX, MOVED_SUN_DEG, is_truth_fit, moved_direction, truth_fit
from f2l_builtin_models.sunsky import SunSky

GRID = LatLongGrid(32, 64)
# w_sky rgb, w_sun rgb, elevation 35 deg, azimuth 100 deg, t = 3, kappa = 2000
TRUE = np.array([0.8, 1.0, 1.3, 40.0, 38.0, 33.0, math.radians(35.0), math.radians(100.0), 3.0, 2000.0])


@pytest.fixture(scope="module")
def truth():
    """A probe sunsky renders itself, with a grey lower hemisphere as a real probe has."""
    probe = SunSky(GRID).probe(TRUE).astype(np.float64)
    probe[GRID.sky_rows:] = 0.3
    return probe


def _meta(sun):
    return {"sky": {"kind": "clear", "sun_direction": list(map(float, sun))}}


def test_moved_direction_turns_by_the_angle_and_is_fixed_per_case():
    d = np.array([0.3, 0.8, -0.5])
    d /= np.linalg.norm(d)
    a = moved_direction(d, 5.0, "pbr-s0-00001")
    assert abs(angle_deg(a, d) - 5.0) < 1e-9 and abs(np.linalg.norm(a) - 1.0) < 1e-12
    np.testing.assert_array_equal(a, moved_direction(d, 5.0, "pbr-s0-00001"))
    assert angle_deg(a, moved_direction(d, 5.0, "pbr-s0-00003")) > 0.1  # another case, another way


def test_a_model_fitted_to_its_own_probe_scores_near_zero_and_the_moved_sun_five_degrees(tmp_path, truth):
    sun = SunSky(GRID).sun_direction(TRUE)
    rows = {name: m for name, m, _ in _truth_fit_rows(truth, "sunsky", GRID, "case-a", _meta(sun), tmp_path)}
    assert set(rows) == {"sunsky" + FIT_SUFFIX, "sunsky" + MOVED_SUFFIX}
    fitted, moved = rows["sunsky" + FIT_SUFFIX], rows["sunsky" + MOVED_SUFFIX]
    assert fitted["Sun-ang (°)"] < 0.5 and fitted["MAE (s)"] < 0.02, fitted
    assert abs(moved["Sun-ang (°)"] - MOVED_SUN_DEG) < 0.6, moved
    # a sun 5 degrees off costs the relit scene (shadows move) and the per-texel light far more
    assert moved["MAE (s)"] > fitted["MAE (s)"] + 0.01
    assert moved["Full-dω MAE (l)"] > 2.0 * fitted["Full-dω MAE (l)"]
    assert all(math.isnan(m["photo residual"]) for m in rows.values())


def test_the_fit_is_cached_read_back_identically_and_refitted_when_the_model_changes(tmp_path, truth):
    probe, sun, runtime_s = truth_fit(truth, "sunsky", GRID, "case-b", tmp_path)
    exr = tmp_path / "sunsky" / "case-b.exr"
    meta = json.loads(exr.with_suffix(".json").read_text())
    assert meta["model"] == "sunsky" and meta["grid"] == [32, 64] and meta["runtime_s"] == runtime_s
    again, sun_again, runtime_again = truth_fit(truth, "sunsky", GRID, "case-b", tmp_path)
    np.testing.assert_array_equal(again, probe.astype(np.float32))
    np.testing.assert_array_equal(sun_again, sun)
    assert runtime_again == runtime_s  # read, not refitted
    meta["model_version"] = "0-old"
    exr.with_suffix(".json").write_text(json.dumps(meta))
    exr.write_bytes(b"not an exr")  # a stale cache is not read
    refit, _, _ = truth_fit(truth, "sunsky", GRID, "case-b", tmp_path)
    np.testing.assert_allclose(refit, probe, rtol=1e-4, atol=1e-6)
    assert json.loads(exr.with_suffix(".json").read_text())["model_version"] == str(SunSky.version)


def test_a_black_truth_is_left_out_with_a_message(tmp_path, capsys):
    rows = _truth_fit_rows(np.zeros(GRID.shape + (3,)), "sunsky", GRID, "case-c", {"sky": {"kind": "overcast"}}, tmp_path)
    assert rows == []
    assert "case-c: sunsky could not be fitted to the true probe" in capsys.readouterr().err


def test_truth_fits_are_listed_with_the_references_and_keep_their_fit_time():
    metrics = {k: 0.1 for k in ("MAE (s)", "RMSE (s)", "si-RMSE (s)", "Full-dω MAE (l)", "Sky-dω MAE (l)",
                                "Sun-dω MAE (l)", "Sun-ang (°)")}
    rows = [{"method": m, "split": "report", "runtime_s": t, **metrics}
            for m, t in (("sunsky", 0.5), ("sunsky" + FIT_SUFFIX, 2.0), ("uniform sky", 0.0))]
    table = summary_table(rows)
    order = [line.split("|")[1].strip() for line in table.splitlines()[2:]]
    assert order == ["uniform sky", "sunsky" + FIT_SUFFIX, "sunsky"]
    assert "| 2 |" in table.splitlines()[3]
    assert is_truth_fit("ae" + MOVED_SUFFIX) and not is_truth_fit("ae (true geometry)")


def test_a_run_that_diverges_returns_its_last_finite_point():
    """An objective that overflows past x = 1 (as a decoder can): L-BFGS's first step toward the
    minimum at 3 lands there; the result is the last finite point, not NaN."""

    def objective(x):
        return torch.where(x < 1.0, (x - 3.0) ** 2, torch.full_like(x, math.inf)).sum(-1)

    x, _ = minimise_restarted(objective, torch.zeros(1, 1, dtype=torch.float64), 50, 1e-10)
    assert torch.isfinite(x).all() and float(x) < 1.0
    # a well-behaved objective is minimised as before
    x, _ = minimise_restarted(lambda x: ((x - 0.5) ** 2).sum(-1), torch.zeros(1, 1, dtype=torch.float64), 50, 1e-10)
    assert abs(float(x) - 0.5) < 1e-6


def test_a_start_whose_intensity_overflows_gives_a_finite_fit(truth):
    """A start with the sun 1e300 × the probe (its log past any float's exp): the fit clamps the log
    intensity, never hands the model a non-finite parameter, and returns a finite fit."""
    from f2l.prior.probe_fit import fit_probe

    model = SunSky(GRID)
    start = TRUE.copy()
    start[3:6] = 1e300
    fit = fit_probe(truth, model, starts=start[None], max_iter=30)
    assert np.isfinite(fit.params).all() and np.isfinite(fit.probe).all() and math.isfinite(fit.loss)
