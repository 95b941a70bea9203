"""The camera fields a :class:`~f2l.io.photo.Photo` keeps (``Photo.exif``), its orientation and the
pinhole focal length in pixels (conventions in :mod:`f2l.io.photo`), from the one metadata reader
(:mod:`f2l.io.photo.metadata`: Pillow for JPEG/PNG, ``exifread`` for RAW and TIFF). Broken EXIF
never makes a photo unusable: it reads as no EXIF.
"""

from __future__ import annotations

import math

from f2l.io.photo.metadata import PhotoMetadata, metadata_from_image, read_metadata

DEFAULT_FOCAL_35MM_MM = 50.0
DIAGONAL_35MM_MM = math.hypot(36.0, 24.0)  # 43.2666 mm
FOCAL_PLANE_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}  # EXIF ResolutionUnit (default 2 = inch)


def _pillow_metadata(im) -> PhotoMetadata:
    """The metadata of an open Pillow image (its GPS IFD unread); empty when the EXIF is unreadable."""
    return metadata_from_image(im, gps=False)


def _file_metadata(path: str) -> PhotoMetadata:
    """The metadata of a RAW or TIFF file via exifread; empty when it finds nothing usable."""
    try:
        return read_metadata(path, backend="exifread")
    except Exception:  # noqa: BLE001 - broken EXIF never makes a photo unusable
        return PhotoMetadata()


def _exif_summary(meta: PhotoMetadata) -> dict:
    """The JSON-able ``Photo.exif``: only valid values, under the names of the ``Photo`` contract."""
    out = {}
    for key in ("exposure_s", "f_number", "iso", "focal_length_mm", "focal_35mm_mm"):
        x = getattr(meta, key)
        if x is not None:
            out[key] = int(round(x)) if key == "iso" else x
    for key in ("make", "model", "datetime_original"):
        if (text := getattr(meta, key)) is not None:
            out[key] = text
    return out


def _exif_size_scale(meta: PhotoMetadata, shape) -> float:
    """Decoded long side over the EXIF pixel dimensions' long side (1 when they are absent)."""
    width, height = meta.exif_image_width, meta.exif_image_height
    return max(shape[:2]) / max(width, height) if width and height else 1.0


def _focal(meta: PhotoMetadata, exif: dict, shape, sensor_scale: float, default_f35: float) -> tuple[float, str]:
    diagonal = math.hypot(shape[0], shape[1])
    if "focal_35mm_mm" in exif:
        return exif["focal_35mm_mm"] / DIAGONAL_35MM_MM * diagonal, "exif-35mm"
    resolution = meta.focal_plane_x_resolution
    unit_mm = FOCAL_PLANE_UNIT_MM.get(meta.focal_plane_unit)
    if "focal_length_mm" in exif and resolution and unit_mm:
        return exif["focal_length_mm"] * resolution / unit_mm * sensor_scale, "exif-focal-plane"
    return default_f35 / DIAGONAL_35MM_MM * diagonal, "default"
