"""Float32 OpenEXR I/O for light probes and HDR images.

Probes are written as three FLOAT (32-bit, never HALF: the sun exceeds half's 65,504 by orders
of magnitude) channels R, G, B, ZIP-compressed, scanline, atomically (temp file in the same
directory, then ``os.replace``). Values are linear scene-referred radiance, so NaN/inf and
negatives below -1e-6 are rejected on write. Optional string metadata is stored as extra header
attributes. Any unreadable, corrupt, truncated or missing file raises ``ExrError("path: reason")``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

import OpenEXR

from f2l.io.atomic import atomic_path

__all__ = ["ExrError", "write_exr", "read_exr", "read_exr_with_metadata",
           "REC709_CHROMATICITIES", "NEGATIVE_TOLERANCE"]

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


def read_exr_with_metadata(path: str | os.PathLike) -> tuple[np.ndarray, dict[str, str]]:
    """Read an EXR: returns (image (H, W, 3) float32, string header attributes).

    Reads channels R, G, B (any pixel type, converted to float32) of the first part, or a single
    luminance channel Y replicated to RGB. Raises ExrError(f"{path}: reason") on any failure.
    """
    path = Path(path)
    if not path.exists():
        raise ExrError(f"{path}: file not found")
    if not path.is_file():
        raise ExrError(f"{path}: not a regular file")
    try:
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


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """Read an EXR as (H, W, 3) float32 (see ``read_exr_with_metadata``)."""
    return read_exr_with_metadata(path)[0]
