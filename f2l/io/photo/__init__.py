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

Modules: this one decodes whole photos and is the entry point (:func:`load_photo`);
:mod:`f2l.io.photo.core` holds :class:`Photo` and the code arithmetic, :mod:`f2l.io.photo.exif`
the ``Photo.exif`` fields and focal length, :mod:`f2l.io.photo.metadata` the one EXIF/RAW metadata
reader behind them (also used by :mod:`f2l.io.raw_meta` and :mod:`f2l.io.capture`),
:mod:`f2l.io.photo.stream` the streamed decoding of large photos.
"""

from __future__ import annotations

import math
import os
import struct
import zlib
from pathlib import Path
from typing import NamedTuple

import numpy as np

from f2l.io.photo.core import (  # noqa: F401 - re-exported: the public API of photo decoding
    BLACK_CODE_8BIT, BLACK_LINEAR, LUMA, Photo, PhotoError, _channel_max, _no_pillow_bomb_guard, _orient,
    _preview_scale, _srgb8, srgb_to_linear,
)
from f2l.io.photo.exif import (  # noqa: F401
    DEFAULT_FOCAL_35MM_MM, DIAGONAL_35MM_MM, _exif_size_scale, _exif_summary, _file_metadata, _focal,
    _pillow_metadata,
)
from f2l.io.photo.metadata import PhotoMetadata
from f2l.io.photo.stream import _CAN_STREAM_PILLOW, StreamedPhoto, _PillowSource, _TiffSource  # noqa: F401

MIN_SIZE = 16
# Photos above this many pixels are refused before decoding (override: $F2L_MAX_PHOTO_PIXELS). At
# 250 MP a 16-bit RGB source alone is 1.5 GB; fit-faces reads only rows it samples beyond that.
MAX_PIXELS = 250_000_000
# Faces are detected on a copy reduced to this long side (fit.py), then fitted at full resolution.
DETECTION_MAX_SIDE = 4096
CLIP_FRACTION = 0.98  # RAW: fraction of full scale (or of the sensor's saturation level) that counts as clipped
RAW_PREVIEW_P99, FLOAT_PREVIEW_P99 = 0.8, 0.9
RASTER_EXTENSIONS = {".jpg", ".jpeg", ".jpe", ".png", ".tif", ".tiff"}
PILLOW_KINDS = {"JPEG": "jpeg", "MPO": "jpeg", "PNG": "png", "TIFF": "tiff"}
# LibRaw ``sizes.flip`` (dcraw bits: 4 transpose, 2 flip rows, 1 flip columns) -> EXIF orientation:
# the inverse of dcraw's table "50132467"[orientation]; checked against postprocess(user_flip=...).
LIBRAW_FLIP_TO_ORIENTATION = {0: 1, 1: 2, 2: 4, 3: 3, 4: 5, 5: 8, 6: 6, 7: 7}


# --- encodings and orientation ------------------------------------------------------------------


# --- EXIF ---------------------------------------------------------------------------------------


# --- decoders: each returns (kind, codes, masks, orientation, metadata, sensor scale) -------------

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
                                 _pillow_metadata(im) if kind == "jpeg" else None)
            try:
                im.load()  # decodes everything now, so truncation is detected here
            except (OSError, SyntaxError, ValueError, EOFError, struct.error, zlib.error) as e:
                raise PhotoError(path, f"truncated or corrupt {im.format} ({e})") from e
            meta = _file_metadata(path) if kind == "tiff" else _pillow_metadata(im)
            arr = _pillow_array(path, im)
    except UnidentifiedImageError as e:
        raise PhotoError(path, "not a recognised image (unknown or unsupported format)") from e
    except Image.DecompressionBombError as e:
        raise PhotoError(path, f"image too large ({e})") from e
    except OSError as e:
        raise PhotoError(path, f"cannot read image ({e})") from e
    orientation = meta.orientation
    return (kind, *_from_array(path, arr, orientation), orientation, meta, _exif_size_scale(meta, arr.shape))


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
        return _Streamed("tiff", _TiffSource(path), (height, width), _file_metadata(path))
    if arr is None or arr.ndim not in (2, 3) or f"{arr.dtype.kind}{arr.itemsize}" not in ("u1", "u2", "f2", "f4", "f8"):
        return _decode_pillow(path, max_pixels)
    meta = _file_metadata(path)
    orientation = meta.orientation
    return ("tiff", *_from_array(path, arr, orientation), orientation, meta, _exif_size_scale(meta, arr.shape))


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
    return "raw", linear, (display, clipped, black), orientation, _file_metadata(path), 0.5 if half_size else 1.0


# --- entry point --------------------------------------------------------------------------------

def _sniff(head: bytes) -> str | None:
    signatures = {b"\xff\xd8\xff": "jpeg", b"\x89PNG\r\n\x1a\n": "png", b"II*\x00": "tiff", b"MM\x00*": "tiff"}
    return next((kind for magic, kind in signatures.items() if head.startswith(magic)), None)


class _Streamed(NamedTuple):
    """A photo to stream: its source, stored (H, W) and metadata (None: the reduced pass reads it)."""

    kind: str
    source: object
    stored_shape: tuple[int, int]
    meta: PhotoMetadata | None


def _stream_wanted(stream: bool | None, width: int, height: int) -> bool:
    return bool(stream) or (stream is None and max(width, height) > DETECTION_MAX_SIDE)


def _load_streamed(path: str, streamed: _Streamed, default_focal_35mm_mm: float, whole) -> StreamedPhoto | None:
    """A :class:`StreamedPhoto` with its reduced copy made now (which also checks that the data
    decodes); None when the photo cannot be streamed after all (then it is decoded whole)."""
    h, w = streamed.stored_shape
    if h < MIN_SIZE or w < MIN_SIZE:
        raise PhotoError(path, f"image is {w}x{h} pixels; at least {MIN_SIZE}x{MIN_SIZE} needed")
    try:
        reduced, meta = streamed.source.reduce(DETECTION_MAX_SIDE)
    except PhotoError:
        raise
    except Exception:  # noqa: BLE001 - a layout, codec or platform the streamed path lacks
        return None
    meta = streamed.meta if streamed.meta is not None else (meta or PhotoMetadata())
    orientation = meta.orientation
    photo = StreamedPhoto(path, streamed.kind, streamed.source, (h, w), orientation, reduced, whole)
    exif = _exif_summary(meta)
    photo.exif = exif
    focal_px, photo.focal_source = _focal(meta, exif, photo.shape, _exif_size_scale(meta, photo.shape),
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
    kind, codes, masks, orientation, meta, sensor_scale = decoded
    height, width = codes.shape[:2]
    if height < MIN_SIZE or width < MIN_SIZE:
        raise PhotoError(path, f"image is {width}x{height} pixels; at least {MIN_SIZE}x{MIN_SIZE} needed")
    if codes.dtype.kind == "f" and not np.isfinite(codes).all():
        raise PhotoError(path, "decoded image contains NaN or infinite values")
    exif = _exif_summary(meta)
    focal_px, focal_source = _focal(meta, exif, codes.shape, sensor_scale, default_focal_35mm_mm)
    return Photo(path=path, kind=kind, codes=codes, masks=masks, focal_px=float(focal_px),
                 focal_source=focal_source, orientation=orientation, exif=exif)
