"""Synthetic DNG writer, RAW metadata/mosaic reading, bilinear demosaic (f2l.capture.dng, .raw_meta)."""

import dataclasses
from datetime import datetime, timedelta, timezone
from pathlib import Path

import exifread
import numpy as np
import pytest
import rawpy
from scipy import ndimage

from f2l.capture.dng import synthetic_sky_scene, write_bracket, write_dng
from f2l.io.photo.dng_tags import dng_layout
from f2l.io.photo.tags import from_exifread
from f2l.io.raw_meta import (
    BAYER_PATTERNS, RawError, bayer_mosaic, demosaic_bilinear, read_raw, read_raw_metadata, read_raw_mosaic,
)  # fmt: skip

CR2 = Path(__file__).resolve().parents[2] / "shared/data/raw/IMG_5952.CR2"
TZ = timezone(timedelta(hours=2))


def _random_mosaic(seed=0, shape=(96, 128), white=4095):
    return np.random.default_rng(seed).integers(0, white + 1, shape).astype(np.uint16)


def test_write_dng_round_trip_is_bit_exact(tmp_path):
    raw = _random_mosaic()
    path = write_dng(tmp_path / "a.dng", raw, exposure_s=1 / 400, f_number=22, iso=640,
                     black_level=[256, 250, 260, 255], white_level=4095, cfa="GRBG", make="Acme", model="Cam 1",
                     lens="Acme 24mm", focal_length_mm=24, timestamp=datetime(2024, 6, 21, 12, 30, 5, tzinfo=TZ),
                     gps=(46.5, -6.25, 1200.0))  # fmt: skip
    with rawpy.imread(str(path)) as decoded:
        assert decoded.raw_image_visible.dtype == np.uint16
        np.testing.assert_array_equal(decoded.raw_image_visible, raw)
        assert decoded.white_level == 4095
        assert decoded.other.iso_speed == 640  # LibRaw finds ISO in the EXIF sub-IFD too
    with open(path, "rb") as fh:
        tags = exifread.process_file(fh, details=False)
    assert str(tags["EXIF ExposureTime"]) == "1/400"
    assert float(tags["EXIF FNumber"].values[0]) == 22
    assert tags["EXIF ISOSpeedRatings"].values[0] == 640
    assert str(tags["Image Make"]) == "Acme" and str(tags["Image Model"]) == "Cam 1"

    meta, mosaic = read_raw(path)
    np.testing.assert_array_equal(mosaic, raw)
    assert (meta.exposure_s, meta.f_number, meta.iso) == (1 / 400, 22.0, 640.0)
    assert meta.exposure_factor == pytest.approx(1 / 400 * 6.4 / 22**2)
    assert meta.ev100 == pytest.approx(-np.log2(1 / 400 * 6.4 / 22**2))
    assert (meta.make, meta.model, meta.camera, meta.lens) == ("Acme", "Cam 1", "Acme Cam 1", "Acme 24mm")
    assert (meta.width, meta.height, meta.cfa_pattern, meta.white_level) == (128, 96, "GRBG", 4095.0)
    assert meta.black_levels == (256.0, 250.0, 260.0, 255.0)  # per CFA position, row-major
    assert meta.focal_length_mm == 24.0 and meta.orientation == 1
    assert meta.timestamp == datetime(2024, 6, 21, 12, 30, 5, tzinfo=TZ)
    assert meta.gps_latitude_deg == pytest.approx(46.5) and meta.gps_longitude_deg == pytest.approx(-6.25)
    assert meta.gps_altitude_m == pytest.approx(1200.0)
    np.testing.assert_allclose(np.reshape(meta.xyz_to_camera, (3, 3))[0], [3.2405, -1.5371, -0.4985])
    assert read_raw_metadata(path, levels=False) == meta  # a DNG states its layout in tags: no decode needed


@pytest.mark.parametrize("cfa", BAYER_PATTERNS)
def test_lossless_jpeg_dng_decodes_bit_exactly_and_is_smaller(tmp_path, cfa):
    raw = np.clip(np.add.outer(np.arange(96) * 20, np.arange(128) * 15) + _random_mosaic(1, white=40), 0, 4095)
    raw = raw.astype(np.uint16)
    kwargs = dict(exposure_s=0.01, f_number=8, iso=100, black_level=[250, 251, 252, 253], cfa=cfa)
    plain = write_dng(tmp_path / "plain.dng", raw, **kwargs)
    packed = write_dng(tmp_path / "packed.dng", raw, compression="ljpeg", **kwargs)
    assert packed.stat().st_size < 0.6 * plain.stat().st_size
    with open(packed, "rb") as fh:
        assert exifread.process_file(fh, details=False)["Image Compression"].values == [7]  # JPEG (lossless)
    meta, mosaic = read_raw(packed)
    np.testing.assert_array_equal(mosaic, raw)
    assert meta == dataclasses.replace(read_raw(plain)[0], path=str(packed))
    with pytest.raises(ValueError, match="compression"):
        write_dng(tmp_path / "bad.dng", raw, compression="zip", **kwargs)


def test_dng_levels_come_from_tags_without_a_decode(tmp_path, monkeypatch):
    import f2l.io.raw_meta as raw_meta

    path = write_dng(tmp_path / "a.dng", _random_mosaic(2), exposure_s=0.01, f_number=8, iso=100,
                     black_level=[10, 20, 30, 40], cfa="GBRG", compression="ljpeg")
    decoded = read_raw_metadata(path)
    monkeypatch.setattr(raw_meta, "read_raw", lambda *a, **k: pytest.fail("decoded a DNG that states its levels"))
    assert read_raw_metadata(path) == decoded
    assert decoded.black_levels == (10.0, 20.0, 30.0, 40.0) and decoded.cfa_pattern == "GBRG"
    with open(path, "rb") as fh:
        tags = exifread.process_file(fh, details=False)
    def layout(exifread_tags):
        return dng_layout(from_exifread(exifread_tags).ifd0)

    assert layout(tags) == ("GBRG", (10.0, 20.0, 30.0, 40.0), 4095.0)
    for extra in ("Image Tag 0xC61B", "Image Tag 0xC618", "Image Tag 0xC68D"):  # black deltas, linearisation, ActiveArea
        assert layout({**tags, extra: tags["Image BlackLevel"]}) is None
    assert layout({k: v for k, v in tags.items() if k != "Image Tag 0xC612"}) is None  # not a DNG
    assert layout({**tags, "Image SubfileType": tags["Image Orientation"]}) is None  # a thumbnail IFD


def test_write_bracket_is_deterministic_and_follows_the_sensor_model(tmp_path):
    scene = synthetic_sky_scene(32, 48, seed=1)
    exposures = [1 / 1000, 1 / 250]
    first = write_bracket(tmp_path / "a", scene, exposures, seed=5)
    again = write_bracket(tmp_path / "b", scene, exposures, seed=5)
    other = write_bracket(tmp_path / "c", scene, exposures, seed=6)
    assert [p.name for p in first] == ["frame_00.dng", "frame_01.dng"]
    assert [p.read_bytes() for p in first] == [p.read_bytes() for p in again]  # no clock in the bytes
    assert first[0].read_bytes() != other[0].read_bytes()

    # Without noise the DN are the documented model: black + (white - black) * radiance * e, clipped.
    quiet = write_bracket(tmp_path / "q", scene, exposures, f_number=4, iso=200, black_level=128, read_noise_dn=0,
                          full_well_e=1e14, full_scale_radiance=2.0, cfa="BGGR")  # fmt: skip
    for path, t in zip(quiet, exposures):
        meta, mosaic = read_raw(path)
        e = t * 2.0 / 16
        assert meta.exposure_factor == pytest.approx(e)
        expected = np.clip(np.rint(128 + (4095 - 128) * bayer_mosaic(scene, "BGGR") / 2.0 * e), 0, 4095)
        assert np.abs(mosaic.astype(int) - expected).max() <= 1
        assert (mosaic == 4095).any()  # the sun clips at exactly the white level
        assert meta.cfa_pattern == "BGGR"


@pytest.mark.parametrize("kind", ["empty", "truncated", "garbage", "missing", "header_only"])
def test_unreadable_files_raise_raw_error_naming_the_file(tmp_path, kind):
    good = write_dng(tmp_path / "good.dng", _random_mosaic(shape=(64, 64)), exposure_s=0.01, f_number=8, iso=100)
    data = good.read_bytes()
    bad = tmp_path / f"{kind}.dng"
    content = {"empty": b"", "truncated": data[: len(data) // 2], "garbage": bytes(range(256)) * 20,
               "header_only": data[:300]}  # fmt: skip
    if kind != "missing":
        bad.write_bytes(content[kind])
    for reader in (read_raw_metadata, read_raw_mosaic):
        with pytest.raises(RawError) as info:
            reader(bad)
        assert str(info.value).startswith(str(bad))
        assert isinstance(info.value, IOError)


def test_canon_cr2_metadata():
    if not CR2.exists():
        pytest.skip(f"real Canon RAW not available at {CR2}")
    meta = read_raw_metadata(CR2)
    assert meta.exposure_s == pytest.approx(1 / 400)
    assert meta.f_number == pytest.approx(22)
    assert meta.iso == 640
    assert meta.make == "Canon" and meta.model == "Canon EOS 30D"
    assert meta.white_level == 4095
    assert all(120 <= b <= 136 for b in meta.black_levels)
    assert meta.cfa_pattern == "RGGB"
    assert (meta.width, meta.height) == (3522, 2348)
    assert meta.timestamp == datetime(2009, 7, 21, 13, 3, 20)
    assert meta.focal_length_mm == 22 and meta.xyz_to_camera is not None
    quick = read_raw_metadata(CR2, levels=False)  # no decode: a CR2's levels need the pixels
    assert (quick.exposure_s, quick.iso, quick.width, quick.black_levels) == (meta.exposure_s, 640, 3522, None)


def _reference_demosaic(mosaic, cfa):
    """Normalised convolution with the bilinear kernels, mirror borders (independent of the code)."""
    kernel_rb = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]]) / 4.0
    kernel_g = np.array([[0, 1, 0], [1, 4, 1], [0, 1, 0]]) / 4.0
    out = np.zeros(mosaic.shape + (3,))
    for c, letter in enumerate("RGB"):
        mask = np.zeros(mosaic.shape)
        for k, l2 in enumerate(cfa):
            if l2 == letter:
                mask[k // 2 :: 2, k % 2 :: 2] = 1
        kernel = kernel_g if letter == "G" else kernel_rb
        out[..., c] = ndimage.correlate(mosaic * mask, kernel, mode="mirror")
    return out


@pytest.mark.parametrize("cfa", BAYER_PATTERNS)
def test_bilinear_demosaic_matches_reference_and_keeps_hdr(cfa):
    rng = np.random.default_rng(3)
    mosaic = np.exp(rng.uniform(-5, 16, (12, 18))).astype(np.float32)  # values 1e7 x apart and more
    rgb = demosaic_bilinear(mosaic, cfa)
    assert rgb.dtype == np.float32 and rgb.shape == (12, 18, 3)
    np.testing.assert_allclose(rgb, _reference_demosaic(mosaic.astype(np.float64), cfa), rtol=1e-5)
    np.testing.assert_array_equal(bayer_mosaic(rgb, cfa), mosaic)  # measured samples are kept exactly
    assert rgb.min() > 0
    flat = demosaic_bilinear(np.full((8, 8), 3.5e6, np.float32), cfa)
    np.testing.assert_array_equal(flat, 3.5e6)
