"""Tests for f2l.io.preview (tone mapping, PNG, contact sheets)."""

from __future__ import annotations

import os

import numpy as np
import pytest
from PIL import Image

from f2l.io.preview import auto_exposure_scale, contact_sheet, probe_preview, save_png, tonemap


def _srgb_u8(v: float) -> int:
    """Reference sRGB OETF (IEC 61966-2-1), written out independently of colour-science."""
    e = 12.92 * v if v <= 0.0031308 else 1.055 * v ** (1 / 2.4) - 0.055
    return int(round(255 * e))


def test_dtype_shape_and_grayscale():
    hdr = np.random.default_rng(0).random((10, 20, 3)) * 100
    out = tonemap(hdr)
    assert out.dtype == np.uint8 and out.shape == (10, 20, 3)
    assert tonemap(hdr[:, :, 0]).shape == (10, 20, 3)
    with pytest.raises(ValueError):
        tonemap(np.zeros((4, 4, 2)))


@pytest.mark.parametrize("value", [1e-4, 0.5, 3.0, 5e6])
def test_constant_maps_to_srgb_of_0_8(value):
    out = tonemap(np.full((6, 8, 3), value))
    assert np.all(out == _srgb_u8(0.8)) and _srgb_u8(0.8) == 231


def test_percentile_mapping_and_exposure():
    # Luminance ramp 1..100 (grey): the 50th percentile (50.5) maps to 0.8.
    ramp = np.repeat(np.linspace(1.0, 100.0, 100)[None, :, None], 3, axis=2)
    assert auto_exposure_scale(ramp, 50.0) == pytest.approx(0.8 / 50.5)
    out = tonemap(ramp, percentile=50.0)
    assert out[0, 49, 0] == _srgb_u8(0.8 * 50 / 50.5) and out[0, 50, 0] == _srgb_u8(0.8 * 51 / 50.5)
    assert np.all(out[0, :60] < 255)
    assert np.all(out[0, 63:] == 255)  # above 1 / 0.8 * p: clipped
    # Fixed exposure: value 0.25 at +1 EV -> 0.5 linear.
    assert np.all(tonemap(np.full((2, 2, 3), 0.25), exposure_ev=1.0) == _srgb_u8(0.5))
    assert np.all(tonemap(np.full((2, 2, 3), 0.25), exposure_ev=-2.0) == _srgb_u8(0.0625))
    # Rec.709 luminance weights: pure green at 1 has luminance 0.7152.
    green = np.zeros((2, 2, 3))
    green[..., 1] = 1.0
    assert auto_exposure_scale(green) == pytest.approx(0.8 / 0.7152)


def test_monotonic():
    values = np.geomspace(1e-4, 1e3, 500)
    img = np.repeat(values[None, :, None], 3, axis=2)
    out = tonemap(img, exposure_ev=0.0)[0, :, 0].astype(int)
    assert np.all(np.diff(out) >= 0)
    assert out[0] < out[-1] == 255


def test_all_zero_nan_and_inf_safe():
    assert np.all(tonemap(np.zeros((4, 4, 3))) == 0)
    assert np.all(tonemap(np.full((4, 4, 3), np.nan)) == 0)
    img = np.ones((4, 4, 3))
    img[0, 0] = np.nan
    img[0, 1] = [np.inf, np.inf, np.inf]
    img[0, 2] = -5.0
    with np.errstate(all="raise"):
        out = tonemap(img)
    assert out[0, 0].tolist() == [0, 0, 0]
    assert out[0, 1].tolist() == [255, 255, 255]
    assert out[0, 2].tolist() == [0, 0, 0]
    assert np.all(out[1:] == _srgb_u8(0.8))
    # Mostly black with a tiny bright spot: the spot stays visible (max fallback).
    spot = np.zeros((32, 32, 3))
    spot[3, 4] = 1e5
    assert tonemap(spot)[3, 4, 0] == _srgb_u8(0.8)


def test_probe_preview_scale():
    probe = np.random.default_rng(1).random((4, 8, 3))
    out = probe_preview(probe, exposure_ev=0.0, scale=3)
    assert out.shape == (12, 24, 3)
    np.testing.assert_array_equal(out[::3, ::3], tonemap(probe, exposure_ev=0.0))


def test_save_png_round_trip(tmp_path):
    img = np.random.default_rng(2).integers(0, 256, size=(7, 9, 3), dtype=np.uint8)
    path = tmp_path / "p.png"
    save_png(path, img)
    np.testing.assert_array_equal(np.asarray(Image.open(path)), img)
    assert os.listdir(tmp_path) == ["p.png"]
    with pytest.raises(ValueError):
        save_png(tmp_path / "f.png", img.astype(np.float32))
    assert os.listdir(tmp_path) == ["p.png"]


def test_contact_sheet_dims():
    wide = np.zeros((64, 128, 3), np.uint8)  # resized to 128 x 256
    square = np.full((50, 50), 200, np.uint8)  # resized to 128 x 128
    rows = [[("a", wide), ("b", square)], [("c", square)]]
    sheet = contact_sheet(rows, cell_height=128, pad=4)
    assert sheet.dtype == np.uint8 and sheet.ndim == 3 and sheet.shape[2] == 3
    # Width: pad + (256 + pad) + (128 + pad); labels are narrower than the tiles.
    assert sheet.shape[1] == 4 + 260 + 132
    # Height: pad + 2 (label_h + 128 + pad) with some positive label height.
    assert (sheet.shape[0] - 4) % 2 == 0
    label_h = (sheet.shape[0] - 4) // 2 - 128 - 4
    assert 5 <= label_h <= 40
    assert np.all(sheet[0, :] == 255) and np.all(sheet[:, -1] == 255)  # white background
    y0 = 4 + label_h
    assert np.all(sheet[y0 : y0 + 128, 4 : 4 + 256] == 0)  # first tile in place
    assert np.all(sheet[y0 : y0 + 128, 264 : 264 + 128] == 200)  # second tile
    assert np.any(sheet[4 : 4 + label_h, 4:40] < 128)  # some label ink above the tile
    # A long label widens its column.
    long = contact_sheet([[("a very long label for a tiny tile", square)]], cell_height=16, pad=2)
    assert long.shape[1] > 16 + 4
    with pytest.raises(ValueError):
        contact_sheet([])


def test_srgb_encoding_is_colour_sciences():
    import colour

    from f2l.io.preview import srgb_encode

    v = np.concatenate([np.linspace(0.0, 1.0, 4097), [0.0031308, 0.0031307, 0.0031309, 1e-9]])
    np.testing.assert_allclose(srgb_encode(v), colour.cctf_encoding(v, function="sRGB"), rtol=0, atol=1e-12)
