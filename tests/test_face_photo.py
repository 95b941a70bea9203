"""f2l.io.photo: decoding, masks, orientation, focal length, EXIF and errors (fixtures made here)."""

import math
import pickle
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, ImageOps
from PIL.TiffImagePlugin import IFDRational

from f2l.io import photo
from f2l.io.photo import DEFAULT_FOCAL_35MM_MM, DIAGONAL_35MM_MM, PhotoError, load_photo

CR2 = Path(__file__).resolve().parents[2] / "shared/data/raw/IMG_5952.CR2"
EXIF_IFD = 0x8769


def inverse_srgb(code, full=255):
    c = np.asarray(code, np.float64) / full
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def codes_8bit(h=20, w=24, seed=0):
    rng = np.random.default_rng(seed)
    codes = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    codes[0, 0], codes[0, 1], codes[0, 2] = (0, 0, 0), (2, 1, 2), (2, 3, 0)  # black, black, not black
    codes[1, 0], codes[1, 1], codes[1, 2] = (255, 255, 255), (255, 10, 10), (254, 128, 0)  # clipped, clipped, not
    codes[2, :4] = 128
    codes[3:6, 3:6] = rng.integers(0, 3, (3, 3, 3))  # a near-black patch
    return codes


def save_with_exif(path, array, ifd0=None, exif_ifd=None, **kwargs):
    exif = Image.Exif()
    for tag, value in (ifd0 or {}).items():
        exif[tag] = value
    if exif_ifd:
        sub = exif.get_ifd(EXIF_IFD)
        sub.update(exif_ifd)
    Image.fromarray(array).save(path, exif=exif, **kwargs)
    return path


# --- values and masks ---------------------------------------------------------------------------

def test_png_8bit_round_trip(tmp_path):
    codes = codes_8bit()
    path = tmp_path / "codes.png"
    Image.fromarray(codes).save(path)
    p = load_photo(path)
    assert (p.kind, p.orientation, p.exif, p.path) == ("png", 1, {}, str(path))
    assert p.linear.dtype == np.float32 and p.linear.shape == codes.shape
    assert p.display.dtype == np.uint8 and np.array_equal(p.display, codes)
    np.testing.assert_allclose(p.linear, inverse_srgb(codes), rtol=1e-6, atol=1e-9)
    assert p.linear[1, 0, 0] == 1.0 and p.linear[0, 0, 0] == 0.0
    assert p.linear[2, 0, 0] == pytest.approx(0.2158605, abs=1e-7)  # sRGB^-1(128 / 255) by the formula, float32
    assert p.linear[0, 1, 1] == pytest.approx(1 / 255 / 12.92, rel=1e-6)
    np.testing.assert_array_equal(p.clipped, (codes == 255).any(axis=-1))
    np.testing.assert_array_equal(p.black, (codes <= 2).all(axis=-1))
    assert p.black[0, 0] and p.black[0, 1] and not p.black[0, 2] and p.black[3:6, 3:6].all()
    assert p.clipped[1, 0] and p.clipped[1, 1] and not p.clipped[1, 2]
    # No EXIF: the default 35 mm-equivalent 50 mm lens over the image diagonal.
    assert p.focal_source == "default"
    assert p.focal_px == pytest.approx(50.0 / 43.2666 * math.hypot(20, 24), rel=1e-5)


def test_black_threshold_is_srgb_code_2():
    assert photo.BLACK_LINEAR == pytest.approx(2 / 255 / 12.92)


def test_greyscale_palette_and_alpha_become_rgb(tmp_path):
    grey = np.tile(np.arange(0, 256, 8, dtype=np.uint8), (20, 1))
    Image.fromarray(grey).save(tmp_path / "grey.png")
    p = load_photo(tmp_path / "grey.png")
    assert p.display.shape == (20, 32, 3) and np.array_equal(p.display, np.repeat(grey[..., None], 3, -1))
    rgba = np.dstack([codes_8bit(), np.full((20, 24), 7, np.uint8)])
    Image.fromarray(rgba).save(tmp_path / "rgba.png")
    assert np.array_equal(load_photo(tmp_path / "rgba.png").display, rgba[..., :3])
    Image.fromarray(codes_8bit()).quantize(16).save(tmp_path / "palette.png")
    assert load_photo(tmp_path / "palette.png").display.shape == (20, 24, 3)


def test_png_16bit_greyscale(tmp_path):
    values = np.linspace(0, 65535, 20 * 24).round().astype(np.uint16).reshape(20, 24)
    values[0, :3] = (514, 515, 0)
    Image.fromarray(values).save(tmp_path / "g16.png")
    p = load_photo(tmp_path / "g16.png")
    expected = inverse_srgb(values, 65535)
    np.testing.assert_allclose(p.linear, np.repeat(expected[..., None], 3, -1), rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(p.clipped, values == 65535)
    np.testing.assert_array_equal(p.black, values <= 514)
    np.testing.assert_array_equal(p.display[..., 0], np.round(values / 257).astype(np.uint8))


def test_tiff_16bit_rgb_and_float(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    rng = np.random.default_rng(1)
    values = rng.integers(0, 65536, (18, 26, 3), dtype=np.uint16)
    values[0, 0] = (65535, 3, 3)
    for byteorder in "<>":
        tifffile.imwrite(tmp_path / "rgb16.tif", values, photometric="rgb", byteorder=byteorder)
        p = load_photo(tmp_path / "rgb16.tif")
        assert p.kind == "tiff" and p.linear.shape == (18, 26, 3)
        np.testing.assert_allclose(p.linear, inverse_srgb(values, 65535), rtol=1e-6, atol=1e-9)
        np.testing.assert_array_equal(p.clipped, (values == 65535).any(-1))

    floats = rng.random((18, 26, 3), dtype=np.float32) * 40.0
    floats[0, 0] = (-0.5, 2.0, 1e4)  # HDR: no clipping; negatives clamp to 0
    tifffile.imwrite(tmp_path / "hdr.tif", floats, photometric="rgb")
    p = load_photo(tmp_path / "hdr.tif")
    np.testing.assert_array_equal(p.linear, np.maximum(floats, 0))
    assert not p.clipped.any() and p.display.dtype == np.uint8 and p.display.shape == (18, 26, 3)
    floats[3, 3, 1] = np.nan
    tifffile.imwrite(tmp_path / "nan.tif", floats, photometric="rgb")
    with pytest.raises(PhotoError, match="nan.tif.*NaN"):
        load_photo(tmp_path / "nan.tif")


def test_float_greyscale_tiff_via_pillow(tmp_path, monkeypatch):
    values = np.linspace(0.0, 3.0, 16 * 20, dtype=np.float32).reshape(16, 20)
    Image.fromarray(values).save(tmp_path / "f.tif")
    monkeypatch.setattr(photo, "_decode_tiff", photo._decode_pillow)  # the path taken without tifffile
    p = load_photo(tmp_path / "f.tif")
    np.testing.assert_array_equal(p.linear, np.repeat(values[..., None], 3, -1))
    assert p.kind == "tiff" and p.display[-1, -1, 0] > p.display[0, 1, 0]


# --- orientation --------------------------------------------------------------------------------

def marked(h=20, w=32):
    """Non-square grey image with a red top-left corner and a blue top-right corner."""
    a = np.full((h, w, 3), 100, np.uint8)
    a[:5, :5] = (255, 0, 0)
    a[:5, -5:] = (0, 0, 255)
    return a


@pytest.mark.parametrize("orientation", range(1, 9))
def test_orient_matches_pillow_exif_transpose(orientation):
    a = np.arange(5 * 7 * 3, dtype=np.uint8).reshape(5, 7, 3)
    image = Image.fromarray(a)
    exif = image.getexif()
    exif[274] = orientation
    expected = np.asarray(ImageOps.exif_transpose(image))
    assert np.array_equal(photo._orient(a, orientation), expected)


def test_jpeg_orientation_6(tmp_path):
    path = save_with_exif(tmp_path / "rot6.jpg", marked(), ifd0={274: 6}, quality=100)
    p = load_photo(path)
    assert p.orientation == 6 and p.kind == "jpeg" and p.display.shape == (32, 20, 3)
    # Rotated 90° clockwise for display: the stored top-left corner is now top-right, top-right is bottom-right.
    top_right, bottom_right = p.display[:4, -4:].reshape(-1, 3).mean(0), p.display[-4:, -4:].reshape(-1, 3).mean(0)
    assert top_right[0] > 200 and top_right[2] < 50 and bottom_right[2] > 200 and bottom_right[0] < 50
    assert p.focal_px == pytest.approx(load_photo(save_with_exif(tmp_path / "r1.jpg", marked())).focal_px)


@pytest.mark.parametrize("orientation, rotate", [(3, 2), (8, 1)])
def test_png_orientation(tmp_path, orientation, rotate):
    stored = marked()
    p = load_photo(save_with_exif(tmp_path / f"o{orientation}.png", stored, ifd0={274: orientation}))
    assert p.orientation == orientation
    assert np.array_equal(p.display, np.rot90(stored, rotate))  # rot90: counter-clockwise
    assert p.linear.shape == p.display.shape and p.clipped.shape == p.display.shape[:2]
    assert p.clipped[-5:, :5].all() if orientation == 8 else p.clipped[-5:, -5:].all()


# --- focal length and EXIF ----------------------------------------------------------------------

def test_focal_from_35mm_equivalent_and_exif_fields(tmp_path):
    exif_ifd = {33434: IFDRational(1, 250), 33437: IFDRational(28, 10), 34855: 200, 37386: IFDRational(45, 10),
                41989: 28, 36867: "2024:06:01 12:30:00"}
    path = save_with_exif(tmp_path / "f35.jpg", marked(48, 64), ifd0={271: "Maker", 272: "Cam 1"},
                          exif_ifd=exif_ifd, quality=95)
    p = load_photo(path)
    assert p.exif == {"exposure_s": 1 / 250, "f_number": 2.8, "iso": 200, "focal_length_mm": 4.5,
                      "focal_35mm_mm": 28.0, "make": "Maker", "model": "Cam 1",
                      "datetime_original": "2024:06:01 12:30:00"}
    assert p.focal_source == "exif-35mm"
    assert p.focal_px == pytest.approx(28 / DIAGONAL_35MM_MM * math.hypot(48, 64))
    assert DIAGONAL_35MM_MM == pytest.approx(43.2666, abs=1e-4)


@pytest.mark.parametrize("exif_width, expected", [(None, 10000.0), (64, 10000.0), (128, 5000.0)])
def test_focal_from_focal_plane_resolution(tmp_path, exif_width, expected):
    # 50 mm lens, 2000 pixels per cm (unit 3) = 200 px/mm -> 10000 px; an image downsized 2x from
    # its EXIF dimensions (128x96 -> 64x48) gets half.
    exif_ifd = {37386: IFDRational(50, 1), 41486: IFDRational(2000, 1), 41488: 3}
    if exif_width:
        exif_ifd.update({40962: exif_width, 40963: exif_width * 3 // 4})
    p = load_photo(save_with_exif(tmp_path / "fp.png", marked(48, 64), ifd0={274: 6}, exif_ifd=exif_ifd))
    assert p.focal_source == "exif-focal-plane" and p.exif["focal_length_mm"] == 50.0
    assert p.focal_px == pytest.approx(expected)


def test_default_focal_parameter(tmp_path):
    path = save_with_exif(tmp_path / "plain.png", marked(48, 64))
    assert DEFAULT_FOCAL_35MM_MM == 50.0
    p = load_photo(path, default_focal_35mm_mm=35.0)
    assert p.focal_source == "default" and p.focal_px == pytest.approx(35 / 43.2666 * 80.0, rel=1e-5)
    assert math.degrees(2 * math.atan(80.0 / 2 / load_photo(path).focal_px)) == pytest.approx(46.8, abs=0.05)
    with pytest.raises(ValueError):
        load_photo(path, default_focal_35mm_mm=0.0)


# --- errors -------------------------------------------------------------------------------------

def assert_photo_error(path, *fragments):
    with pytest.raises(PhotoError) as info:
        load_photo(path)
    message = str(info.value)
    assert Path(path).name in message and info.value.path == str(path)
    for fragment in fragments:
        assert fragment in message
    return message


def test_missing_and_empty_files(tmp_path):
    assert_photo_error(tmp_path / "missing.jpg", "no such file")
    (tmp_path / "empty.png").write_bytes(b"")
    assert_photo_error(tmp_path / "empty.png", "zero-byte")
    assert_photo_error(tmp_path, "not a regular file")


@pytest.mark.parametrize("suffix, kwargs", [(".jpg", {"quality": 90}), (".png", {})])
def test_truncated_files(tmp_path, suffix, kwargs):
    rng = np.random.default_rng(2)
    full = tmp_path / f"full{suffix}"
    Image.fromarray(rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)).save(full, **kwargs)
    data = full.read_bytes()
    half = tmp_path / f"half{suffix}"
    half.write_bytes(data[: len(data) // 2])
    assert_photo_error(half, "truncated or corrupt")


def test_truncated_tiff(tmp_path):
    Image.fromarray(codes_8bit(64, 64)).save(tmp_path / "full.tif")
    data = (tmp_path / "full.tif").read_bytes()
    (tmp_path / "half.tif").write_bytes(data[: len(data) // 2])
    assert_photo_error(tmp_path / "half.tif", "truncated")


def test_not_images(tmp_path):
    (tmp_path / "noise.cr2").write_bytes(np.random.default_rng(3).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    assert_photo_error(tmp_path / "noise.cr2", "not a supported photo")
    (tmp_path / "notes.jpg").write_text("this is not a picture\n" * 20)
    assert_photo_error(tmp_path / "notes.jpg", "not a recognised image")
    Image.fromarray(codes_8bit()).save(tmp_path / "picture.gif")
    assert_photo_error(tmp_path / "picture.gif", "not a supported photo")
    Image.fromarray(codes_8bit()).save(tmp_path / "picture.bmp.png", format="BMP")
    assert_photo_error(tmp_path / "picture.bmp.png", "unsupported image format BMP")


def test_too_small(tmp_path):
    Image.fromarray(codes_8bit(15, 40)).save(tmp_path / "thin.png")
    assert_photo_error(tmp_path / "thin.png", "40x15", "16x16")


def test_photo_error_is_a_picklable_value_error():
    error = pickle.loads(pickle.dumps(PhotoError("a/b.jpg", "truncated JPEG (x)")))
    assert isinstance(error, ValueError) and str(error) == "a/b.jpg: truncated JPEG (x)"
    assert (error.path, error.reason) == ("a/b.jpg", "truncated JPEG (x)")


# --- RAW ----------------------------------------------------------------------------------------

requires_cr2 = pytest.mark.skipif(not CR2.is_file(), reason=f"sample RAW {CR2} not present (shared data)")


@requires_cr2
def test_canon_cr2():
    start = time.perf_counter()
    p = load_photo(CR2)
    assert time.perf_counter() - start < 5.0
    assert p.kind == "raw" and p.orientation == 1
    assert p.exif["exposure_s"] == 1 / 400 and p.exif["f_number"] == 22 and p.exif["iso"] == 640
    assert p.exif["make"] == "Canon" and p.exif["model"] == "Canon EOS 30D"
    assert p.exif["datetime_original"] == "2009:07:21 13:03:20"
    h, w = p.linear.shape[:2]
    assert (h, w) == (1174, 1761)  # half size: one pixel per 2x2 CFA block of the 2348x3522 image
    assert p.linear.dtype == np.float32 and np.isfinite(p.linear).all() and p.linear.min() >= 0
    assert 0 < p.linear.max() <= 1
    assert p.display.dtype == np.uint8 and p.display.shape == (h, w, 3)
    assert p.clipped.shape == p.black.shape == (h, w) and p.clipped.dtype == p.black.dtype == bool
    # 22 mm on the 30D's 22.5 mm-wide sensor (FocalPlaneXResolution 3959 px/inch at 3504 px) at half size;
    # a 1.6x crop factor (35.2 mm equivalent) over the diagonal gives nearly the same.
    assert p.focal_source == "exif-focal-plane"
    assert p.focal_px == pytest.approx(22 * 233600 / 59 / 25.4 / 2)
    assert p.focal_px == pytest.approx(22 * 1.6 / DIAGONAL_35MM_MM * math.hypot(h, w), rel=0.02)
    # The preview maps the 99th luminance percentile near 0.8 (sRGB code ~231).
    luma = p.display.astype(np.float64) @ [0.2126, 0.7152, 0.0722]
    assert 215 <= np.percentile(luma, 99) <= 240
    import json

    json.dumps(p.exif)


@requires_cr2
def test_cr2_truncated(tmp_path):
    data = CR2.read_bytes()
    (tmp_path / "cut.CR2").write_bytes(data[: len(data) // 2])
    assert_photo_error(tmp_path / "cut.CR2", "RAW")


@requires_cr2
def test_libraw_flip_mapping_and_sensor_clipping():
    """LibRaw's flips equal the EXIF orientations we record, and saturated photosites become clipped pixels."""
    rawpy = pytest.importorskip("rawpy")
    kwargs = dict(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=True, half_size=True,
                  output_color=rawpy.ColorSpace.sRGB, adjust_maximum_thr=0.0)
    with rawpy.imread(str(CR2)) as raw:
        values, colours = raw.raw_image_visible, raw.raw_colors_visible
        values[100:140, 200:260] = raw.white_level  # every photosite saturated
        red = values[300:340, 400:460]
        red[colours[300:340, 400:460] == 0] = 128 + int(0.6 * (raw.white_level - 128))  # only red, via WB
        clipped = photo._raw_clipped(raw, half_size=True)
        upright = raw.postprocess(user_flip=0, **kwargs)
        for flip in (3, 5, 6):
            turned = raw.postprocess(user_flip=flip, **kwargs)
            assert np.array_equal(turned, photo._orient(upright, photo.LIBRAW_FLIP_TO_ORIENTATION[flip]))
    assert clipped.shape == upright.shape[:2]
    assert clipped[50:70, 100:130].all() and clipped[150:170, 200:230].all()
    assert clipped.sum() == 20 * 30 * 2  # nothing else in this image is near saturation
    assert (upright[150:170, 200:230, 0] >= 0.98 * 65535).all()  # red really clips in LibRaw's output
