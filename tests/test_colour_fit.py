"""Colour-correction fitting, ΔE2000 and apply_correction (f2l.colour.fit)."""

import numpy as np
import pytest

from f2l.colour.chart import reference_chart, render_chart_photo
from f2l.colour.detect import detect_chart
from f2l.colour.fit import ColourCorrection, apply_correction, fit_correction, resolve_method

CAMERA = np.array([[0.62, 0.28, 0.06], [0.14, 0.78, 0.14], [0.02, 0.22, 0.52]])  # cross-talk + green cast
CORNERS = np.array([[150.0, 120.0], [560.0, 95.0], [590.0, 380.0], [130.0, 350.0]])


@pytest.fixture(scope="module")
def detection():
    photo = render_chart_photo(CAMERA, exposure=0.85, noise_sigma=0.004, vignetting=0.1, corners=CORNERS,
                               size=(480, 720), seed=21)
    found = detect_chart(photo.display, photo.linear, clipped=photo.clipped)
    assert found is not None and found.valid.all()
    return found


@pytest.mark.parametrize("method", ["3x3", "root-polynomial"])
def test_synthetic_chart_corrected_below_one_delta_e(detection, method):
    fit = fit_correction(detection.rgb, detection.valid, method=method)
    stats = fit.stats()
    assert fit.status == "ok" and fit.correction.method == resolve_method(method)
    assert fit.correction.matrix.shape == (3, 3 if method == "3x3" else 6)
    assert stats["mean_delta_e_after"] <= 1.0
    assert stats["max_delta_e_after"] <= 2.5
    # white balance + exposure alone leave the cross-talk: the matrix must improve a lot on that
    assert stats["mean_delta_e_before"] > 3.0
    # the neutral row is right after the gains alone
    assert np.nanmax(fit.delta_e_before[18:23]) < 2.0


def test_exact_camera_values_recover_inverse_camera_matrix():
    ref = reference_chart()
    measured = 0.6 * ref.rgb @ CAMERA.T
    fit = fit_correction(measured, method="3x3")
    composed = fit.correction.matrix @ np.diag(fit.correction.gains)
    np.testing.assert_allclose(composed, np.linalg.inv(0.6 * CAMERA), rtol=1e-6, atol=1e-8)
    assert fit.stats()["max_delta_e_after"] < 1e-4
    # exposure_gain: corrected luminance per unit camera green on the neutrals
    neutral_camera = measured[18:24]
    lum = ref.rgb[18:24] @ [0.2126, 0.7152, 0.0722]
    expected = np.sum(lum * neutral_camera[:, 1]) / np.sum(neutral_camera[:, 1] ** 2)
    assert fit.correction.exposure_gain == pytest.approx(expected, rel=1e-6)


def test_three_clipped_patches_still_give_a_valid_correction():
    photo = render_chart_photo(CAMERA, exposure=0.85, noise_sigma=0.004, vignetting=0.1, corners=CORNERS, seed=22,
                               clipped_patches=[19, 20, 21])
    found = detect_chart(photo.display, photo.linear, clipped=photo.clipped)
    assert [n for n, _ in found.excluded] == [19, 20, 21]
    fit = fit_correction(found.rgb, found.valid)
    assert fit.status == "ok" and fit.valid.sum() == 21
    assert fit.stats()["mean_delta_e_after"] <= 1.5
    assert np.isnan(fit.delta_e_after[18:21]).sum() == 0  # excluded patches are still reported


def test_too_few_patches_or_no_neutral_row_gives_identity(detection):
    few = np.zeros(24, bool)
    few[[0, 5, 10, 18, 20]] = True
    fit = fit_correction(detection.rgb, few)
    assert fit.status == "identity" and fit.correction.is_identity
    assert "5 valid patches" in fit.reason
    no_neutral = np.ones(24, bool)
    no_neutral[18:24] = False
    fit = fit_correction(detection.rgb, no_neutral)
    assert fit.status == "identity" and "0 valid neutral patches" in fit.reason
    # root-polynomial needs more patches than 3x3
    eight = np.zeros(24, bool)
    eight[[0, 2, 4, 6, 8, 18, 20, 22]] = True
    assert fit_correction(detection.rgb, eight, method="3x3").status == "ok"
    assert fit_correction(detection.rgb, eight, method="root-polynomial").status == "identity"
    # nothing measurable at all: still no exception
    fit = fit_correction(np.full((24, 3), np.nan))
    assert fit.status == "identity" and np.isnan(fit.delta_e_after).all()
    assert np.isnan(fit.stats()["mean_delta_e_after"])


@pytest.mark.parametrize("method", ["3x3", "root-polynomial"])
def test_apply_correction_round_trip(detection, method):
    fit = fit_correction(detection.rgb, detection.valid, method=method)
    corr = fit.correction
    np.testing.assert_allclose(apply_correction(detection.rgb, corr), fit.corrected_rgb, rtol=1e-5, atol=1e-6)
    # an image: shape kept, float32, per-pixel identical to the patch mapping
    image = np.broadcast_to(detection.rgb[None, :, :], (5, 24, 3)).astype(np.float32)
    out = apply_correction(image, corr)
    assert out.shape == image.shape and out.dtype == np.float32
    np.testing.assert_allclose(out[3], fit.corrected_rgb, rtol=1e-4, atol=1e-5)
    # camera RGB of the reference chart maps back to the reference (the synthetic camera is linear)
    camera = 0.85 * fit.reference.rgb @ CAMERA.T
    np.testing.assert_allclose(apply_correction(camera, corr), fit.reference.rgb, atol=0.02)
    # colour only: the exposure gain divided out
    np.testing.assert_allclose(apply_correction(image, corr, keep_exposure=False), out / corr.exposure_gain,
                               rtol=1e-5)
    # serialisation round trip
    again = ColourCorrection.from_dict(corr.to_dict())
    np.testing.assert_array_equal(apply_correction(image, again), out)


def test_apply_identity_is_a_safe_copy():
    rgb = np.random.default_rng(0).random((4, 6, 3)).astype(np.float32)
    for corr in (None, ColourCorrection.identity()):
        out = apply_correction(rgb, corr)
        np.testing.assert_array_equal(out, rgb)
        assert out is not rgb
    with pytest.raises(ValueError, match="unknown colour-correction method"):
        resolve_method("vandermonde")
