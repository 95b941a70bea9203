"""Reference ColorChecker values and the synthetic chart renderer (f2l.colour.chart)."""

import numpy as np
import pytest

from f2l.colour.chart import (DEFAULT_EDITION, NEUTRAL_INDICES, apply_homography, editions, reference_chart,
                              render_chart_photo, rgb709_to_lab, srgb_encode_uint8)


def test_reference_chart_is_linear_rec709_d65():
    ref = reference_chart()
    assert ref.edition == DEFAULT_EDITION
    assert ref.rgb.shape == (24, 3) and ref.lab.shape == (24, 3)
    assert ref.names[0] == "dark skin" and ref.names[18].startswith("white")
    neutral = ref.rgb[list(NEUTRAL_INDICES)]
    # Bradford-adapted to D65: the neutral row is (nearly) neutral in Rec.709, white → black
    assert np.all(np.abs(neutral / neutral.mean(axis=1, keepdims=True) - 1) < 0.06)
    assert np.all(np.diff(neutral.mean(axis=1)) < 0)
    assert 0.8 < neutral[0].mean() < 0.95 and neutral[-1].mean() < 0.05
    np.testing.assert_allclose(rgb709_to_lab(ref.rgb), ref.lab, atol=1e-6)
    assert ref.rgb[17, 0] < 0  # cyan is outside the Rec.709 gamut; kept negative


def test_editions_differ_and_unknown_edition_raises():
    assert "ColorChecker24 - Before November 2014" in editions()
    before = reference_chart("ColorChecker24 - Before November 2014")
    after = reference_chart("ColorChecker24 - After November 2014")
    assert np.abs(before.rgb - after.rgb).max() > 1e-3
    with pytest.raises(ValueError, match="unknown 24-patch"):
        reference_chart("ColorCheckerSG - After November 2014")


def test_noiseless_render_matches_camera_model():
    matrix = np.array([[0.7, 0.2, 0.1], [0.1, 0.8, 0.1], [0.05, 0.15, 0.6]])
    photo = render_chart_photo(matrix, exposure=0.9, noise_sigma=0.0, vignetting=0.0, size=(240, 360), seed=1)
    assert photo.linear.shape == (240, 360, 3) and photo.linear.dtype == np.float32
    assert photo.display.dtype == np.uint8
    np.testing.assert_array_equal(photo.display, srgb_encode_uint8(photo.linear))
    expected = 0.9 * photo.reference.rgb @ matrix.T
    np.testing.assert_allclose(photo.patch_camera_rgb, expected, rtol=1e-9)
    centres = np.round(photo.patch_polygons.mean(axis=1)).astype(int)
    sampled = photo.linear[centres[:, 1], centres[:, 0]]
    np.testing.assert_allclose(sampled, np.clip(expected, 0, 1), atol=1e-5)
    # polygons are the homography images of the canonical squares, inside the picture
    assert (photo.patch_polygons >= 0).all() and (photo.patch_polygons[..., 0] < 360).all()
    np.testing.assert_allclose(apply_homography(photo.homography, np.zeros((1, 2)))[0],
                               photo.patch_polygons[0].min(axis=0), atol=10)


def test_render_is_deterministic_and_clips_requested_patches():
    a = render_chart_photo(seed=5, size=(240, 360), clipped_patches=[19, 5])
    b = render_chart_photo(seed=5, size=(240, 360), clipped_patches=[19, 5])
    np.testing.assert_array_equal(a.linear, b.linear)
    for number in (19, 5):
        centre = np.round(a.patch_polygons[number - 1].mean(axis=0)).astype(int)
        assert (a.linear[centre[1], centre[0]] == 1.0).all()
        assert a.clipped[centre[1], centre[0]]
    centre = np.round(a.patch_polygons[20].mean(axis=0)).astype(int)
    assert (a.linear[centre[1], centre[0]] < 1.0).all()
