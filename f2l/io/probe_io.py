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
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["read_hdr_image", "HDR_IMAGE_EXTENSIONS"]

HDR_IMAGE_EXTENSIONS = (".exr", ".hdr", ".rgbe", ".tif", ".tiff", ".pfm")
"""Extensions f2l treats as linear HDR images (``f2l ingest`` lists ``.exr``/``.hdr``/``.pfm`` as probes)."""


def _read_oiio(path: Path) -> np.ndarray:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ValueError(f"{path}: cannot open ({oiio.geterror() or 'unknown format'})")
    try:
        spec = inp.spec()
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


def read_hdr_image(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) float32 of an HDR image file (module doc); ValueError naming the file."""
    from f2l.io.exr import NEGATIVE_TOLERANCE, ExrError, read_exr

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: file not found")
    if path.suffix.lower() == ".exr":
        try:
            return read_exr(path)
        except ExrError as exc:
            raise ValueError(str(exc)) from exc
    img = _read_oiio(path)
    channels = img.shape[2]
    if channels == 1 or channels == 2:  # luminance (+ alpha)
        img = np.repeat(img[:, :, :1], 3, axis=2)
    elif channels >= 3:
        img = img[:, :, :3]
    if not np.all(np.isfinite(img)):
        raise ValueError(f"{path}: NaN or infinite values")
    if img.size and float(img.min()) < -NEGATIVE_TOLERANCE:
        raise ValueError(f"{path}: negative values (min {float(img.min()):g}); radiance must be >= 0")
    return np.ascontiguousarray(np.maximum(img, 0.0))


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
