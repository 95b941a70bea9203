"""`f2l eval-real` diagnostics: the light's colour, MAE (s) once the colour is right, the sun's share."""

import numpy as np
import pytest

from f2l.lighting.grid import LatLongGrid, direction_from_angles
from f2l.metrics import rendering_metrics
from f2l.render.evaluate import DIAGNOSTIC_NAMES, diagnostics, diagnostics_table

GRID = LatLongGrid(32, 64)
SUN = direction_from_angles(np.radians(40.0), 0.7)


def _sky_with_sun() -> np.ndarray:
    probe = np.zeros(GRID.shape + (3,))
    probe[: GRID.sky_rows] = [0.5, 0.7, 1.0]
    row, col = GRID.direction_to_texel(SUN)
    probe[int(row), int(col)] += np.array([1.0, 0.9, 0.8]) * 40.0 / GRID.solid_angles[int(row), int(col)]
    return probe


def test_the_truth_itself_has_no_colour_error_and_no_sun_share_error():
    truth = _sky_with_sun()
    d = diagnostics(truth, truth, GRID, SUN)
    assert d["colour R/G"] == pytest.approx(1.0) and d["colour B/G"] == pytest.approx(1.0)
    assert d["MAE (s), colour matched"] == pytest.approx(0.0, abs=1e-12)
    assert d["sun share"] == pytest.approx(0.0, abs=1e-12)


def test_a_colour_cast_is_measured_and_matching_the_colour_removes_its_error():
    truth = _sky_with_sun()
    cast = truth * np.array([0.8, 1.0, 1.25])
    d = diagnostics(cast, truth, GRID, SUN)
    assert d["colour R/G"] == pytest.approx(0.8) and d["colour B/G"] == pytest.approx(1.25)
    assert rendering_metrics(cast, truth, GRID)["MAE (s)"] > 0.02
    assert d["MAE (s), colour matched"] == pytest.approx(0.0, abs=1e-9)


def test_a_probe_without_the_sun_has_too_little_energy_in_the_sun_cap():
    truth = _sky_with_sun()
    sky_only = truth.copy()
    sky_only[: GRID.sky_rows] = [0.5, 0.7, 1.0]
    d = diagnostics(sky_only, truth, GRID, SUN)
    assert d["sun share"] < -0.3
    assert np.isnan(diagnostics(truth, truth, GRID, None)["sun share"])


def test_an_empty_estimate_gives_nan_not_an_error_and_the_table_lists_each_method():
    truth = _sky_with_sun()
    d = diagnostics(np.zeros_like(truth), truth, GRID, SUN)
    assert set(d) == set(DIAGNOSTIC_NAMES) and all(np.isnan(v) for v in d.values())
    rows = [{"method": m, "split": "report", "sky_kind": "clear", "MAE (s)": 0.2,
             **diagnostics(truth * [0.9, 1, 1.1], truth, GRID, SUN)} for m in ("sunsky", "ae")]
    table = diagnostics_table(rows)
    assert "| sunsky | 0.9 | 1.1 |" in table and "| ae |" in table
