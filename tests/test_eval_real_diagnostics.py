"""`f2l eval-real` diagnostics: the light's colour, MAE (s) once the colour is right, the sun's share."""

import numpy as np
import pytest

from f2l.lighting.grid import LatLongGrid, direction_from_angles
from f2l.metrics import rendering_metrics
from f2l.evaluation.eval_report import diagnostics_table
from f2l.evaluation.evaluate import DIAGNOSTIC_NAMES, diagnostics

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
    # the gain is applied to the float32 rendering (the scene is linear in the probe): float32 exact
    assert d["MAE (s), colour matched"] == pytest.approx(0.0, abs=1e-5)


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


def test_the_elevation_error_has_the_sign_of_the_estimates_lean():
    truth = _sky_with_sun()
    higher = direction_from_angles(np.radians(50.0), 0.7)
    d = diagnostics(truth, truth, GRID, SUN, est_sun_direction=higher)
    assert d["sun elevation error (°)"] == pytest.approx(10.0, abs=1e-9)
    lower = direction_from_angles(np.radians(25.0), 0.7)
    assert diagnostics(truth, truth, GRID, SUN, est_sun_direction=lower)["sun elevation error (°)"] == pytest.approx(-15.0)
    # without an explicit sun, the probe's own (the direction Sun-ang scores): within a texel here
    assert abs(diagnostics(truth, truth, GRID, SUN)["sun elevation error (°)"]) < 180.0 / GRID.height
    assert np.isnan(diagnostics(truth, truth, GRID, None)["sun elevation error (°)"])


def test_the_truth_without_its_sun_disk_differs_from_the_truth_only_in_the_disk():
    from f2l.metrics import evaluate_pair
    from f2l.metrics.lighting import cap_mask
    from f2l.evaluation.evaluate import baseline_probes, sun_disk_radius_deg, without_sun_disk

    assert sun_disk_radius_deg(LatLongGrid(64, 128)) == pytest.approx(0.27 + 2.8125 / np.sqrt(2.0))
    truth = _sky_with_sun()
    probe = baseline_probes(truth, GRID, SUN)["truth without its sun disk"]
    disk = cap_mask(GRID, SUN, sun_disk_radius_deg(GRID))
    row, col = GRID.direction_to_texel(SUN)
    assert disk[int(row), int(col)]  # the texel that holds the sun is in the disk
    np.testing.assert_array_equal(probe[~disk], truth[~disk])
    np.testing.assert_allclose(probe[disk], np.broadcast_to([0.5, 0.7, 1.0], probe[disk].shape))
    m = evaluate_pair(probe, truth, GRID, overcast=False, est_sun_dir=SUN, gt_sun_dir=SUN)
    assert m["Sun-dω MAE (l)"] > 0.1 and m["Full-dω MAE (l)"] > 0.0
    # overcast (no true sun): the truth itself
    np.testing.assert_array_equal(without_sun_disk(truth, GRID, None), truth)


def test_the_elevation_bias_table_splits_sky_sources_and_bands_and_leaves_out_baselines():
    from f2l.evaluation.eval_report import elevation_bias_table

    def row(method, source, elevation, error, angle):
        return {"method": method, "split": "report", "sky_kind": "clear", "source": source,
                "sun_elevation_deg": elevation, "sun elevation error (°)": error, "Sun-ang (°)": angle}

    rows = [row("sunsky", "sunsky", 30.0, 2.0, 5.0), row("sunsky", "sunsky", 40.0, 4.0, 7.0),
            row("sunsky", "park", 10.0, 13.0, 20.0), row("sunsky", "bridge", 88.0, -20.0, 30.0),
            row("uniform sky", "sunsky", 30.0, 9.0, 40.0),
            {**row("sunsky", "sunsky", 30.0, 50.0, 50.0), "split": "tune"}]
    table = elevation_bias_table(rows)
    line = next(x for x in table.splitlines() if x.startswith("| sunsky |"))
    cells = [c.strip() for c in line.strip("|").split("|")][1:]
    assert cells[1] == "+3.0° / 6° (2)"  # Hosek–Wilkie 15–45°: the tuning row is left out
    assert cells[4] == "+13.0° / 20° (1)" and cells[7] == "-20.0° / 30° (1)"
    assert cells[0] == "—" and "uniform sky" not in table


def _sky_with_lobe(sun, grid=GRID, kappa=3000.0, energy=40.0):
    """A blue-ish sky gradient plus a vMF sun lobe of ``energy`` per channel × (1, 0.9, 0.8)."""
    d = grid.directions
    probe = np.zeros(grid.shape + (3,))
    probe[: grid.sky_rows] = np.array([0.5, 0.7, 1.0]) * (1.0 + 0.5 * d[: grid.sky_rows, :, 1:2])
    lobe = np.exp(kappa * (d @ sun - 1.0))
    lobe /= (lobe * grid.solid_angles).sum()
    return probe + energy * lobe[..., None] * np.array([1.0, 0.9, 0.8])


def test_moving_a_sun_onto_itself_or_back_changes_little_and_keeps_its_energy():
    from f2l.evaluation.evaluate import sun_disk_radius_deg, sun_moved

    grid = LatLongGrid(64, 128)
    other = direction_from_angles(np.radians(15.0), -2.0)
    probe = _sky_with_lobe(SUN, grid)
    weights = (grid.solid_angles * grid.upper_mask)[..., None]
    moved = sun_moved(probe, grid, SUN, other)
    # the upper hemisphere's energy, per channel, is kept
    np.testing.assert_allclose((moved * weights).sum((0, 1)), (probe * weights).sum((0, 1)), rtol=1e-12)
    # the sun is now in the true sun's disk, and its old place holds only sky
    from f2l.metrics.lighting import cap_mask
    disk = cap_mask(grid, other, sun_disk_radius_deg(grid))
    old = cap_mask(grid, SUN, 4.0)
    assert (moved[disk] * grid.solid_angles[disk][:, None]).sum(0)[0] > 0.95 * 40.0
    assert moved[old].max() < 2.0 and probe[old].max() > 100.0
    # moved back, the metrics are the original's within the disk's spread
    from f2l.metrics import rendering_metrics
    back = sun_moved(moved, grid, other, SUN)
    assert rendering_metrics(back, probe, grid)["MAE (s)"] < 0.01
    # a sky with no sun is left as it is (nothing above the ring's median moves)
    sky = _sky_with_lobe(SUN, grid, energy=0.0)
    assert np.abs(sun_moved(sky, grid, SUN, other) - sky).max() < 0.05


def test_the_sun_at_the_truth_removes_a_misplaced_suns_error_but_not_a_colour_cast():
    grid = LatLongGrid(64, 128)
    truth = _sky_with_lobe(SUN, grid)
    wrong = direction_from_angles(np.radians(70.0), 2.0)
    estimate = _sky_with_lobe(wrong, grid) * np.array([0.9, 1.0, 1.15])
    d = diagnostics(estimate, truth, grid, SUN, est_sun_direction=wrong)
    from f2l.metrics import evaluate_pair
    m = evaluate_pair(estimate, truth, grid, overcast=False, est_sun_dir=wrong, gt_sun_dir=SUN)
    assert m["MAE (s)"] > 0.1 and m["Full-dω MAE (l)"] > 0.05
    assert d["MAE (s), sun at the truth"] < 0.5 * m["MAE (s)"]
    assert d["Full-dω MAE (l), sun at the truth"] < 0.5 * m["Full-dω MAE (l)"]
    # the colour cast is still there after the move, and matching the colour removes most of the rest
    assert d["MAE (s), sun at the truth"] > 0.02
    assert d["MAE (s), sun at the truth, colour matched"] < 0.5 * d["MAE (s), sun at the truth"]
    # overcast, or a baseline (sun_at_truth=False): not scored
    assert np.isnan(diagnostics(estimate, truth, grid, None)["MAE (s), sun at the truth"])
    assert np.isnan(diagnostics(estimate, truth, grid, SUN, wrong, sun_at_truth=False)["Full-dω MAE (l), sun at the truth"])


def test_the_sun_direction_table_lists_estimates_on_clear_cases_only():
    from f2l.evaluation.eval_report import sun_direction_table

    grid = LatLongGrid(64, 128)
    truth = _sky_with_lobe(SUN, grid)
    d = diagnostics(truth, truth, grid, SUN, SUN)
    base = {"split": "report", "sky_kind": "clear", "Sun-ang (°)": 0.0, "MAE (s)": 0.0, "Full-dω MAE (l)": 0.0, **d}
    rows = [{**base, "method": "sunsky"}, {**base, "method": "uniform sky"},
            {**base, "method": "sunsky", "sky_kind": "overcast", "MAE (s)": 9.0}]
    table = sun_direction_table(rows)
    assert "uniform sky" not in table
    line = next(x for x in table.splitlines() if x.startswith("| sunsky |"))
    assert line.startswith("| sunsky | 1 | 0 | 0 |")
