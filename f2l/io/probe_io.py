"""HDR images in any format OpenImageIO reads: probes, flat fields, given environment maps.

:func:`read_hdr_image` returns (H, W, 3) float32 linear values, top row first, for
- OpenEXR (``.exr``): through OpenEXR (:func:`f2l.io.exr.read_exr`): it checks every chunk of a
  truncated or corrupt file and names the file, where OpenImageIO fills what it cannot read;
- Radiance RGBE (``.hdr``, ``.rgbe``), float TIFF (``.tif``, ``.tiff``), PFM (``.pfm``) and
  anything else OpenImageIO's wheel opens, through OpenImageIO. OpenImageIO 3.2 reads PFM rows in
  file order, but the PFM format stores the bottom row first: f2l flips them (tested against a
  file written to the format's definition).
One-channel images are replicated to RGB, a fourth (alpha) channel is dropped. NaN, inf and
negative values below -1e-6 are rejected. Every failure is ``ValueError(f"{path}: reason")``.

Memory is bounded by the work, not by what a header claims. The size is read from the header
first; an image of at most :data:`f2l.io.exr.MAX_DECODE_PIXELS` pixels (33,554,432; environment
variable ``F2L_MAX_DECODE_PIXELS`` or the ``max_pixels`` argument raise it) is decoded whole, as
above. A larger one is refused, naming the file and its size, unless the caller passes
``target_hw=(height, width)``, the lat-long size it resamples to anyway: then it is decoded
:data:`BAND_PIXELS` at a time through OpenImageIO (``read_scanlines``) and each band is
area-averaged into the target (:class:`f2l.lighting.resample.BandResampler`, the same weights as
:func:`f2l.lighting.resample.resample`), in O(band + target) memory. Images over
:data:`MAX_IMAGE_PIXELS` are refused from the header alone, target or not. Native libraries' own
messages go to the debug log (``f2l --debug-log``), never to stdout/stderr.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["read_hdr_image", "hdr_image_size", "HDR_IMAGE_EXTENSIONS", "BAND_PIXELS", "MAX_IMAGE_PIXELS"]

HDR_IMAGE_EXTENSIONS = (".exr", ".hdr", ".rgbe", ".tif", ".tiff", ".pfm")
"""Extensions f2l treats as linear HDR images (``f2l ingest`` lists ``.exr``/``.hdr``/``.pfm`` as probes)."""


BAND_PIXELS = 2**22
"""Pixels (4,194,304: about 50 MB as float32 RGB) decoded per band when an image over the decode
limit is read in bands (at least one row per band)."""

MAX_IMAGE_PIXELS = 2**30
"""Largest image (1,073,741,824 pixels, e.g. 46000 x 23000) read at all, even in bands; a header
claiming more is refused before anything is decoded."""


def _open_oiio(path: Path):
    import OpenImageIO as oiio

    from f2l.io.exr import quiet_native

    with quiet_native(path):
        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            raise ValueError(f"{path}: cannot open ({oiio.geterror() or 'unknown format'})")
    return inp


def _read_oiio(path: Path) -> np.ndarray:
    from f2l.io.exr import quiet_native

    inp = _open_oiio(path)
    try:
        spec = inp.spec()
        with quiet_native(path):
            pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
            error = inp.geterror()
    finally:
        inp.close()
    if pixels is None or error:
        raise ValueError(f"{path}: cannot read pixels ({error or 'no data'})")
    img = np.asarray(pixels, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
    if path.suffix.lower() == ".pfm":
        img = img[::-1]  # PFM stores the bottom row first; OpenImageIO 3.2 returns file order
    return img


def _rgb_checked(img: np.ndarray, path: Path, channels: list[int] | None = None) -> np.ndarray:
    """(H, W, 3) of a decoded (H, W, C) block: the given channel indices, or luminance replicated
    / the first three; ValueError for NaN, inf or negative values below the tolerance."""
    from f2l.io.exr import NEGATIVE_TOLERANCE

    if channels is not None and channels != [0, 1, 2]:
        img = img[:, :, channels]
    elif img.shape[2] == 1 or img.shape[2] == 2:  # luminance (+ alpha)
        img = np.repeat(img[:, :, :1], 3, axis=2)
    elif img.shape[2] >= 3:
        img = img[:, :, :3]
    if not img.size:
        return np.ascontiguousarray(img)
    low, high = float(img.min()), float(img.max())  # NaN propagates through both
    if not (np.isfinite(low) and np.isfinite(high)):
        raise ValueError(f"{path}: NaN or infinite values")
    if low < -NEGATIVE_TOLERANCE:
        raise ValueError(f"{path}: negative values (min {low:g}); radiance must be >= 0")
    return np.ascontiguousarray(np.maximum(img, 0.0) if low < 0 else img)


def hdr_image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(height, width) of an HDR image from its header, nothing decoded; ValueError naming the file."""
    from f2l.io.exr import ExrError, exr_size

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: file not found")
    if path.suffix.lower() == ".exr":
        try:
            return exr_size(path)
        except ExrError as exc:
            raise ValueError(str(exc)) from exc
    inp = _open_oiio(path)
    try:
        spec = inp.spec()
        return int(spec.height), int(spec.width)
    finally:
        inp.close()


def _exr_channels(names: list[str], path: Path) -> list[int]:
    """Indices of R, G, B (or Y three times) among an EXR's channels, as :func:`read_exr` picks them."""
    if all(c in names for c in "RGB"):
        return [names.index(c) for c in "RGB"]
    if "Y" in names:
        return [names.index("Y")] * 3
    raise ValueError(f"{path}: no R, G, B (or Y) channels, found {sorted(names)}")


def _read_banded(path: Path, target_hw: tuple[int, int], band_pixels: int) -> np.ndarray:
    """The image area-averaged to ``target_hw``, decoded ``band_pixels`` at a time (module doc)."""
    from f2l.io.exr import quiet_native
    from f2l.lighting.resample import BandResampler

    inp = _open_oiio(path)
    try:
        spec = inp.spec()
        height, width, nch, y0 = int(spec.height), int(spec.width), int(spec.nchannels), int(spec.y)
        channels = _exr_channels(list(spec.channelnames), path) if path.suffix.lower() == ".exr" else None
        flip = path.suffix.lower() == ".pfm"  # PFM: bottom row first in the file (see _read_oiio)
        rows = max(1, int(band_pixels) // width)
        out = BandResampler(height, width, int(target_hw[0]), int(target_hw[1]))
        starts = range(0, height, rows)
        for start in (reversed(starts) if flip else starts):
            stop = min(start + rows, height)
            with quiet_native(path):
                pixels = inp.read_scanlines(0, 0, y0 + start, y0 + stop, 0, 0, nch, "float")
                error = inp.geterror()
            if pixels is None or error:
                raise ValueError(f"{path}: cannot read rows {start}-{stop - 1} ({error or 'no data'})")
            band = np.asarray(pixels, dtype=np.float32).reshape(stop - start, width, nch)
            band = _rgb_checked(band[::-1] if flip else band, path, channels)
            out.add(band)
            del band, pixels
    finally:
        inp.close()
    return out.result().astype(np.float32)


def read_hdr_image(path: str | os.PathLike, target_hw: tuple[int, int] | None = None, *,
                   max_pixels: int | None = None, band_pixels: int = BAND_PIXELS) -> np.ndarray:
    """(H, W, 3) float32 of an HDR image file (module doc); ValueError naming the file.

    An image within the decode limit (``max_pixels``, default
    :func:`f2l.io.exr.decode_pixel_limit`) is returned whole, whatever ``target_hw``. A larger
    one is refused, unless ``target_hw`` = (height, width) is given: then it is returned as the
    lat-long area average at that size (what :func:`f2l.lighting.resample.resample` would give),
    decoded ``band_pixels`` at a time. Callers that resample a probe anyway should pass their size.
    """
    from f2l.io.exr import ExrError, decode_pixel_limit, read_exr, too_large_message

    path = Path(path)
    limit = decode_pixel_limit(max_pixels)
    height, width = hdr_image_size(path)
    pixels = height * width
    if pixels > MAX_IMAGE_PIXELS:
        raise ValueError(f"{path}: {width}x{height} image ({pixels:,} pixels) is larger than f2l reads "
                         f"({MAX_IMAGE_PIXELS:,} pixels at most): refused from its header")
    if pixels > limit:
        if target_hw is None:
            raise ValueError(too_large_message(path, height, width, limit)
                             + "; this reader was given no target size to downsample it to")
        if width > limit:
            raise ValueError(too_large_message(path, height, width, limit)
                             + f"; a single row of {width:,} pixels is over it")
        return _read_banded(path, target_hw, min(int(band_pixels), limit))
    if path.suffix.lower() == ".exr":
        try:
            return read_exr(path, max_pixels=limit)
        except ExrError as exc:
            raise ValueError(str(exc)) from exc
    return _rgb_checked(_read_oiio(path), path)


def release_openimageio_references() -> None:
    """Drop the OpenImageIO objects colour-science keeps in module globals (``colour.io.image``
    imports ``TypeDesc`` and builds a bit-depth table of them when OpenImageIO is installed).
    Left alive until interpreter shutdown, they make nanobind print "leaked instances / types /
    functions" to stderr after every f2l command; f2l runs this at exit (``atexit``)."""
    import sys

    module = sys.modules.get("colour.io.image")
    if module is None:
        return
    for name, value in list(vars(module).items()):
        owner = getattr(value, "__module__", None) or getattr(type(value), "__module__", "") or ""
        if str(owner).startswith("OpenImageIO") or name == "MAPPING_BIT_DEPTH":
            setattr(module, name, None)
