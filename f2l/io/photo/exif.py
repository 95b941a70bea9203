"""EXIF of a photo: the fields f2l keeps (``Photo.exif``), its orientation, and the pinhole focal
length in pixels (conventions in :mod:`f2l.io.photo`). Pillow reads JPEG/PNG EXIF, ``exifread``
RAW and TIFF; broken EXIF never makes a photo unusable.
"""

from __future__ import annotations

import logging
import math

DEFAULT_FOCAL_35MM_MM = 50.0
DIAGONAL_35MM_MM = math.hypot(36.0, 24.0)  # 43.2666 mm
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
