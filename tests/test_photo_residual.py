"""`f2l eval-real`'s photo residual: how well a probe explains a face through its own transport."""

from types import SimpleNamespace

import numpy as np
import pytest

from f2l.lighting.grid import LatLongGrid, rotate_y
from f2l.evaluation.eval_report import residual_table
from f2l.evaluation.photo_residual import IDEAL_PEAK, PhotoResidual, best_scale_l1, ideal_photo, photo_residual
from f2l.synth.render import make_synthetic_set

GRID = LatLongGrid(32, 64)


def test_the_l1_scale_is_exact_for_a_scaled_copy_and_ignores_a_few_gross_outliers():
    rng = np.random.default_rng(0)
    s = rng.uniform(0.1, 1.0, 400)
    assert best_scale_l1(2.5 * s, s) == pytest.approx(2.5)
    o = 2.5 * s
    o[:30] *= 8.0  # 7% of the pixels wildly off (a highlight, a misfit shadow)
    assert best_scale_l1(o, s) == pytest.approx(2.5)
    assert best_scale_l1(o, np.zeros_like(s)) == 0.0


def test_the_residual_is_zero_for_the_shading_itself_and_scale_invariant_per_channel():
    rng = np.random.default_rng(1)
    shading = rng.uniform(0.05, 2.0, (300, 3))
    observed = shading * np.array([0.4, 0.25, 0.15])
    assert photo_residual(observed, shading) == pytest.approx(0.0, abs=1e-12)
    noisy = observed * (1.0 + 0.05 * rng.standard_normal(observed.shape))
    r = photo_residual(noisy, shading)
    assert 0.02 < r < 0.06  # ~ mean |N(0, 0.05)| = 0.04
    assert photo_residual(noisy, 7.0 * shading) == pytest.approx(r)
    assert np.isnan(photo_residual(np.zeros_like(observed), shading))


@pytest.fixture(scope="module")
def face():
    f = next(iter(make_synthetic_set(1, GRID, seed=3, image_size=96, overcast_fraction=0.0, threads=1)))
    record = SimpleNamespace(face_id="f0", grid_height=GRID.height, grid_width=GRID.width, normals=f.normals,
                             observed_rgb=f.observed_rgb, mask=f.mask, visibility_bits=f.visibility_bits)
    return record, np.asarray(f.gt_probe, np.float64), f.meta


def test_the_true_probe_explains_an_own_render_better_than_the_same_sky_turned_away(face):
    record, truth, meta = face
    fit = PhotoResidual(record)
    r_truth = fit.residual(truth)
    assert r_truth < 0.03  # own forward model: only the render's noise and 8-bit rounding are left
    for angle_deg in (60.0, 120.0, 180.0):
        turned = rotate_y(truth, np.radians(angle_deg))
        assert fit.residual(turned) > r_truth + 0.05
    assert fit.residual(3.0 * truth) == pytest.approx(r_truth)
    with pytest.raises(ValueError, match="grid"):
        fit.residual(np.ones((8, 16, 3)))


def test_the_ideal_photo_is_the_forward_model_of_the_probe_with_the_photos_skin_colour(face):
    """ideal_photo = k ⊙ T l at one exposure: for an own render (the same forward model plus noise
    and 8-bit rounding) it is the photo itself up to that exposure; under another probe the truth no
    longer explains it, the other probe does exactly; its brightest masked pixel is IDEAL_PEAK."""
    record, truth, _ = face
    mask = np.asarray(record.mask, bool)
    ideal = ideal_photo(record, truth, threads=1)
    assert ideal.dtype == np.float32 and ideal.shape == record.observed_rgb.shape
    assert ideal[mask].max() == pytest.approx(IDEAL_PEAK, rel=1e-6)
    observed = np.asarray(record.observed_rgb, np.float64)
    lit = mask & (observed > 0.05).all(1) & (observed < 0.9).all(1)
    ratio = ideal[lit] / observed[lit]
    scale = np.median(ratio)
    assert np.median(np.abs(ratio / scale - 1.0)) < 0.03  # per channel: the skin's colour is kept
    assert photo_residual(ideal[mask], PhotoResidual(record).transport.matmul(
        truth.reshape(-1, 3), dtype=np.float64)[np.flatnonzero(mask)]) < 1e-6
    turned = rotate_y(truth, np.radians(120.0))
    other = SimpleNamespace(**{**vars(record), "observed_rgb": ideal_photo(record, turned, threads=1)})
    fit = PhotoResidual(other)
    assert fit.residual(turned) < 1e-6 and fit.residual(truth) > 0.05
    with pytest.raises(ValueError, match="grid"):
        ideal_photo(record, np.ones((8, 16, 3)))
    with pytest.raises(ValueError, match="black"):
        ideal_photo(record, np.zeros_like(truth))


def test_the_table_counts_far_off_suns_that_fit_the_photo_as_well_as_the_truth():
    def row(method, ang, r_est, r_truth):
        return {"method": method, "split": "report", "sky_kind": "clear", "Sun-ang (°)": ang,
                "photo residual": r_est, "photo residual, truth": r_truth}

    rows = [row("sunsky", 40.0, 0.05, 0.06), row("sunsky", 30.0, 0.08, 0.06), row("sunsky", 10.0, 0.05, 0.05),
            row("sunsky", 20.0, 0.04, 0.04), row("uniform sky", 50.0, float("nan"), float("nan"))]
    table = residual_table(rows)
    # 3 far-off (> 15 deg); 2 of them (40 and 20 deg) fit as well as the truth: 60 of 100 summed degrees
    assert "| sunsky | 4 | " in table and "| 3 | 2 | 60% |" in table
    assert "uniform sky" not in table
