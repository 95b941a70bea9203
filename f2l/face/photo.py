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

Large photos: a photo above ``MAX_PIXELS`` (250 MP; ``$F2L_MAX_PHOTO_PIXELS`` or ``max_pixels=``)
is refused from its header, before decoding, with a :class:`PhotoError` naming the file and both
sizes (Pillow's own decompression-bomb guard is off: this limit replaces it). A photo whose long
side exceeds ``DETECTION_MAX_SIDE`` is *streamed* (:class:`StreamedPhoto`): it is never held
whole. Faces are detected on a reduced copy (JPEG: libjpeg's DCT scaling through ``Image.draft``;
PNG: Pillow's own decoder run row block by row block into an anonymous mapping whose finished rows
are box-reduced and released; TIFF: strips or tiles one band at a time, or direct row reads when
uncompressed), and face fitting reads the full-resolution rows and columns around each face only
(:meth:`StreamedPhoto.rows`; JPEG/PNG decode again up to the face's last row). Memory is then about
the reduced copy plus the face's window, whatever the photo's size: `f2l fit-faces` on a
12,000 × 12,000 PNG without a face peaks at 0.23 GiB RSS (3.1 GiB when decoded whole as float,
1.1 GiB as whole 8-bit codes; measurements in ``docs/large_photos.md``). Streamed are 8-bit JPEG (RGB, grey),
non-interlaced PNG (RGB, RGBA, grey, grey+alpha, palette, 16-bit) and 8/16-bit integer TIFF, on
Linux (``madvise``); anything else (CMYK JPEG, interlaced PNG, float TIFF, RAW, other platforms)
is decoded whole as below, within the same pixel limit. A streamed photo's whole-image arrays
(``linear``, ``display``, ...) are still there for callers that need them (chart detection): the
first use decodes the photo whole. Photos within ``DETECTION_MAX_SIDE`` are decoded whole.
Within it, a whole photo costs its source codes (8/16-bit: kept as they are; ``linear``,
``clipped``, ``black`` are derived on first use) plus Pillow's buffer while decoding.

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
import mmap
import os
import struct
import sys
import zlib
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path
from typing import NamedTuple

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

    def detection_image(self, max_side: int) -> tuple[np.ndarray, float, tuple[float, float]]:
        """(display reduced so its long side is <= ``max_side``, scale, offset): a reduced pixel
        position p maps to ``offset + p / scale`` in the photo (x, y; here offset (0, 0), scale
        1 / f).

        An integer box reduction (the mean of f x f display pixels from the top-left corner),
        made from blocks of rows, so a large photo is never held in a second full-size form.
        Photos within the limit come back as ``display`` itself, scale 1."""
        h, w = self.shape
        f = _box_factor(h, w, max_side)
        if f == 1:
            return self.display, 1.0, (0.0, 0.0)
        reducer = _BoxReducer(f, (0, 0), (h // f, w // f))
        block = max(f, ((1 << 22) // max(1, w * f)) * f)  # whole blocks of rows (~4M source pixels)
        for r0 in range(0, (h // f) * f, block):
            rows = slice(r0, min(h, r0 + block))
            reducer(r0, self.codes[rows] if self.masks is None else self.masks[0][rows])
        return reducer.out, 1.0 / f, (0.0, 0.0)


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


def _decode_pillow(path: str, max_pixels: int | None = None, stream: bool | None = False):
    from PIL import Image, UnidentifiedImageError

    try:
        with _no_pillow_bomb_guard(), Image.open(path) as im:
            kind = PILLOW_KINDS.get(im.format)
            if kind is None:
                raise PhotoError(path, f"unsupported image format {im.format} (use RAW, JPEG, PNG or TIFF)")
            _check_pixels(path, im.size[0], im.size[1], max_pixels)
            if kind in ("jpeg", "png") and _stream_wanted(stream, *im.size) and _CAN_STREAM_PILLOW:
                # JPEG keeps its EXIF before the pixels; a PNG's is read by the streamed pass
                return _Streamed(kind, _PillowSource(path, kind), (im.size[1], im.size[0]),
                                 _pillow_tags(im) if kind == "jpeg" else None)
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


def _decode_tiff(path: str, max_pixels: int | None = None, stream: bool | None = False):
    """TIFF through tifffile (16-bit RGB, float); layouts or codecs it lacks go to Pillow."""
    try:
        import tifffile
    except ImportError:
        return _decode_pillow(path, max_pixels)
    try:
        with tifffile.TiffFile(path) as tf:
            page = tf.pages[0]
            width, height = int(page.imagewidth), int(page.imagelength)
            _check_pixels(path, width, height, max_pixels)
            ends = [offset + count for offset, count in zip(page.dataoffsets, page.databytecounts)]
            truncated = bool(ends) and max(ends) > os.path.getsize(path)
            usable = page.photometric in (tifffile.PHOTOMETRIC.MINISBLACK, tifffile.PHOTOMETRIC.RGB)
            streamable = (usable and not truncated and _stream_wanted(stream, width, height)
                          and np.dtype(page.dtype).str[1:] in ("u1", "u2") and page.imagedepth == 1
                          and page.fillorder == 1 and not page.is_subsampled)
            arr = page.asarray() if usable and not truncated and not streamable else None
            if arr is not None and page.planarconfig == tifffile.PLANARCONFIG.SEPARATE and arr.ndim == 3:
                arr = np.moveaxis(arr, 0, -1)
    except PhotoError:
        raise
    except Exception:  # noqa: BLE001 - unknown codec, odd layout or corrupt: Pillow decides
        return _decode_pillow(path, max_pixels)
    if truncated:
        raise PhotoError(path, "truncated TIFF (image data runs past the end of the file)")
    if streamable:
        return _Streamed("tiff", _TiffSource(path), (height, width), _exifread_tags(path))
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


# --- streamed decoding of large photos (module docstring) ----------------------------------------

# JPEG/PNG input is handed to Pillow's decoder in pieces of this size; between pieces the rows it
# has finished are consumed and their memory released. Deflate expands at most 1,032-fold (JPEG
# less), ~1,400-fold into Pillow's 4-byte pixels: the rows in flight stay within ~25 MB.
STREAM_CHUNK_BYTES = 16384
# Pillow modes streamed, with their bytes per pixel in Pillow's image memory.
_STREAM_MODES = {"RGB": 4, "RGBA": 4, "LA": 4, "L": 1, "P": 1, "I;16": 2}
_STREAM_DECODE_ERRORS = (OSError, SyntaxError, ValueError, EOFError, IndexError, struct.error, zlib.error)
# Streaming JPEG/PNG needs anonymous private mappings whose pages can be given back (madvise).
_CAN_STREAM_PILLOW = (sys.platform.startswith("linux") and hasattr(mmap, "MAP_ANONYMOUS")
                      and hasattr(mmap, "MADV_DONTNEED") and hasattr(mmap.mmap, "madvise"))


class _StreamUnavailable(Exception):
    """This photo cannot be streamed here: decode it whole."""


class _StopDecode(Exception):
    """The rows that were asked for have been read."""


def _box_factor(h: int, w: int, max_side: int) -> int:
    return max(1, math.ceil(max(h, w) / max(1, int(max_side))))


def _display_codes(codes: np.ndarray) -> np.ndarray:
    """uint8 display codes of 8- or 16-bit codes (as :func:`_code_planes`)."""
    if codes.dtype == np.uint8:
        return codes
    return ((codes.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)


class _BoxReducer:
    """Box reduction of rows fed in order, in blocks of any size: ``out[i, j]`` is the rounded mean
    of the display codes of rows ``r + i f .. r + (i + 1) f`` and columns ``c + j f ..`` (start
    (r, c)); the sum is exact and divided in float32, as numpy's mean of those integers."""

    def __init__(self, f: int, start: tuple[int, int], shape: tuple[int, int]):
        self.f, (self.r_start, self.c_start) = f, start
        self.out = np.zeros((shape[0], shape[1], 3), np.uint8)
        self._rows = np.zeros((shape[1] * f, 3), np.uint32)  # the current block's column sums

    def __call__(self, r0: int, codes: np.ndarray) -> None:
        f, (hr, wr) = self.f, self.out.shape[:2]
        lo, hi = max(r0, self.r_start), min(r0 + len(codes), self.r_start + hr * f)
        if hi <= lo:
            return
        part = _display_codes(codes[lo - r0 : hi - r0, self.c_start : self.c_start + wr * f])
        for k, r in enumerate(range(lo, hi)):  # row by row and column by column: numpy's fast paths
            self._rows += part[k]
            if (r - self.r_start) % f == f - 1:
                groups = self._rows.reshape(wr, f, 3)
                total = groups[:, 0].copy()
                for j in range(1, f):
                    total += groups[:, j]
                i = (r - self.r_start) // f
                self.out[i] = np.round(total.astype(np.float32) / np.float32(f * f)).astype(np.uint8)
                self._rows[:] = 0


class _Window:
    """Collects rows ``r0:r1``, columns ``c0:c1`` of rows fed in order."""

    def __init__(self, r0: int, r1: int, c0: int, c1: int):
        self.r0, self.r1, self.c0, self.c1 = r0, r1, c0, c1
        self.out: np.ndarray | None = None

    def __call__(self, start: int, codes: np.ndarray) -> None:
        lo, hi = max(start, self.r0), min(start + len(codes), self.r1)
        if hi <= lo:
            return
        if self.out is None:
            self.out = np.zeros((self.r1 - self.r0, self.c1 - self.c0, 3), codes.dtype)
        self.out[lo - self.r0 : hi - self.r0] = codes[lo - start : hi - start, self.c0 : self.c1]


class _ReduceTo:
    """A consumer box-reducing a stored image to a long side <= ``max_side`` (:class:`_BoxReducer`
    from the top-left corner); its size (and a decoder's own scale) is told by ``begin``."""

    def __init__(self, max_side: int):
        self.max_side = int(max_side)

    def begin(self, width: int, height: int, scale: int = 1) -> None:
        self.scale, self.f = scale, _box_factor(height, width, self.max_side)
        self.reducer = _BoxReducer(self.f, (0, 0), (height // self.f, width // self.f))

    def __call__(self, r0: int, codes: np.ndarray) -> None:
        self.reducer(r0, codes)

    def result(self) -> _Reduced:
        return _Reduced(self.reducer.out, self.scale * self.f, self.max_side)


@dataclass
class _Reduced:
    """A reduced copy in the stored frame: pixel j covers stored pixels [j f, (j + 1) f)."""

    image: np.ndarray  # (m_rows, m_cols, 3) uint8
    factor: int
    max_side: int


def _oriented_axes(orientation: int) -> tuple[tuple[int, bool], tuple[int, bool]]:
    """For the oriented rows and columns: (the stored axis they run along, reversed or not)."""
    probe = _orient(np.arange(6).reshape(2, 3), orientation)
    origin, down, right = (divmod(int(v), 3) for v in (probe[0, 0], probe[1, 0], probe[0, 1]))
    row_axis = 0 if down[0] != origin[0] else 1
    return ((row_axis, down[row_axis] < origin[row_axis]),
            (1 - row_axis, right[1 - row_axis] < origin[1 - row_axis]))


def _palette_lut(im) -> np.ndarray:
    """(256, 3) uint8 RGB of a P image's palette, read without loading the image."""
    rawmode, data = im.palette.getdata()
    if rawmode not in ("RGB", "RGBA", "RGBX"):
        raise _StreamUnavailable(f"palette mode {rawmode}")
    pal = np.frombuffer(data, np.uint8)
    pal = pal[: len(pal) // len(rawmode) * len(rawmode)].reshape(-1, len(rawmode))[:256, :3]
    lut = np.zeros((256, 3), np.uint8)
    lut[: len(pal)] = pal
    return lut


def _pillow_rows_rgb(raw: np.ndarray, mode: str, width: int, lut) -> np.ndarray:
    """(n, W, 3) codes of rows of Pillow's image memory (a view for the 4-byte modes)."""
    n = len(raw)
    if _STREAM_MODES[mode] == 4:  # RGB(X), RGBA and LA (stored L, L, L, A): the first three bytes
        return raw.reshape(n, width, 4)[..., :3]
    if mode == "P":
        return lut[raw]
    grey = raw.view("<u2").astype(np.uint16) if mode == "I;16" else raw
    return np.repeat(grey[..., None], 3, axis=-1)


def _pillow_scan(path: str, consume, stop: int | None = None, draft: int | None = None,
                 want_tags: bool = False) -> dict | None:
    """Decode a JPEG or PNG with Pillow's own decoder, row block by row block.

    The decoder writes into an anonymous private mapping of the image's size, fed
    ``STREAM_CHUNK_BYTES`` of input at a time; between pieces, the rows it has finished are
    passed to ``consume(first_row, codes)`` ((n, W, 3) uint8/uint16, stored frame, valid during
    the call) and their pages given back, so only the rows in flight are ever resident. A row is
    finished once a later one has been written (rows are written whole and in order): the RGB
    unpacker sets every pixel's fourth byte to 255 on fresh (zero) pages, and other modes get a
    pseudo-random 4-byte guard at the end of each row first (data equal to the guard only delays
    a row). Stops after row ``stop``. ``draft`` (JPEG): decode at 1/draft scale (libjpeg's DCT
    scaling). ``consume.begin(width, height, scale)`` is called first when it exists. Returns the
    Pillow tags (``want_tags``: read after decoding; a PNG may keep its EXIF after the pixels)."""
    from PIL import Image

    with _no_pillow_bomb_guard(), Image.open(path) as im:
        if draft:
            im.draft(im.mode, (im.size[0] // draft, im.size[1] // draft))
        mode, (w, h) = im.mode, im.size
        if (mode not in _STREAM_MODES or len(im.tile) != 1 or im.info.get("interlace")
                or getattr(im, "is_animated", False) or not _CAN_STREAM_PILLOW):
            raise _StreamUnavailable(f"{im.format} {mode}")
        stride = w * _STREAM_MODES[mode]
        try:
            lut = _palette_lut(im) if mode == "P" else None
            flags = mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | getattr(mmap, "MAP_NORESERVE", 0)
            mm = mmap.mmap(-1, stride * h, flags=flags)  # address space; pages only as written
            im.im = Image.core.map_buffer(mm, (w, h), "raw", 0, (mode, stride, 1))
        except (AttributeError, TypeError, ValueError, OSError) as e:
            raise _StreamUnavailable(str(e)) from e
        if hasattr(consume, "begin"):
            consume.begin(w, h, im.decoderconfig[0] if draft and im.decoderconfig else 1)
        raw = np.frombuffer(mm, np.uint8).reshape(h, stride)
        tail = raw[:, stride - 4 :]
        if mode == "RGB":
            guard = None
        else:
            guard = np.random.default_rng(h).integers(0, 256, size=(h, 4), dtype=np.uint8)
            tail[:] = guard
        done = 0

        def written(r: int) -> bool:
            return bool(tail[r, 3]) if guard is None else bool((tail[r] != guard[r]).any())

        def frontier() -> int:  # first row not known to be finished
            if done >= h or not written(done):
                return done
            lo, step = done, 1
            while True:
                hi = lo + step
                if hi >= h:
                    hi = h
                    break
                if not written(hi):
                    break
                lo, step = hi, step * 2
            while hi - lo > 1:
                mid = (lo + hi) // 2
                lo, hi = (mid, hi) if written(mid) else (lo, mid)
            return lo  # the last written row may still be in the decoder's hands: not yet

        def flush(final: bool = False) -> None:
            nonlocal done
            end = h if final else frontier()
            if end > done:
                consume(done, _pillow_rows_rgb(raw[done:end], mode, w, lut))
                a = done * stride // mmap.PAGESIZE * mmap.PAGESIZE
                b = len(mm) if final else end * stride // mmap.PAGESIZE * mmap.PAGESIZE
                if b > a:
                    mm.madvise(mmap.MADV_DONTNEED, a, b - a)
                done = end
            if stop is not None and done >= stop:
                raise _StopDecode

        read = im.load_read if hasattr(im, "load_read") else im.fp.read

        def load_read(n: int) -> bytes:
            flush()
            return read(n)

        im.load_read = load_read
        im.decodermaxblock = STREAM_CHUNK_BYTES
        tags = None
        try:
            try:
                im.load()
                flush(final=True)
            except _StopDecode:
                pass
            except _STREAM_DECODE_ERRORS as e:
                raise PhotoError(path, f"truncated or corrupt {im.format} ({e})") from e
            if want_tags:
                tags = _pillow_tags(im)
        finally:
            del raw, tail
            im.close()  # releases Pillow's view of the mapping
            with contextlib.suppress(BufferError):
                mm.close()
    return tags


class _PillowSource:
    """A streamed JPEG or PNG (:func:`_pillow_scan`)."""

    def __init__(self, path: str, kind: str):
        self.path, self.kind = path, kind

    def reduce(self, max_side: int) -> tuple[_Reduced, dict | None]:
        """The reduced copy (JPEG: libjpeg's DCT scaling by the power of two <= 8 that brings the
        long side nearest to ``max_side``, then a box; PNG: a box over every row) and the tags."""
        draft = None
        if self.kind == "jpeg":
            from PIL import Image

            with _no_pillow_bomb_guard(), Image.open(self.path) as im:
                f = _box_factor(im.size[1], im.size[0], max_side)
            draft = next((s for s in (2, 4) if s >= f), 8) if f > 1 else None
        reducer = _ReduceTo(max_side)
        tags = _pillow_scan(self.path, reducer, draft=draft, want_tags=True)
        return reducer.result(), tags

    def scan(self, consume, start: int = 0, stop: int | None = None) -> None:
        _pillow_scan(self.path, consume, stop=stop)


class _TiffSource:
    """A streamed 8/16-bit integer TIFF: rows read directly when the data is uncompressed and
    contiguous, otherwise one band of strips or tiles (all planes) decoded at a time."""

    def __init__(self, path: str):
        self.path = path

    def reduce(self, max_side: int) -> tuple[_Reduced, dict | None]:
        import tifffile

        with tifffile.TiffFile(self.path) as tf:
            page = tf.pages[0]
            width, height = int(page.imagewidth), int(page.imagelength)
        reducer = _ReduceTo(max_side)
        reducer.begin(width, height)
        self.scan(reducer)
        return reducer.result(), None

    def scan(self, consume, start: int = 0, stop: int | None = None) -> None:
        import tifffile

        with tifffile.TiffFile(self.path) as tf:
            page, fh = tf.pages[0], tf.filehandle
            h, w, spp = int(page.imagelength), int(page.imagewidth), int(page.samplesperpixel)
            stop = h if stop is None else min(int(stop), h)
            dtype = np.dtype(page.dtype).newbyteorder(tf.byteorder)
            if page.is_contiguous and (page.planarconfig == 1 or spp == 1):
                row_bytes = w * spp * dtype.itemsize
                step = max(1, (1 << 24) // row_bytes)
                for r0 in range(start, stop, step):
                    n = min(step, stop - r0)
                    fh.seek(page.dataoffsets[0] + r0 * row_bytes)
                    data = fh.read(n * row_bytes)
                    if len(data) < n * row_bytes:
                        raise PhotoError(self.path, "truncated TIFF (image data runs past the end of the file)")
                    consume(r0, _tiff_rgb(np.frombuffer(data, dtype).reshape(n, w, spp)))
                return
            band = int(page.tilelength if page.is_tiled else min(page.rowsperstrip, h))
            planes = spp if page.planarconfig == 2 and spp > 1 else 1
            bands, across = math.ceil(h / band), (math.ceil(w / page.tilewidth) if page.is_tiled else 1)
            if len(page.dataoffsets) != planes * bands * across:
                raise _StreamUnavailable("unexpected segment layout")
            args = {"_fullsize": bool(page.is_tiled)}
            if page.compression in (6, 7, 34892, 33007):  # JPEG
                args.update(jpegtables=page.jpegtables, jpegheader=page.jpegheader)
            for b in range(start // band, math.ceil(stop / band)):
                r0 = b * band
                n = min(band, h - r0)
                rows = np.zeros((n, w, spp), dtype.newbyteorder("="))
                for p in range(planes):
                    for t in range(across):
                        index = (p * bands + b) * across + t
                        if not page.databytecounts[index]:
                            continue
                        fh.seek(page.dataoffsets[index])
                        segment, at, _ = page.decode(fh.read(page.databytecounts[index]), index, **args)
                        if segment is None:
                            continue
                        c0 = int(at[3])
                        seg = segment[0, :n, : w - c0]
                        rows[:, c0 : c0 + seg.shape[1], p : p + seg.shape[2]] = seg
                consume(r0, _tiff_rgb(rows))


def _tiff_rgb(arr: np.ndarray) -> np.ndarray:
    """(n, W, 3) native-order codes of (n, W, S) TIFF samples, as :func:`_from_array` takes them."""
    arr = arr.astype(arr.dtype.newbyteorder("="), copy=False)
    return arr[..., :3] if arr.shape[-1] >= 3 else np.repeat(arr[..., :1], 3, axis=-1)


class StreamedPhoto:
    """A large photo read on demand (module docstring): what face fitting uses of :class:`Photo`
    (``shape``, :meth:`detection_image`, :meth:`rows`, the camera fields) without holding the
    photo; its whole-image arrays decode it whole on first use."""

    def __init__(self, path: str, kind: str, source, stored_shape: tuple[int, int], orientation: int,
                 reduced: _Reduced, whole):
        self.path, self.kind, self.orientation = path, kind, orientation
        self._source, self._stored_shape, self._reduced, self._whole_loader = source, stored_shape, reduced, whole
        self._windows: dict = {}
        self.focal_px, self.focal_source, self.exif = 0.0, "default", {}

    @property
    def shape(self) -> tuple[int, int]:
        (row_axis, _), _ = _oriented_axes(self.orientation)
        h, w = self._stored_shape
        return (h, w) if row_axis == 0 else (w, h)

    def detection_image(self, max_side: int) -> tuple[np.ndarray, float, tuple[float, float]]:
        """As :meth:`Photo.detection_image`; the reduction runs in the stored frame from its
        top-left corner, so with a flipped orientation (and for JPEG's DCT scaling, whose last
        block may be partial) the offset is not zero."""
        if self._reduced.max_side != int(max_side):
            self._reduced = self._source.reduce(max_side)[0]
        red = self._reduced
        offset = []
        for axis, flipped in _oriented_axes(self.orientation):
            n, m = self._stored_shape[axis], red.image.shape[axis]
            offset.append(float(n - red.factor * m) if flipped else 0.0)
        return _orient(red.image, self.orientation), 1.0 / red.factor, (offset[1], offset[0])

    def rows(self, index: np.ndarray, cols: slice = slice(None)) -> dict:
        """As :meth:`Photo.rows`: reads the full-resolution window spanning the rows and columns
        asked for (one pass over the file, unless :meth:`prefetch` read it)."""
        index = np.asarray(index, np.int64)
        h, w = self.shape
        col_index = np.arange(w)[cols]
        if len(index) == 0 or len(col_index) == 0:
            return _code_planes(np.zeros((len(index), len(col_index), 3), np.uint8))
        box = (int(index.min()), int(index.max()) + 1, int(col_index.min()), int(col_index.max()) + 1)
        if box not in self._windows:
            self.prefetch([box])
        return _code_planes(self._windows[box][index - box[0]][:, col_index - box[2]])

    def prefetch(self, boxes) -> None:
        """Read the full-resolution windows ``(r0, r1, c0, c1)`` (oriented rows and columns) in one
        pass over the file, replacing those read before."""
        self._windows = {}
        boxes = list(dict.fromkeys(tuple(int(v) for v in box) for box in boxes))
        if not boxes:
            return
        windows = [_Window(*self._stored_box(*box)) for box in boxes]

        def consume(start: int, codes: np.ndarray) -> None:
            for window in windows:
                window(start, codes)

        self._source.scan(consume, start=min(w.r0 for w in windows), stop=max(w.r1 for w in windows))
        for box, window in zip(boxes, windows):
            if window.out is None:
                raise PhotoError(self.path, f"rows {window.r0}..{window.r1} could not be read")
            self._windows[box] = _orient(window.out, self.orientation)

    def _stored_box(self, r0: int, r1: int, c0: int, c1: int) -> tuple[int, int, int, int]:
        """The stored-frame rows and columns of an oriented window."""
        stored = [(0, 0), (0, 0)]
        for (axis, flipped), (a, b) in zip(_oriented_axes(self.orientation), ((r0, r1), (c0, c1))):
            n = self._stored_shape[axis]
            stored[axis] = (n - b, n - a) if flipped else (a, b)
        return (*stored[0], *stored[1])

    @cached_property
    def whole(self) -> Photo:
        """The photo decoded whole (:class:`Photo`), for callers that need every pixel."""
        return self._whole_loader()

    codes = property(lambda self: self.whole.codes)
    masks = property(lambda self: self.whole.masks)
    linear = property(lambda self: self.whole.linear)
    display = property(lambda self: self.whole.display)
    clipped = property(lambda self: self.whole.clipped)
    black = property(lambda self: self.whole.black)


# --- entry point --------------------------------------------------------------------------------

def _sniff(head: bytes) -> str | None:
    signatures = {b"\xff\xd8\xff": "jpeg", b"\x89PNG\r\n\x1a\n": "png", b"II*\x00": "tiff", b"MM\x00*": "tiff"}
    return next((kind for magic, kind in signatures.items() if head.startswith(magic)), None)


class _Streamed(NamedTuple):
    """A photo to stream: its source, stored (H, W) and tags (None: the reduced pass reads them)."""

    kind: str
    source: object
    stored_shape: tuple[int, int]
    tags: dict | None


def _stream_wanted(stream: bool | None, width: int, height: int) -> bool:
    return bool(stream) or (stream is None and max(width, height) > DETECTION_MAX_SIDE)


def _load_streamed(path: str, streamed: _Streamed, default_focal_35mm_mm: float, whole) -> StreamedPhoto | None:
    """A :class:`StreamedPhoto` with its reduced copy made now (which also checks that the data
    decodes); None when the photo cannot be streamed after all (then it is decoded whole)."""
    h, w = streamed.stored_shape
    if h < MIN_SIZE or w < MIN_SIZE:
        raise PhotoError(path, f"image is {w}x{h} pixels; at least {MIN_SIZE}x{MIN_SIZE} needed")
    try:
        reduced, tags = streamed.source.reduce(DETECTION_MAX_SIDE)
    except PhotoError:
        raise
    except Exception:  # noqa: BLE001 - a layout, codec or platform the streamed path lacks
        return None
    tags = streamed.tags if streamed.tags is not None else (tags or {})
    orientation = _orientation(tags)
    photo = StreamedPhoto(path, streamed.kind, streamed.source, (h, w), orientation, reduced, whole)
    exif = _exif_summary(tags)
    photo.exif = exif
    focal_px, photo.focal_source = _focal(tags, exif, photo.shape, _exif_size_scale(tags, photo.shape),
                                          default_focal_35mm_mm)
    photo.focal_px = float(focal_px)
    return photo


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
               max_pixels: int | None = None, stream: bool | None = None) -> Photo | StreamedPhoto:
    """Decode one photo (conventions: module docstring); bad input raises :class:`PhotoError`.

    A photo of more than ``max_pixels`` (default :func:`max_photo_pixels`) is refused from its
    header, before anything is decoded (RAW: the output size at ``raw_half_size``).

    ``stream``: None streams JPEG/PNG/TIFF photos whose long side exceeds ``DETECTION_MAX_SIDE``
    (a :class:`StreamedPhoto`, its reduced copy decoded now); True streams any photo that can be,
    False none.

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
        decode = _decode_tiff
    elif sniffed in ("jpeg", "png") or suffix in RASTER_EXTENSIONS:
        decode = _decode_pillow
    else:
        decode = None
        decoded = _decode_raw(path, raw_half_size, max_pixels)
    if decode is not None:
        decoded = decode(path, max_pixels, stream)
        if isinstance(decoded, _Streamed):
            def whole() -> Photo:
                return load_photo(path, default_focal_35mm_mm=default_focal_35mm_mm, max_pixels=max_pixels,
                                  stream=False)

            photo = _load_streamed(path, decoded, default_focal_35mm_mm, whole)
            if photo is not None:
                return photo
            decoded = decode(path, max_pixels, False)
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
