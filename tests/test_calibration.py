"""Calibration of the estimates' sun cones and the risk–coverage curve (f2l.evaluation.calibration),
in the eval-real report and in ``f2l report``, on hand-made rows with hand-computed answers."""

import csv
import doctest
import math

import numpy as np
import pytest

import f2l.evaluation.calibration as cal
import f2l.metrics.calibration as metrics_cal


def rows_of(triples, method="sunsky"):
    return [{"method": method, "Sun-ang (°)": a, "sun_cone68_deg": c68, "sun_cone90_deg": c90}
            for a, c68, c90 in triples]


# Sun-ang, 68% cone, 90% cone
HAND = [(2.0, 3.0, 5.0), (8.0, 4.0, 9.0), (30.0, 10.0, 20.0), (5.0, 6.0, 12.0), (12.0, 15.0, 25.0)]


def test_doctests():
    result = doctest.testmod(metrics_cal)
    assert result.attempted >= 2 and result.failed == 0


def test_cone_coverage_counts_the_true_suns_inside_each_cone():
    cov = cal.cone_coverage(rows_of(HAND))
    # inside 68%: 2 <= 3, 5 <= 6, 12 <= 15 -> 3 of 5; inside 90%: all but 30 > 20 -> 4 of 5
    assert cov == {"n": 5, "inside 68%": pytest.approx(0.6), "inside 90%": pytest.approx(0.8)}


def test_rows_without_a_cone_or_a_sun_are_left_out():
    rows = rows_of(HAND) + rows_of([(math.nan, 3.0, 5.0), (4.0, None, None)]) + [{"Sun-ang (°)": "1.0"}]
    assert cal.cone_coverage(rows)["n"] == 5
    assert math.isnan(cal.cone_coverage([])["inside 90%"])


def test_risk_coverage_keeps_the_narrowest_cones_first():
    curve = cal.risk_coverage(rows_of(HAND))
    # sorted by 90% cone: 5 (2°), 9 (8°), 12 (5°), 20 (30°), 25 (12°)
    # keep ceil(f 5) = 5, 4, 3, 2 faces: means 57/5, 45/4, 15/3, 10/2
    assert curve == [(1.0, 5, pytest.approx(11.4)), (0.75, 4, pytest.approx(11.25)), (0.5, 3, pytest.approx(5.0)),
                     (0.25, 2, pytest.approx(5.0))]


def test_calibration_table_has_one_line_per_method_with_the_hand_numbers():
    rows = rows_of(HAND) + rows_of([(1.0, 2.0, 4.0), (50.0, 5.0, 10.0)], method="ae")
    for r, mae, pred in zip(rows, (0.1, 0.2, 0.5, 0.15, 0.3, 0.1, 0.4), (0.12, 0.18, 0.4, 0.2, 0.25, 0.1, 0.3)):
        r["MAE (s)"], r["predicted_mae_s"] = mae, pred
    lines = cal.calibration_table(rows).splitlines()
    assert len(lines) == 4 and lines[2].startswith("| ae | 2 | 50% | 50% | 3.5 / 7 |")
    assert lines[3].startswith("| sunsky | 5 | 60% | 80% | 6 / 12 | 11.4 | 11.2 | 5 | 5 |")
    # predicted 0.23 / measured 0.25 on average; ranks (1, 2, 5, 3, 4) against (1, 3, 5, 2, 4): rho = 1 - 6 * 2 / 120 = 0.9
    assert lines[3].endswith("| 0.23 / 0.25 | 0.9 |")
    assert lines[2].endswith("| — | — |")  # fewer than 3 pairs


def test_fit_mae_model_recovers_a_linear_law():
    rng = np.random.default_rng(0)
    x = np.column_stack([np.ones(20), rng.random(20), rng.random(20)])
    assert cal.fit_mae_model(x, x @ [0.1, 0.3, -0.05]) == pytest.approx([0.1, 0.3, -0.05])


def eval_rows():
    rows = []
    for split, shift in (("report", 0.0), ("tune", 1.0)):
        for i, (a, c68, c90) in enumerate(HAND):
            rows.append({"method": "sunsky", "case": f"c{i}", "split": split, "sky_kind": "clear",
                         "Sun-ang (°)": a + shift, "sun_cone68_deg": c68, "sun_cone90_deg": c90,
                         "MAE (s)": 0.1, "predicted_mae_s": 0.1})
        rows.append({"method": "uniform sky", "case": "c0", "split": split, "sky_kind": "clear", "Sun-ang (°)": 9.0,
                     "sun_cone68_deg": math.nan, "sun_cone90_deg": math.nan})
        rows.append({"method": "sunsky", "case": "o", "split": split, "sky_kind": "overcast", "Sun-ang (°)": math.nan,
                     "sun_cone68_deg": 50.0, "sun_cone90_deg": 90.0})
    return rows


def test_the_eval_real_report_has_a_calibration_section_per_part_and_the_plot(tmp_path):
    from f2l.evaluation.eval_report import calibration_section

    text = calibration_section(eval_rows(), tmp_path)
    assert "reporting part" in text and "tuning part" in text
    assert "| sunsky | 5 | 60% | 80% |" in text and "uniform sky" not in text
    assert (tmp_path / "eval_real_risk_coverage.png").stat().st_size > 1000
    assert calibration_section([r for r in eval_rows() if r["method"] == "uniform sky"], tmp_path) == ""


def test_f2l_report_shows_the_calibration_and_each_faces_cones(tmp_path):
    from f2l.estimate.record import _base_row
    from f2l.io.tables import rows_to_table, write_table_atomic
    from f2l.report.build import write_report

    est = tmp_path / "estimates"
    est.mkdir()
    rows = []
    for i, (a, c68, c90) in enumerate(HAND):
        row = _base_row({"face_id": f"f{i}", "source_path": "x.png", "grid_height": 8, "grid_width": 16}, "sunsky")
        row.update(sun_cone68_deg=c68, sun_cone90_deg=c90, predicted_mae_s=0.1 + i / 100)
        rows.append(row)
    write_table_atomic(rows_to_table(rows, "estimates"), est / "estimates.parquet", "estimates")
    with open(est / "metrics_per_face.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["model", "face_id", "Sun-ang (°)", "runtime_s"])
        w.writeheader()
        w.writerows({"model": "sunsky", "face_id": f"f{i}", "Sun-ang (°)": a, "runtime_s": 1.0}
                    for i, (a, _, _) in enumerate(HAND))
    from f2l.metrics import METRIC_NAMES

    with open(est / "metrics_summary.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["model", "n", "runtime_s mean", *[f"{m} mean" for m in METRIC_NAMES]])
        w.writeheader()
        w.writerow({"model": "sunsky", "n": 5, "runtime_s mean": 1.0, **{f"{m} mean": 0.1 for m in METRIC_NAMES}})
    write_report(tmp_path)
    page = (tmp_path / "report.html").read_text()
    assert 'id="calibration-table"' in page
    assert "<td>60%</td><td>80%</td><td>11.4</td><td>11.25</td><td>5</td><td>5</td>" in page
    assert (tmp_path / "report_files" / "risk_coverage.png").is_file()
