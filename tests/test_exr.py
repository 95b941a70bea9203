"""Tests for f2l.io.exr (float32 EXR I/O)."""

from __future__ import annotations

import os

import numpy as np
import OpenEXR
import pytest

from f2l.io.exr import ExrError, read_exr, read_exr_with_metadata, write_exr

RNG = np.random.default_rng(3)


def _hdr(height: int = 32, width: int = 64) -> np.ndarray:
    # Log-uniform 1e-3 .. 1e4 plus a 5e6 'sun': dynamic range > 1e9.
    img = np.exp(RNG.uniform(np.log(1e-3), np.log(1e4), size=(height, width, 3))).astype(np.float32)
    img[height // 2, width // 3] = [5e6, 4.5e6, 4e6]
    return img


def test_round_trip_bit_exact(tmp_path):
    img = _hdr()
    path = tmp_path / "probe.exr"
    write_exr(path, img)
    back = read_exr(path)
    assert back.dtype == np.float32 and back.shape == img.shape
    np.testing.assert_array_equal(back, img)  # bit exact
    assert back.max() == np.float32(5e6)  # > 65504: not half
    # Stored as FLOAT, ZIP-compressed, channels R, G, B.
    exr = OpenEXR.File(str(path), separate_channels=True)
    chans = exr.channels()
    assert set(chans) == {"R", "G", "B"}
    assert all(c.type() == OpenEXR.FLOAT for c in chans.values())
    assert exr.header()["compression"] == OpenEXR.ZIP_COMPRESSION
    np.testing.assert_array_equal(chans["G"].pixels, img[:, :, 1])


def test_uncompressed_round_trip_and_unknown_codec(tmp_path):
    img = _hdr()
    write_exr(tmp_path / "plain.exr", img, compression="none")
    np.testing.assert_array_equal(read_exr(tmp_path / "plain.exr"), img)
    assert OpenEXR.File(str(tmp_path / "plain.exr")).header()["compression"] == OpenEXR.NO_COMPRESSION
    with pytest.raises(ValueError, match="compression"):
        write_exr(tmp_path / "bad.exr", img, compression="jpeg")
    assert not (tmp_path / "bad.exr").exists()


def test_float64_and_grayscale_input(tmp_path):
    img64 = RNG.random((8, 12, 3)) * 1e5
    write_exr(tmp_path / "a.exr", img64)
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr"), img64.astype(np.float32))
    gray = RNG.random((8, 12)).astype(np.float32) * 7e4
    write_exr(str(tmp_path / "g.exr"), gray)
    back = read_exr(str(tmp_path / "g.exr"))
    assert back.shape == (8, 12, 3)
    for c in range(3):
        np.testing.assert_array_equal(back[:, :, c], gray)


def test_metadata_round_trip(tmp_path):
    meta = {"f2l.source": "IMG_0001.CR2", "f2l.grid": "64x128", "note": "ünïcode ok"}
    write_exr(tmp_path / "m.exr", _hdr(4, 8), metadata=meta)
    img, back = read_exr_with_metadata(tmp_path / "m.exr")
    assert img.shape == (4, 8, 3)
    assert back == meta
    with pytest.raises(ValueError, match="reserved"):
        write_exr(tmp_path / "r.exr", _hdr(4, 8), metadata={"compression": "none"})
    with pytest.raises(ValueError):
        write_exr(tmp_path / "r.exr", _hdr(4, 8), metadata={"n": 3})  # type: ignore[dict-item]


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, -1e-3, 1e39])
def test_invalid_values_rejected(tmp_path, bad):
    img = _hdr(4, 8).astype(np.float64)
    img[1, 2, 0] = bad
    path = tmp_path / "bad.exr"
    with pytest.raises(ValueError, match="bad.exr"):
        write_exr(path, img)
    assert not path.exists()
    assert os.listdir(tmp_path) == []  # no temp file left behind


def test_tiny_negative_accepted(tmp_path):
    img = np.zeros((4, 4, 3), np.float32)
    img[0, 0, 0] = -5e-7
    write_exr(tmp_path / "n.exr", img)
    np.testing.assert_array_equal(read_exr(tmp_path / "n.exr"), img)


def test_bad_shape_rejected(tmp_path):
    with pytest.raises(ValueError, match="x.exr"):
        write_exr(tmp_path / "x.exr", np.zeros((4, 4, 4), np.float32))


def test_corrupt_file_raises(tmp_path):
    path = tmp_path / "corrupt.exr"
    path.write_bytes(RNG.bytes(4096))
    with pytest.raises(ExrError, match="corrupt.exr"):
        read_exr(path)


@pytest.mark.parametrize("keep", [0, 20, 200, 0.5, 0.95, -1])
def test_truncated_file_raises(tmp_path, keep):
    good = tmp_path / "good.exr"
    write_exr(good, _hdr(64, 128))
    data = good.read_bytes()
    n = keep if isinstance(keep, int) and keep >= 0 else (len(data) - 1 if keep == -1 else int(len(data) * keep))
    path = tmp_path / "trunc.exr"
    path.write_bytes(data[:n])
    with pytest.raises(ExrError, match="trunc.exr"):
        read_exr(path)


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(ExrError, match="nope.exr"):
        read_exr(tmp_path / "nope.exr")
    with pytest.raises(ExrError):
        read_exr(tmp_path)
    assert issubclass(ExrError, IOError)


def test_overwrite_is_atomic_and_leaves_no_temp(tmp_path):
    path = tmp_path / "p.exr"
    write_exr(path, _hdr(4, 8))
    second = _hdr(6, 10)
    write_exr(path, second)
    np.testing.assert_array_equal(read_exr(path), second)
    assert sorted(os.listdir(tmp_path)) == ["p.exr"]
    # A failed write keeps the previous file intact.
    with pytest.raises(ValueError):
        write_exr(path, np.full((2, 2, 3), np.nan))
    np.testing.assert_array_equal(read_exr(path), second)
    assert sorted(os.listdir(tmp_path)) == ["p.exr"]
