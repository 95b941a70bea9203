"""Load one photo (camera RAW, JPEG, PNG or TIFF) for face fitting.

Conventions of :class:`Photo` (all arrays share one frame: the *oriented* image, EXIF orientation
or the RAW's flip applied, row 0 at the top):

* ``linear`` — float32 linear RGB with sRGB/Rec.709 primaries, >= 0, finite. 1.0 is the full scale
  of the source encoding: code 255 or 65535 (exact inverse sRGB of the codes), or for RAW the white
  level of the least-amplified channel after camera white balance (LibRaw, no auto-brightening, no
  gamma, ``adjust_maximum_thr=0`` so the scale never depends on image content). Float TIFFs are
  taken as already linear (negatives clamped to 0).
* ``display`` — uint8 sRGB for detectors and overlays, never a radiometric input. 8-bit sources:
  their own codes; 16-bit: codes rounded to 8 bits; RAW: ``linear`` scaled so the 99th percentile of
  Rec.709 luminance is 0.8, clipped, sRGB-encoded; float TIFF: the same with 0.9.
* ``clipped`` — any channel saturated in the source encoding: code 255 / 65535; RAW: see
  :func:`_raw_clipped`. Float TIFFs cannot saturate: all False.
* ``black`` — all channels <= ``BLACK_LINEAR`` = sRGB⁻¹(2/255) ≈ 6.07e-4 of full scale: 8-bit codes
  <= 2, 16-bit codes <= 514, RAW output <= 39/65535; float TIFF: after the display scaling.
* ``focal_px`` — pinhole focal length in pixels of the decoded image, from FocalLengthIn35mmFilm
  (f35 / 43.2666 mm × image diagonal in pixels: the crop-factor convention), else FocalLength ×
  FocalPlaneXResolution (sensor pixels per mm, rescaled to the decoded size: ×0.5 for RAW
  ``half_size``; JPEG/PNG/TIFF: long side over the ExifImageWidth/Length long side when present),
  else a 35 mm-equivalent ``DEFAULT_FOCAL_35MM_MM`` (50 mm: diagonal field of view ≈ 46.8°).
  Orientation swaps width and height, not the diagonal, so it never changes ``focal_px``.

Large photos: a photo above ``MAX_PIXELS`` (250 MP; ``$F2L_MAX_PHOTO_PIXELS``) is refused from its
header, before decoding. Within it, a photo costs its source codes (8/16-bit: kept as they are;
``linear``, ``clipped``, ``black`` are derived on first use) plus Pillow's buffer while decoding;
face fitting detects on a reduced copy (``DETECTION_MAX_SIDE``) and reads only the rows and
columns its footprints sample (:meth:`Photo.rows`). A 12,000 × 12,000 PNG without a face: 1.1 GB
peak RSS for `f2l fit-faces` (3.2 GB before); a 100 MP 16-bit TIFF with a face: 1.1 GB (3.4 GB).

EXIF comes from Pillow for JPEG/PNG and from ``exifread`` for RAW and TIFF. Pillow cannot decode
16-bit-RGB or float TIFFs, so TIFFs go through ``tifffile`` when it is installed; Pillow reads
16-bit *RGB* PNGs as their high bytes, so those load with 8-bit precision. Bad input raises
:class:`PhotoError` naming the file and the reason. Deterministic; prints nothing (LibRaw itself
may write "Unexpected end of file" to stderr for a truncated RAW).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import struct
import zlib
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np

DEFAULT_FOCAL_35MM_MM = 50.0
DIAGONAL_35MM_MM = math.hypot(36.0, 24.0)  # 43.2666 mm
MIN_SIZE = 16
# Photos above this many pixels are refused before decoding (override: $F2L_MAX_PHOTO_PIXELS). At
# 250 MP a 16-bit RGB source alone is 1.5 GB; fit-faces reads only rows it samples beyond that.
MAX_PIXELS = 250_000_000
# Faces are detected on a copy reduced to this long side (fit.py), then fitted at full resolution.
DETECTION_MAX_SIDE = 4096
BLACK_CODE_8BIT = 2
CLIP_FRACTION = 0.98  # RAW: fraction of full scale (or of the sensor's saturation level) that counts as clipped
RAW_PREVIEW_P99, FLOAT_PREVIEW_P99 = 0.8, 0.9
LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)
RASTER_EXTENSIONS = {".jpg", ".jpeg", ".jpe", ".png", ".tif", ".tiff"}
PILLOW_KINDS = {"JPEG": "jpeg", "MPO": "jpeg", "PNG": "png", "TIFF": "tiff"}
# LibRaw ``sizes.flip`` (dcraw bits: 4 transpose, 2 flip rows, 1 flip columns) -> EXIF orientation:
# the inverse of dcraw's table "50132467"[orientation]; checked against postprocess(user_flip=...).
LIBRAW_FLIP_TO_ORIENTATION = {0: 1, 1: 2, 2: 4, 3: 3, 4: 5, 5: 8, 6: 6, 7: 7}
# Pillow tag ids (IFD0 and the Exif sub-IFD 0x8769 merged); exifread calls them "Image X" / "EXIF X".
EXIF_TAG_IDS = {
    "ExposureTime": 33434, "FNumber": 33437, "ISOSpeedRatings": 34855, "Make": 271, "Model": 272,
    "FocalLength": 37386, "FocalLengthIn35mmFilm": 41989, "DateTimeOriginal": 36867, "Orientation": 274,
    "FocalPlaneXResolution": 41486, "FocalPlaneResolutionUnit": 41488, "ExifImageWidth": 40962,
    "ExifImageLength": 40963,
}
RATIONAL_TAGS = {"ExposureTime", "FNumber", "FocalLength", "FocalPlaneXResolution"}
FOCAL_PLANE_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # EXIF ResolutionUnit (default 2 = inch)

# exifread warns about odd tags through its logger; without a handler that would reach stderr.
logging.getLogger("exifread").addHandler(logging.NullHandler())


class PhotoError(ValueError):
    """A photo that cannot be used; ``str(e)`` is ``"<path>: <reason>"``."""

    def __init__(self, path, reason: str):
        self.path, self.reason = str(path), reason
        super().__init__(f"{self.path}: {reason}")

    def __reduce__(self):
        return PhotoError, (self.path, self.reason)


@dataclass(eq=False)
class Photo:
    """A decoded photo; the module docstring states each field's conventions.

    Memory stays near the size of the source encoding: 8/16-bit sources keep their codes
    (``codes``, oriented, (H, W, 3) uint8/uint16) and ``linear``, ``clipped``, ``black`` (and for
    16-bit, ``display``) are made from them on first use; face fitting reads only the rows it
    samples (:meth:`rows`) and detects on :meth:`detection_image`. RAW and float sources hold
    their arrays."""

    path: str
    kind: str  # "raw" | "jpeg" | "png" | "tiff"
    codes: np.ndarray  # (H, W, 3) uint8 / uint16 source codes, or float32 linear (RAW, float TIFF)
    focal_px: float
    focal_source: str  # "exif-35mm" | "exif-focal-plane" | "default"
    orientation: int  # EXIF orientation applied (1 = none)
    exif: dict
    masks: tuple | None = None  # (display, clipped, black) held explicitly (RAW, float TIFF)

    @property
    def shape(self) -> tuple[int, int]:
        return self.codes.shape[0], self.codes.shape[1]

    def rows(self, index: np.ndarray, cols: slice = slice(None)) -> dict:
        """``linear`` (n, w, 3) float32, ``clipped`` / ``black`` (n, w) bool and ``display``
        (n, w, 3) uint8 of the image rows ``index`` and columns ``cols``, computed from those
        pixels only."""
        index = np.asarray(index)
        if self.masks is not None:
            display, clipped, black = self.masks
            return {"linear": self.codes[index, cols], "clipped": clipped[index, cols],
                    "black": black[index, cols], "display": display[index, cols]}
        return _code_planes(self.codes[index, cols])

    @cached_property
    def _full(self) -> dict:
        return self.rows(np.arange(self.shape[0]))

    @property
    def linear(self) -> np.ndarray:  # (H, W, 3) float32
        return self.codes if self.masks is not None else self._full["linear"]

    @property
    def display(self) -> np.ndarray:  # (H, W, 3) uint8
        if self.masks is not None:
            return self.masks[0]
        return self.codes if self.codes.dtype == np.uint8 else self._full["display"]

    @property
    def clipped(self) -> np.ndarray:  # (H, W) bool
        return self.masks[1] if self.masks is not None else self._full["clipped"]

    @property
    def black(self) -> np.ndarray:  # (H, W) bool
        return self.masks[2] if self.masks is not None else self._full["black"]

    def detection_image(self, max_side: int) -> tuple[np.ndarray, float]:
        """(display reduced so its long side is <= ``max_side``, its scale = reduced / full px).

        An integer box reduction (the mean of f x f display pixels), made from blocks of rows, so
        a large photo is never held in a second full-size form. Photos within the limit come
        back as ``display`` itself, scale 1."""
        h, w = self.shape
        f = max(1, math.ceil(max(h, w) / max(1, int(max_side))))
        if f == 1:
            return self.display, 1.0
        hr, wr = h // f, w // f
        out = np.empty((hr, wr, 3), np.uint8)
        block = max(1, (1 << 22) // max(1, w * f))  # reduced rows per step (~4M source pixels)
        for r0 in range(0, hr, block):
            r1 = min(hr, r0 + block)
            src = self.rows(np.arange(r0 * f, r1 * f))["display"][:, : wr * f].astype(np.float32)
            out[r0:r1] = np.round(src.reshape(r1 - r0, f, wr, f, 3).mean(axis=(1, 3))).astype(np.uint8)
        return out, wr / w


def _code_planes(codes: np.ndarray) -> dict:
    """linear / clipped / black / display of 8- or 16-bit sRGB codes (module docstring)."""
    full = np.iinfo(codes.dtype).max
    peak = _channel_max(codes)
    display = codes if full == 255 else ((codes.astype(np.uint32) * 255 + full // 2) // full).astype(np.uint8)
    return {"linear": _decode_lut(8 * codes.itemsize)[codes], "clipped": peak == full,
            "black": peak <= BLACK_CODE_8BIT * full // 255, "display": display}


# --- encodings and orientation ------------------------------------------------------------------

def srgb_to_linear(v):
    """Exact inverse sRGB transfer function (IEC 61966-2-1) of values in [0, 1], float64."""
    v = np.asarray(v, np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


BLACK_LINEAR = float(srgb_to_linear(BLACK_CODE_8BIT / 255))


@lru_cache(maxsize=2)
def _decode_lut(bits: int) -> np.ndarray:
    full = (1 << bits) - 1
    return srgb_to_linear(np.arange(full + 1) / full).astype(np.float32)


@lru_cache(maxsize=1)
def _encode_lut() -> np.ndarray:
    x = np.arange(65536) / 65535.0
    return np.round(255 * np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)).astype(np.uint8)


def _srgb8(linear: np.ndarray) -> np.ndarray:
    """uint8 sRGB codes of linear values (clipped to [0, 1], quantised to 16 bits, then a LUT)."""
    return _encode_lut()[(np.clip(linear, 0.0, 1.0) * 65535 + 0.5).astype(np.uint16)]


def _preview_scale(linear: np.ndarray, target: float) -> float:
    """Factor mapping the 99th percentile of Rec.709 luminance to ``target`` (1 for a black image)."""
    p99 = float(np.percentile(linear @ LUMA, 99))
    return target / p99 if p99 > 0 else 1.0


def _channel_max(a: np.ndarray) -> np.ndarray:
    return np.maximum(np.maximum(a[..., 0], a[..., 1]), a[..., 2])  # much faster than a.max(axis=-1)


def _orient(a: np.ndarray, orientation: int) -> np.ndarray:
    """Apply EXIF orientation 1..8 to an (H, W, ...) array, as PIL.ImageOps.exif_transpose does."""
    ops = {1: lambda x: x, 2: lambda x: x[:, ::-1], 3: lambda x: x[::-1, ::-1], 4: lambda x: x[::-1],
           5: lambda x: x.swapaxes(0, 1), 6: lambda x: np.rot90(x, -1),
           7: lambda x: x[::-1, ::-1].swapaxes(0, 1), 8: lambda x: np.rot90(x, 1)}
    return np.ascontiguousarray(ops[orientation](a))


# --- EXIF ---------------------------------------------------------------------------------------

def _number(value, rational: bool = False) -> float | None:
    """Positive finite float of a Pillow/exifread value (IFDRational, Ratio, int, 1-tuple, (num, den))."""
    if isinstance(value, (list, tuple)):
        if rational and len(value) == 2 and all(isinstance(v, int) for v in value):
            value = value[0] / value[1] if value[1] else None
        else:
            value = value[0] if value else None
    try:
        x = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return x if math.isfinite(x) and x > 0 else None


def _text(value) -> str | None:
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    return (value.strip("\x00 \t\r\n") if isinstance(value, str) else "") or None


def _pillow_tags(im) -> dict:
    """{tag name: raw value} from Pillow's IFD0 and Exif sub-IFD; {} when the EXIF is unreadable."""
    try:
        exif = im.getexif()
        merged = {**dict(exif), **dict(exif.get_ifd(0x8769))}
    except Exception:  # noqa: BLE001 - broken EXIF never makes a photo unusable
        return {}
    return {name: merged[tag] for name, tag in EXIF_TAG_IDS.items() if tag in merged}


def _exifread_tags(path: str) -> dict:
    """{tag name: raw value} via exifread (RAW and TIFF); {} when it finds nothing usable."""
    import exifread

    try:
        with open(path, "rb") as fh:
            tags = exifread.process_file(fh, details=False)
    except Exception:  # noqa: BLE001 - broken EXIF never makes a photo unusable
        return {}
    found = {name: tags.get(f"EXIF {name}") or tags.get(f"Image {name}") for name in EXIF_TAG_IDS}
    return {name: tag.values for name, tag in found.items() if tag is not None}


def _exif_summary(tags: dict) -> dict:
    """The JSON-able ``Photo.exif``: only valid values, under the names of the ``Photo`` contract."""
    out = {}
    for key, name in [("exposure_s", "ExposureTime"), ("f_number", "FNumber"), ("iso", "ISOSpeedRatings"),
                      ("focal_length_mm", "FocalLength"), ("focal_35mm_mm", "FocalLengthIn35mmFilm")]:
        x = _number(tags.get(name), name in RATIONAL_TAGS)
        if x is not None:
            out[key] = int(round(x)) if key == "iso" else x
    for key, name in [("make", "Make"), ("model", "Model"), ("datetime_original", "DateTimeOriginal")]:
        if (text := _text(tags.get(name))) is not None:
            out[key] = text
    return out


def _orientation(tags: dict) -> int:
    value = _number(tags.get("Orientation"))
    return int(value) if value in (1, 2, 3, 4, 5, 6, 7, 8) else 1


def _exif_size_scale(tags: dict, shape) -> float:
    """Decoded long side over the EXIF pixel dimensions' long side (1 when they are absent)."""
    width, height = _number(tags.get("ExifImageWidth")), _number(tags.get("ExifImageLength"))
    return max(shape[:2]) / max(width, height) if width and height else 1.0


def _focal(tags: dict, exif: dict, shape, sensor_scale: float, default_f35: float) -> tuple[float, str]:
    diagonal = math.hypot(shape[0], shape[1])
    if "focal_35mm_mm" in exif:
        return exif["focal_35mm_mm"] / DIAGONAL_35MM_MM * diagonal, "exif-35mm"
    resolution = _number(tags.get("FocalPlaneXResolution"), rational=True)
    unit_mm = FOCAL_PLANE_UNIT_MM.get(int(_number(tags.get("FocalPlaneResolutionUnit")) or 2))
    if "focal_length_mm" in exif and resolution and unit_mm:
        return exif["focal_length_mm"] * resolution / unit_mm * sensor_scale, "exif-focal-plane"
    return default_f35 / DIAGONAL_35MM_MM * diagonal, "default"


# --- decoders: each returns (kind, codes, masks, orientation, tags, sensor scale) -----------------

def _from_array(path, arr: np.ndarray, orientation: int):
    """(codes, masks) of an (H, W[, C]) uint8/uint16 (sRGB codes) or float (linear) array: integer
    codes are kept as they are (``Photo`` derives the rest), float gets its masks now."""
    arr = (arr[..., None] if arr.ndim == 2 else arr).astype(arr.dtype.newbyteorder("="), copy=False)
    arr = _orient(arr[..., :3] if arr.shape[-1] >= 3 else np.repeat(arr[..., :1], 3, axis=-1), orientation)
    if arr.dtype in (np.uint8, np.uint16):
        return arr, None
    if arr.dtype.kind != "f":
        raise PhotoError(path, f"unsupported sample type {arr.dtype}")
    if not np.isfinite(arr).all():
        raise PhotoError(path, "float image contains NaN or infinite values")
    linear = np.maximum(arr.astype(np.float32), 0.0)
    scale = np.float32(_preview_scale(linear, FLOAT_PREVIEW_P99))
    black = _channel_max(linear) * scale <= BLACK_LINEAR
    return linear, (_srgb8(linear * scale), np.zeros(linear.shape[:2], bool), black)


def _pillow_array(path, im) -> np.ndarray:
    if im.mode.startswith("I;16"):
        return np.asarray(im).astype(np.uint16)
    if im.mode == "I" and im.format == "PNG":  # 16-bit greyscale PNG in older Pillow versions
        return np.clip(np.asarray(im), 0, 65535).astype(np.uint16)
    if im.mode == "F":
        return np.asarray(im, np.float32)
    if im.mode.startswith("I"):
        raise PhotoError(path, f"unsupported {im.format} pixel mode {im.mode} (32-bit integers)")
    # 1, L, P, LA, RGB, RGBA, CMYK, YCbCr...: RGB, alpha dropped. Copied out in strips: whole,
    # numpy's copy goes through a bytes object of the same size (and convert() through a second
    # Pillow buffer), tripling a large photo's footprint.
    w, h = im.size
    out = np.empty((h, w, 3), np.uint8)
    step = max(1, (1 << 20) // max(1, w))
    for y0 in range(0, h, step):
        strip = im.crop((0, y0, w, min(h, y0 + step)))
        out[y0 : y0 + step] = np.asarray(strip if strip.mode == "RGB" else strip.convert("RGB"))
    return out


@contextlib.contextmanager
def _no_pillow_bomb_guard():
    """Pillow's decompression-bomb guard (a warning on stderr above 89 MP, an error above 179 MP)
    is replaced by f2l's own limit (:func:`_check_pixels`), checked before decoding."""
    from PIL import Image

    saved = Image.MAX_IMAGE_PIXELS
    Image.MAX_IMAGE_PIXELS = None
    try:
        yield
    finally:
        Image.MAX_IMAGE_PIXELS = saved


def _decode_pillow(path: str, max_pixels: int | None = None):
    from PIL import Image, UnidentifiedImageError

    try:
        with _no_pillow_bomb_guard(), Image.open(path) as im:
            kind = PILLOW_KINDS.get(im.format)
            if kind is None:
                raise PhotoError(path, f"unsupported image format {im.format} (use RAW, JPEG, PNG or TIFF)")
            _check_pixels(path, im.size[0], im.size[1], max_pixels)
            try:
                im.load()  # decodes everything now, so truncation is detected here
            except (OSError, SyntaxError, ValueError, EOFError, struct.error, zlib.error) as e:
                raise PhotoError(path, f"truncated or corrupt {im.format} ({e})") from e
            tags = _exifread_tags(path) if kind == "tiff" else _pillow_tags(im)
            arr = _pillow_array(path, im)
    except UnidentifiedImageError as e:
        raise PhotoError(path, "not a recognised image (unknown or unsupported format)") from e
    except Image.DecompressionBombError as e:
        raise PhotoError(path, f"image too large ({e})") from e
    except OSError as e:
        raise PhotoError(path, f"cannot read image ({e})") from e
    orientation = _orientation(tags)
    return (kind, *_from_array(path, arr, orientation), orientation, tags, _exif_size_scale(tags, arr.shape))


def _decode_tiff(path: str, max_pixels: int | None = None):
    """TIFF through tifffile (16-bit RGB, float); layouts or codecs it lacks go to Pillow."""
    try:
        import tifffile
    except ImportError:
        return _decode_pillow(path, max_pixels)
    try:
        with tifffile.TiffFile(path) as tf:
            page = tf.pages[0]
            _check_pixels(path, int(page.imagewidth), int(page.imagelength), max_pixels)
            ends = [offset + count for offset, count in zip(page.dataoffsets, page.databytecounts)]
            truncated = bool(ends) and max(ends) > os.path.getsize(path)
            usable = page.photometric in (tifffile.PHOTOMETRIC.MINISBLACK, tifffile.PHOTOMETRIC.RGB)
            arr = page.asarray() if usable and not truncated else None
            if arr is not None and page.planarconfig == tifffile.PLANARCONFIG.SEPARATE and arr.ndim == 3:
                arr = np.moveaxis(arr, 0, -1)
    except PhotoError:
        raise
    except Exception:  # noqa: BLE001 - unknown codec, odd layout or corrupt: Pillow decides
        return _decode_pillow(path, max_pixels)
    if truncated:
        raise PhotoError(path, "truncated TIFF (image data runs past the end of the file)")
    if arr is None or arr.ndim not in (2, 3) or f"{arr.dtype.kind}{arr.itemsize}" not in ("u1", "u2", "f2", "f4", "f8"):
        return _decode_pillow(path, max_pixels)
    tags = _exifread_tags(path)
    orientation = _orientation(tags)
    return ("tiff", *_from_array(path, arr, orientation), orientation, tags, _exif_size_scale(tags, arr.shape))


def _raw_clipped(raw, half_size: bool) -> np.ndarray | None:
    """Saturated pixels from the photosites, on LibRaw's output grid before its flip (None: not a 2x2 CFA).

    A photosite of colour c is saturated when (v - black_c) * wb_c >= 0.98 (white - black_c), with
    the camera white balance wb normalised to a minimum of 1: LibRaw clips each white-balanced
    channel at full scale *before* the colour matrix, so strongly amplified channels (red, blue)
    clip below the white level. It is also saturated when v >= black_c + 0.98 (sat - black_c), sat
    being the data maximum when that lies within 75-100 % of the white level (LibRaw's
    adjust_maximum rule for sensors that saturate early; used only here, never for scaling).
    A pixel is clipped when any photosite of its 2x2 CFA block is: half size has one pixel per
    block; full size marks the block dilated by one pixel (demosaicing spreads values).
    Must run before ``postprocess`` (which shrinks the raw data in place for half size).
    """
    if raw.raw_pattern is None or raw.raw_pattern.shape != (2, 2) or raw.num_colors < 3:
        return None
    values = raw.raw_image_visible  # unpacks the RAW data
    pattern = raw.raw_colors_visible[:2, :2]
    black = np.asarray(raw.black_level_per_channel, np.float64)
    white = float(raw.white_level)
    wb = np.asarray(raw.camera_whitebalance, np.float64)
    wb = wb if wb[0] > 0 and wb[2] > 0 else np.asarray(raw.daylight_whitebalance, np.float64)  # LibRaw's fallback
    wb[1] = wb[1] if wb[1] > 0 else 1.0
    wb[3] = wb[3] if wb[3] > 0 else wb[1]
    wb /= wb.min()
    data_max = float(values.max())
    saturation = data_max if 0.75 * white < data_max < white else white
    threshold = np.ceil(np.minimum(black + CLIP_FRACTION * (white - black) / wb,
                                   black + CLIP_FRACTION * (saturation - black)))
    h, w = values.shape
    blocks = np.zeros(((h + 1) // 2, (w + 1) // 2), bool)
    for i in (0, 1):
        for j in (0, 1):
            hit = values[i::2, j::2] >= threshold[pattern[i, j]]
            blocks[: hit.shape[0], : hit.shape[1]] |= hit
    if half_size:
        return blocks
    from scipy.ndimage import binary_dilation

    return binary_dilation(np.repeat(np.repeat(blocks, 2, axis=0), 2, axis=1)[:h, :w], np.ones((3, 3), bool))


def _decode_raw(path: str, half_size: bool, max_pixels: int | None = None):
    import rawpy

    try:
        with rawpy.imread(path) as raw:
            orientation = LIBRAW_FLIP_TO_ORIENTATION.get(raw.sizes.flip, 1)
            div = 2 if half_size else 1
            _check_pixels(path, raw.sizes.width // div, raw.sizes.height // div, max_pixels)
            sensor_clipped = _raw_clipped(raw, half_size)
            rgb = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=True,
                                  half_size=half_size, output_color=rawpy.ColorSpace.sRGB, user_flip=None,
                                  adjust_maximum_thr=0.0)
    except rawpy.LibRawError as e:
        message = e.args[0].decode("utf-8", "replace") if e.args and isinstance(e.args[0], bytes) else str(e)
        if isinstance(e, rawpy.LibRawFileUnsupportedError):
            raise PhotoError(path, f"not a supported photo: not JPEG/PNG/TIFF, and LibRaw says: {message}") from None
        state = "truncated or unreadable" if isinstance(e, rawpy.LibRawIOError) else "corrupt or undecodable"
        raise PhotoError(path, f"{state} RAW file (LibRaw {type(e).__name__}: {message})") from e
    except PhotoError:
        raise
    except (OSError, ValueError) as e:
        raise PhotoError(path, f"cannot decode RAW file ({e})") from e
    if rgb.ndim != 3 or rgb.shape[-1] != 3 or rgb.dtype != np.uint16:
        raise PhotoError(path, f"unexpected LibRaw output {rgb.shape} {rgb.dtype}")
    peak = _channel_max(rgb)
    clipped = peak >= CLIP_FRACTION * 65535
    if sensor_clipped is not None and (sensor_clipped := _orient(sensor_clipped, orientation)).shape == clipped.shape:
        clipped |= sensor_clipped  # shapes differ only for odd sensors (e.g. Fuji SuperCCD): output test only
    linear = rgb.astype(np.float32) / np.float32(65535)
    code_scale = np.float32(_preview_scale(linear, RAW_PREVIEW_P99) / 65535)
    display = _srgb8(np.arange(65536, dtype=np.float32) * code_scale)[rgb]  # per-code LUT: fast
    black = peak <= math.floor(BLACK_LINEAR * 65535)
    return "raw", linear, (display, clipped, black), orientation, _exifread_tags(path), 0.5 if half_size else 1.0


# --- entry point --------------------------------------------------------------------------------

def _sniff(head: bytes) -> str | None:
    signatures = {b"\xff\xd8\xff": "jpeg", b"\x89PNG\r\n\x1a\n": "png", b"II*\x00": "tiff", b"MM\x00*": "tiff"}
    return next((kind for magic, kind in signatures.items() if head.startswith(magic)), None)


def max_photo_pixels() -> int:
    """The pixel limit: ``$F2L_MAX_PHOTO_PIXELS`` when set, else ``MAX_PIXELS``."""
    value = os.environ.get("F2L_MAX_PHOTO_PIXELS")
    try:
        return int(float(value)) if value else MAX_PIXELS
    except ValueError:
        return MAX_PIXELS


def _check_pixels(path: str, width: int, height: int, max_pixels: int | None) -> None:
    limit = max_photo_pixels() if max_pixels is None else int(max_pixels)
    if width * height > limit:
        raise PhotoError(path, f"image is {width}x{height} = {width * height / 1e6:.0f} MP, above the "
                               f"{limit / 1e6:.0f} MP limit (F2L_MAX_PHOTO_PIXELS); not decoded")


def load_photo(path, *, raw_half_size: bool = True, default_focal_35mm_mm: float = DEFAULT_FOCAL_35MM_MM,
               max_pixels: int | None = None) -> Photo:
    """Decode one photo (conventions: module docstring); bad input raises :class:`PhotoError`.

    A photo of more than ``max_pixels`` (default :func:`max_photo_pixels`) is refused from its
    header, before anything is decoded (RAW: the output size at ``raw_half_size``).

    JPEG/PNG content and ``.jpg``/``.png``/``.tif``/``.tiff`` files are decoded as images; anything
    else goes to LibRaw (any RAW it knows: CR2, CR3, NEF, ARW, DNG, RAF, ORF, RW2, PEF, SRW, ...).
    ``raw_half_size`` makes each 2x2 CFA block one pixel (half width and height, no demosaicing).
    """
    if not (math.isfinite(default_focal_35mm_mm) and default_focal_35mm_mm > 0):
        raise ValueError(f"default_focal_35mm_mm must be positive, got {default_focal_35mm_mm}")
    path = os.fspath(path)
    p = Path(path)
    if not p.exists():
        raise PhotoError(path, "no such file")
    if not p.is_file():
        raise PhotoError(path, "not a regular file")
    try:
        with open(p, "rb") as fh:
            head = fh.read(16)
    except OSError as e:
        raise PhotoError(path, f"cannot read file ({e.strerror or e})") from e
    if not head:
        raise PhotoError(path, "zero-byte file")
    sniffed, suffix = _sniff(head), p.suffix.lower()
    if sniffed == "tiff" and suffix in (".tif", ".tiff"):
        decoded = _decode_tiff(path, max_pixels)
    elif sniffed in ("jpeg", "png") or suffix in RASTER_EXTENSIONS:
        decoded = _decode_pillow(path, max_pixels)
    else:
        decoded = _decode_raw(path, raw_half_size, max_pixels)
    kind, codes, masks, orientation, tags, sensor_scale = decoded
    height, width = codes.shape[:2]
    if height < MIN_SIZE or width < MIN_SIZE:
        raise PhotoError(path, f"image is {width}x{height} pixels; at least {MIN_SIZE}x{MIN_SIZE} needed")
    if codes.dtype.kind == "f" and not np.isfinite(codes).all():
        raise PhotoError(path, "decoded image contains NaN or infinite values")
    exif = _exif_summary(tags)
    focal_px, focal_source = _focal(tags, exif, codes.shape, sensor_scale, default_focal_35mm_mm)
    return Photo(path=path, kind=kind, codes=codes, masks=masks, focal_px=float(focal_px),
                 focal_source=focal_source, orientation=orientation, exif=exif)
