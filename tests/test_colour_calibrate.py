"""Batch calibration on real chart photos, colour.parquet and reports (f2l.colour.calibrate)."""

import json
from pathlib import Path

import colour
import numpy as np
import pyarrow.parquet as pq
import pytest
from PIL import Image

from f2l.colour.calibrate import calibrate, calibrate_photo, format_summary, read_corrections, summarise
from f2l.colour.chart import NEUTRAL_INDICES, render_chart_photo, rgb709_to_lab
from f2l.colour.detect import LUMA
from f2l.io.schema import table_errors

CHARTS = Path(__file__).parent / "data" / "colour_charts"
FIXTURES = ["classic_chair.jpg", "classic_fabric.jpg", "classic_wall.jpg"]


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    """The three real photos, a synthetic chart with 3 clipped patches, a photo without a chart, a corrupt file."""
    inputs = tmp_path_factory.mktemp("charts_in")
    paths = [CHARTS / name for name in FIXTURES]
    clipped = render_chart_photo(seed=31, clipped_patches=[19, 20, 21])
    Image.fromarray(clipped.display).save(inputs / "synthetic_clipped.png")
    rng = np.random.default_rng(1)
    smooth = np.kron(rng.random((6, 8, 3)), np.ones((40, 40, 1)))  # no chart in it
    Image.fromarray((smooth * 255).astype(np.uint8)).save(inputs / "no_chart.png")
    (inputs / "corrupt.jpg").write_bytes(b"\xff\xd8\xff\xe0 not really a jpeg")
    paths += [inputs / "synthetic_clipped.png", inputs / "no_chart.png", inputs / "corrupt.jpg"]
    out = tmp_path_factory.mktemp("calibrated")
    results = calibrate(paths, out, method="3x3")
    return {r.source_path: r for r in results}, out


def test_statuses_per_photo(batch):
    results, out = batch
    by_name = {Path(p).name: r for p, r in results.items()}
    assert by_name["no_chart.png"].status == "no_chart"
    assert "no ColorChecker Classic found" in by_name["no_chart.png"].reason
    assert by_name["corrupt.jpg"].status == "error" and "corrupt.jpg" in by_name["corrupt.jpg"].reason
    clipped = by_name["synthetic_clipped.png"]
    assert clipped.status == "partial"
    assert "3 patches excluded: 19 (clipped), 20 (clipped), 21 (clipped)" in clipped.reason
    assert clipped.fit.stats()["mean_delta_e_after"] <= 1.5
    for name in FIXTURES:
        assert by_name[name].status in ("ok", "partial"), by_name[name].reason
    summary = summarise(list(results.values()), out)
    assert summary["photos"] == 6 and summary["status"]["no_chart"] == 1 and summary["status"]["error"] == 1
    text = format_summary(summary)
    assert text.count("\n| ") == 6 and "no_chart: " in text  # one row per photo


@pytest.mark.parametrize("name", FIXTURES)
def test_real_photos_locate_all_patches_in_order(batch, name):
    results, _ = batch
    result = results[str(CHARTS / name)]
    detection, fit = result.detection, result.fit
    height, width = Image.open(CHARTS / name).size[::-1]
    # all 24 patches located inside the photo, most of them usable
    assert detection.patch_polygons.shape == (24, 4, 2)
    assert (detection.patch_polygons >= 0).all()
    assert (detection.patch_polygons[..., 0] < width).all() and (detection.patch_polygons[..., 1] < height).all()
    assert np.isfinite(detection.rgb).all() and fit.valid.sum() >= 22
    # neutral row: darker from white to black
    luminance = detection.rgb[list(NEUTRAL_INDICES)] @ LUMA
    assert np.all(np.diff(luminance) < 0)
    # patch order: every corrected patch is closest (ΔE2000) to its own reference patch ...
    lab = rgb709_to_lab(fit.corrected_rgb)
    distances = colour.delta_E(lab[:, None, :], fit.reference.lab[None, :, :], method="CIE 2000")
    np.testing.assert_array_equal(distances.argmin(axis=1), np.arange(24))
    # ... and chromatic patches keep their hue
    ref_chroma = np.hypot(fit.reference.lab[:, 1], fit.reference.lab[:, 2])
    hue = np.degrees(np.arctan2(lab[:, 2], lab[:, 1]))
    ref_hue = np.degrees(np.arctan2(fit.reference.lab[:, 2], fit.reference.lab[:, 1]))
    hue_error = np.abs((hue - ref_hue + 180) % 360 - 180)
    assert hue_error[ref_chroma > 20].max() < 25
    stats = fit.stats()
    assert stats["mean_delta_e_after"] < stats["mean_delta_e_before"]
    assert stats["mean_delta_e_after"] < 3.5


def test_colour_table_conforms_to_schema(batch):
    results, out = batch
    table = pq.read_table(out / "colour.parquet")
    assert table.num_rows == 6
    assert table_errors(table, "colour", str(out / "colour.parquet")) == []
    rows = {r["source_path"]: r for r in table.to_pylist()}
    clipped = next(r for p, r in rows.items() if p.endswith("synthetic_clipped.png"))
    assert clipped["n_valid_patches"] == 21 and clipped["method"] == "Cheung 2004"
    assert [e["patch"] for e in json.loads(clipped["excluded_json"])] == [19, 20, 21]
    assert len(json.loads(clipped["patches_json"])) == 24 and len(clipped["matrix"]) == 9
    failed = next(r for p, r in rows.items() if p.endswith("no_chart.png"))
    assert failed["method"] == "identity" and failed["mean_delta_e_after"] is None
    corrections = read_corrections(out / "colour.parquet")
    assert corrections[failed["source_path"]].is_identity
    assert not corrections[clipped["source_path"]].is_identity


def test_reports_written(batch):
    results, out = batch
    result = results[str(CHARTS / "classic_wall.jpg")]
    png = Image.open(out / result.report_png)
    assert png.format == "PNG" and png.size[0] > 500
    table = (out / result.report_table).read_text(encoding="utf-8")
    assert "| 24 | black 2 (1.5 D) |" in table and "| mean (used patches) |" in table
    assert not list(out.rglob("*.tmp"))


def test_root_polynomial_and_bad_arguments(tmp_path):
    results = calibrate([CHARTS / "classic_wall.jpg"], tmp_path, method="root-polynomial", reports=False)
    assert results[0].correction.method == "Finlayson 2015" and results[0].report_png is None
    assert results[0].correction.matrix.shape == (3, 6)
    with pytest.raises(ValueError, match="unknown colour-correction method"):
        calibrate([CHARTS / "classic_wall.jpg"], tmp_path, method="lut")
    with pytest.raises(ValueError, match="unknown 24-patch"):
        calibrate([CHARTS / "classic_wall.jpg"], tmp_path, edition="nope")


def test_overexposed_neutral_row_gives_identity_status():
    photo = render_chart_photo(seed=32, clipped_patches=list(range(19, 25)))
    status, reason, detection, fit = calibrate_photo(photo.display, photo.linear, clipped=photo.clipped,
                                                     source="over.png")
    assert detection is not None and [n for n, _ in detection.excluded] == list(range(19, 25))
    assert status == "identity" and fit.correction.is_identity
    assert reason.startswith("over.png: identity correction") and "0 valid neutral patches" in reason
