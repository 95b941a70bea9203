"""The decoded photo (:class:`Photo`), its errors, and the sample-code arithmetic it rests on.

Conventions of :class:`Photo` are stated in :mod:`f2l.io.photo`, which decodes files into it:
sRGB codes <-> linear values (IEC 61966-2-1, exact inverse), the derived ``clipped`` / ``black``
masks, EXIF orientation, the box reduction used for face detection, and the switch that replaces
Pillow's decompression-bomb guard by f2l's own pixel limit.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

BLACK_CODE_8BIT = 2
LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


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
