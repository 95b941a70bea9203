"""Chart detection (OpenCV mcc) and patch measurement on the linear image (f2l.colour.detect)."""

import numpy as np
import pytest

from f2l.colour import detect as detect_module
from f2l.colour.chart import render_chart_photo, srgb_encode_uint8
from f2l.colour.detect import detect_chart

CAMERA = np.array([[0.62, 0.28, 0.06], [0.14, 0.78, 0.14], [0.02, 0.22, 0.52]])  # cross-talk + green cast
CORNERS = np.array([[150.0, 120.0], [560.0, 95.0], [590.0, 380.0], [130.0, 350.0]])  # perspective warp


def _pitch_px(photo) -> float:
    side = np.linalg.norm(photo.patch_polygons[:, 1] - photo.patch_polygons[:, 0], axis=1)
    return float(side.mean() / 0.84)


@pytest.fixture(scope="module")
def photo():
    return render_chart_photo(CAMERA, exposure=0.85, noise_sigma=0.004, vignetting=0.1, corners=CORNERS,
                              size=(480, 720), seed=11)


@pytest.fixture(scope="module")
def detection(photo):
    return detect_chart(photo.display, photo.linear, clipped=photo.clipped)


def test_synthetic_chart_detected_with_all_patches(photo, detection):
    assert detection is not None
    assert detection.variant == "display"
    assert detection.valid.all() and detection.excluded == []
    centre_error = np.linalg.norm(detection.patch_centres - photo.patch_polygons.mean(axis=1), axis=1)
    assert centre_error.max() < 0.1 * _pitch_px(photo)
    # the median of the inner region recovers the camera value (noise, vignetting within a patch: < 3 %)
    np.testing.assert_allclose(detection.rgb, photo.patch_camera_rgb, rtol=0.03, atol=0.003)
    assert (detection.n_pixels > 100).all()
    assert np.all(detection.spread < detect_module.SPREAD_LIMIT)


def test_clipped_patches_are_excluded_with_reason():
    photo = render_chart_photo(CAMERA, corners=CORNERS, seed=12, clipped_patches=[19, 20, 21])
    found = detect_chart(photo.display, photo.linear, clipped=photo.clipped)
    assert found is not None
    assert found.excluded == [(19, "clipped"), (20, "clipped"), (21, "clipped")]
    # without the clipped mask, the 0.98 × clip-level rule alone finds them
    found = detect_chart(photo.display, photo.linear)
    assert [n for n, _ in found.excluded] == [19, 20, 21]


def test_shadow_edge_makes_patch_nonuniform():
    photo = render_chart_photo(CAMERA, corners=CORNERS, seed=13)
    linear = photo.linear.copy()
    x0, y0 = photo.patch_polygons[6].min(axis=0).astype(int)
    x1, y1 = photo.patch_polygons[6].max(axis=0).astype(int)
    linear[y0:y1, (x0 + x1) // 2:x1] *= 0.5  # a shadow over half of patch 7
    found = detect_chart(srgb_encode_uint8(linear), linear)
    assert found is not None
    assert found.excluded == [(7, "nonuniform")]


def test_photo_without_chart_returns_none_with_log():
    data = pytest.importorskip("skimage.data")
    display = np.ascontiguousarray(data.astronaut()[::2, ::2])
    linear = (display / 255.0).astype(np.float32) ** 2.2
    log = []
    assert detect_chart(display, linear, log=log) is None
    assert [line.split(":")[0] for line in log] == list(detect_module.VARIANTS)
    assert all("no chart" in line for line in log)


def test_grid_of_random_colours_rejected_as_implausible():
    rng = np.random.default_rng(0)
    coarse = rng.random((12, 16, 3)).astype(np.float32) ** 2  # chart-like squares, no neutral row
    texture = np.repeat(np.repeat(coarse, 20, axis=0), 20, axis=1)
    log = []
    assert detect_chart(srgb_encode_uint8(texture), texture, log=log) is None
    assert any("neutral row not ordered" in line for line in log)


def test_dark_photo_found_on_exposure_normalised_variant():
    photo = render_chart_photo(CAMERA, corners=CORNERS, seed=14, noise_sigma=0.0)
    linear = photo.linear * 0.02  # badly underexposed: mcc fails on its sRGB encoding
    log = []
    found = detect_chart(srgb_encode_uint8(linear), linear, log=log)
    assert found is not None and found.variant != "display"
    assert log[0] == "display: mcc found no chart"
    assert found.valid.sum() == 24


def test_patch_order_rotated_when_mcc_reports_it_upside_down(photo, monkeypatch):
    real = detect_module._mcc_quads

    def reversed_quads(image):
        quads, cost = real(image)
        return quads[::-1].copy(), cost

    monkeypatch.setattr(detect_module, "_mcc_quads", reversed_quads)
    found = detect_chart(photo.display, photo.linear)
    assert found is not None and found.rotated
    centre_error = np.linalg.norm(found.patch_centres - photo.patch_polygons.mean(axis=1), axis=1)
    assert centre_error.max() < 0.1 * _pitch_px(photo)


def test_size_mismatch_raises(photo):
    with pytest.raises(ValueError, match="differ in size"):
        detect_chart(photo.display[:100], photo.linear)
