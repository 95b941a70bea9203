"""Float32 OpenEXR I/O for light probes and HDR images.

Probes are written as three FLOAT (32-bit, never HALF: the sun exceeds half's 65,504 by orders
of magnitude) channels R, G, B, ZIP-compressed, scanline, atomically (temp file in the same
directory, then ``os.replace``). Values are linear scene-referred radiance, so NaN/inf and
negatives below -1e-6 are rejected on write. Optional string metadata is stored as extra header
attributes. Any unreadable, corrupt, truncated or missing file raises ``ExrError("path: reason")``.

Hostile files: the header's data window is checked before any pixel is decoded; an image of more
than :data:`MAX_DECODE_PIXELS` pixels is refused (naming the file and its size) instead of
allocating what the header claims (a 1-MB file may claim 100000 x 50000 float pixels, 60 GB).
Raise the limit with the environment variable ``F2L_MAX_DECODE_PIXELS`` or the ``max_pixels``
argument; :func:`f2l.io.probe_io.read_hdr_image` reads larger images in bands, downsampled to the
size its caller needs. What OpenEXR's C++ library prints itself (e.g. "Warning: Exception raised
reading pixel data for part 0 - ...", on stdout) goes to the debug log (``f2l --debug-log``),
never to stdout or stderr.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

import OpenEXR

from f2l.io.atomic import atomic_path

__all__ = ["ExrError", "write_exr", "read_exr", "read_exr_with_metadata", "exr_size",
           "REC709_CHROMATICITIES", "NEGATIVE_TOLERANCE", "MAX_DECODE_PIXELS", "DECODE_PIXELS_ENV",
           "decode_pixel_limit", "quiet_native", "too_large_message"]

_log = logging.getLogger(__name__)

MAX_DECODE_PIXELS = 2**25
"""Most pixels (width x height; 33,554,432, e.g. an 8192 x 4096 lat-long HDRI or a 6000 x 4000
photo) an image reader decodes at once: about 400 MB as float32 RGB, twice that while OpenEXR's
channels are stacked. Larger images are refused by :func:`read_exr`, and read in bands and
downsampled by :func:`f2l.io.probe_io.read_hdr_image` when its caller gives a target size. Raise it
with the environment variable ``F2L_MAX_DECODE_PIXELS`` (an integer) or a ``max_pixels`` argument."""

DECODE_PIXELS_ENV = "F2L_MAX_DECODE_PIXELS"
"""Environment variable that overrides :data:`MAX_DECODE_PIXELS`."""


def decode_pixel_limit(max_pixels: int | None = None) -> int:
    """The decode limit in pixels: ``max_pixels`` when given, else ``$F2L_MAX_DECODE_PIXELS``,
    else :data:`MAX_DECODE_PIXELS`. ValueError for a value that is not a positive integer."""
    if max_pixels is None:
        raw = os.environ.get(DECODE_PIXELS_ENV, "").strip()
        if not raw:
            return MAX_DECODE_PIXELS
        try:
            max_pixels = int(raw.replace("_", ""))
        except ValueError:
            raise ValueError(f"{DECODE_PIXELS_ENV}={raw!r}: not an integer number of pixels") from None
    if isinstance(max_pixels, bool) or int(max_pixels) != max_pixels or max_pixels < 1:
        raise ValueError(f"the decode limit must be a positive number of pixels, got {max_pixels!r}")
    return int(max_pixels)


def quiet_native(path):
    """Context manager: what native code (OpenEXR, OpenImageIO) prints to fd 1 or 2 while it reads
    ``path`` goes to this module's debug log (``f2l --debug-log``), never to stdout/stderr."""
    from f2l.io.native_stderr import native_output_to_log

    return native_output_to_log(_log, str(path))

NEGATIVE_TOLERANCE = 1e-6
"""Values in [-1e-6, 0) are accepted (rounding noise); anything more negative is an error."""

# Header attributes that OpenEXR manages itself; metadata may not override them.
_RESERVED = frozenset(
    {
        "channels", "compression", "dataWindow", "displayWindow", "lineOrder", "pixelAspectRatio",
        "screenWindowCenter", "screenWindowWidth", "type", "tiles", "name", "version",
        "chunkCount", "maxSamplesPerPixel", "view", "multiView",
    }
)  # fmt: skip


class ExrError(IOError):
    """An EXR file could not be read; the message is ``f"{path}: reason"``."""


def _as_rgb(image: np.ndarray, path) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"{path}: image must be (H, W) or (H, W, 3), got shape {np.shape(image)}")
    if not (np.issubdtype(img.dtype, np.floating) or np.issubdtype(img.dtype, np.integer)):
        raise ValueError(f"{path}: image dtype must be numeric, got {img.dtype}")
    with np.errstate(over="ignore"):
        img32 = img.astype(np.float32)
    if not np.all(np.isfinite(img32)):
        raise ValueError(f"{path}: image has NaN or infinite values (or exceeds float32 range)")
    low = float(img32.min())
    if low < -NEGATIVE_TOLERANCE:
        raise ValueError(f"{path}: image has negative values (min {low:g}); radiance must be >= 0")
    return img32


EXR_COMPRESSIONS = {"zip": OpenEXR.ZIP_COMPRESSION, "none": OpenEXR.NO_COMPRESSION}
"""Lossless codecs :func:`write_exr` offers. ZIP is the default; "none" is for large intermediates
(a 1-MP float32 view: ZIP 0.16 s for 5% smaller, none 0.01 s)."""


REC709_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)
"""Red, green, blue and white (D65) CIE xy of linear Rec.709, as EXR's ``chromaticities`` attribute."""


def write_exr(path: str | os.PathLike, image: np.ndarray, metadata: dict[str, str] | None = None, *,
              compression: str = "zip", chromaticities: tuple[float, ...] | None = None) -> None:
    """Write ``image`` (H, W, 3) or (H, W) (replicated to RGB) as a float32 RGB EXR.

    FLOAT channels R, G, B, ``compression`` one of :data:`EXR_COMPRESSIONS`; ``metadata`` is stored
    as string header attributes (names must not collide with standard EXR attributes). Atomic: a
    crash never leaves a partial file at ``path``. ``chromaticities`` (8 floats: xy of R, G, B,
    white; e.g. :data:`REC709_CHROMATICITIES`) is written as the standard attribute of that name.
    Raises ValueError naming the path for NaN/inf/negative values.
    """
    path = Path(path)
    img = _as_rgb(image, path)
    if compression not in EXR_COMPRESSIONS:
        raise ValueError(f"{path}: compression must be one of {sorted(EXR_COMPRESSIONS)}, got {compression!r}")
    header: dict = {"compression": EXR_COMPRESSIONS[compression], "type": OpenEXR.scanlineimage}
    for key, value in (metadata or {}).items():
        if not isinstance(key, str) or not isinstance(value, str):
            raise ValueError(f"{path}: metadata must map str to str, got {key!r}: {type(value).__name__}")
        if key in _RESERVED:
            raise ValueError(f"{path}: metadata key {key!r} is a reserved EXR attribute")
        header[key] = value
    if chromaticities is not None:
        if len(chromaticities) != 8:
            raise ValueError(f"{path}: chromaticities must be 8 numbers (xy of R, G, B, white)")
        header["chromaticities"] = tuple(float(v) for v in chromaticities)
    channels = {name: np.ascontiguousarray(img[:, :, i]) for i, name in enumerate("RGB")}

    with atomic_path(path) as tmp:
        OpenEXR.File(header, channels).write(tmp)


def _check_file(path: Path) -> None:
    if not path.exists():
        raise ExrError(f"{path}: file not found")
    if not path.is_file():
        raise ExrError(f"{path}: not a regular file")


def exr_size(path: str | os.PathLike) -> tuple[int, int]:
    """(height, width) of an EXR's data window (first part), from its header alone; ExrError."""
    path = Path(path)
    _check_file(path)
    try:
        with quiet_native(path):
            exr = OpenEXR.File(str(path), header_only=True)
            header = exr.header(0)
        lo, hi = header["dataWindow"]
        height, width = int(hi[1]) - int(lo[1]) + 1, int(hi[0]) - int(lo[0]) + 1
    except Exception as exc:  # OpenEXR raises RuntimeError/ValueError/... for bad files
        raise ExrError(f"{path}: unreadable EXR header ({exc})") from exc
    if height < 1 or width < 1:
        raise ExrError(f"{path}: empty or inverted data window ({width}x{height})")
    return height, width


def too_large_message(path, height: int, width: int, limit: int) -> str:
    """The refusal of an image over the decode limit: file, size, limit and how to raise it."""
    return (f"{path}: {width}x{height} image ({width * height:,} pixels) exceeds the decode limit of "
            f"{limit:,} pixels (set {DECODE_PIXELS_ENV} to raise it)")


def read_exr_with_metadata(path: str | os.PathLike, *, max_pixels: int | None = None
                           ) -> tuple[np.ndarray, dict[str, str]]:
    """Read an EXR: returns (image (H, W, 3) float32, string header attributes).

    Reads channels R, G, B (any pixel type, converted to float32) of the first part, or a single
    luminance channel Y replicated to RGB. Raises ExrError(f"{path}: reason") on any failure, and
    for an image of more than ``max_pixels`` pixels (default :func:`decode_pixel_limit`), checked
    on the header before any pixel is decoded.
    """
    path = Path(path)
    limit = decode_pixel_limit(max_pixels)
    height, width = exr_size(path)
    if height * width > limit:
        raise ExrError(too_large_message(path, height, width, limit))
    try:
        with quiet_native(path):
            exr = OpenEXR.File(str(path), separate_channels=True)
        parts = exr.parts
        if not parts:  # OpenEXR drops a part whose pixel data failed to decode
            raise ExrError(f"{path}: corrupt or truncated pixel data")
        header = exr.header(0)
        channels = exr.channels(0)
    except ExrError:
        raise
    except Exception as exc:  # OpenEXR raises RuntimeError/ValueError/... for bad files
        raise ExrError(f"{path}: unreadable EXR ({exc})") from exc

    names = set(channels)
    if {"R", "G", "B"} <= names:
        planes = [channels[c].pixels for c in "RGB"]
    elif "Y" in names:
        planes = [channels["Y"].pixels] * 3
    else:
        raise ExrError(f"{path}: no R, G, B (or Y) channels, found {sorted(names)}")
    try:
        lo, hi = header["dataWindow"]
        shape = (int(hi[1]) - int(lo[1]) + 1, int(hi[0]) - int(lo[0]) + 1)
        if any(p is None or np.shape(p) != shape for p in planes):
            raise ExrError(f"{path}: channel data missing or subsampled (expected {shape})")
        image = np.stack([np.asarray(p, dtype=np.float32) for p in planes], axis=-1)
    except ExrError:
        raise
    except Exception as exc:
        raise ExrError(f"{path}: bad pixel data ({exc})") from exc
    metadata = {k: v for k, v in header.items() if isinstance(v, str) and k not in _RESERVED}
    return image, metadata


def read_exr(path: str | os.PathLike, *, max_pixels: int | None = None) -> np.ndarray:
    """Read an EXR as (H, W, 3) float32 (see ``read_exr_with_metadata``)."""
    return read_exr_with_metadata(path, max_pixels=max_pixels)[0]
