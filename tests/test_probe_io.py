"""Probes in any HDR format OpenImageIO reads (f2l.io.probe_io): each read against data written
independently of the reader (by the format's definition, or by another library)."""

from __future__ import annotations

import numpy as np
import pytest

from f2l.io.exr import write_exr
from f2l.io.probe_io import read_hdr_image

RNG = np.random.default_rng(4)
IMAGE = (RNG.uniform(0.01, 1.0, (6, 10, 3)) * 10.0 ** RNG.uniform(-3, 5, (6, 10, 1))).astype(np.float32)


def test_pfm_is_read_bottom_row_first(tmp_path):
    """PFM stores the bottom row first (and little-endian for a negative scale)."""
    path = tmp_path / "probe.pfm"
    h, w, _ = IMAGE.shape
    path.write_bytes(b"PF\n%d %d\n-1.0\n" % (w, h) + IMAGE[::-1].astype("<f4").tobytes())
    np.testing.assert_array_equal(read_hdr_image(path), IMAGE)


def test_float_tiff_and_exr(tmp_path):
    import tifffile

    tifffile.imwrite(tmp_path / "probe.tif", IMAGE, photometric="rgb")
    np.testing.assert_array_equal(read_hdr_image(tmp_path / "probe.tif"), IMAGE)
    write_exr(tmp_path / "probe.exr", IMAGE)
    np.testing.assert_array_equal(read_hdr_image(tmp_path / "probe.exr"), IMAGE)


def test_radiance_hdr_within_rgbe_precision(tmp_path):
    import cv2

    cv2.imwrite(str(tmp_path / "probe.hdr"), np.ascontiguousarray(IMAGE[:, :, ::-1]))  # OpenCV: BGR
    got = read_hdr_image(tmp_path / "probe.hdr")
    # RGBE: an 8-bit mantissa shared by the three channels, relative to the largest one
    err = np.abs(got - IMAGE) / IMAGE.max(axis=2, keepdims=True)
    assert err.max() < 1 / 128


def test_bad_files_are_named(tmp_path):
    with pytest.raises(ValueError, match="missing.pfm: file not found"):
        read_hdr_image(tmp_path / "missing.pfm")
    bad = tmp_path / "bad.hdr"
    bad.write_bytes(b"not an image")
    with pytest.raises(ValueError, match="bad.hdr"):
        read_hdr_image(bad)
    nan = IMAGE.copy()
    nan[0, 0, 0] = np.nan
    h, w, _ = nan.shape
    (tmp_path / "nan.pfm").write_bytes(b"PF\n%d %d\n-1.0\n" % (w, h) + nan[::-1].astype("<f4").tobytes())
    with pytest.raises(ValueError, match="nan.pfm: NaN"):
        read_hdr_image(tmp_path / "nan.pfm")
