"""The one reader of camera metadata: a photo's or RAW file's EXIF as a typed, frozen
:class:`PhotoMetadata` (camera, exposure, focal length, orientation, capture time and offset,
GPS position, the DNG layout and colour matrix). :mod:`f2l.io.photo` (``Photo.exif``, the focal
length), :mod:`f2l.io.raw_meta` (``RawMeta``) and :mod:`f2l.io.capture` (the sun prior's time and
place) all read it here.

Conventions:

- Tags come from :mod:`f2l.io.photo.tags` (Pillow or exifread, one read of the file). A value
  is looked up in the Exif sub-IFD, then in IFD0.
- Numbers (exposure in seconds, f-number, ISO, focal lengths in mm, focal-plane resolution,
  EXIF pixel size) are positive finite floats, else ``None``; a rational stored as two integers
  counts as their quotient. Texts (make, model, lens, ``datetime_original``) are stripped of NULs
  and white space, ``None`` when empty. ``orientation`` is EXIF 1..8, else 1.
- Times and places are parsed strictly, each with the reason it is unusable in ``problems``
  (keys ``"position"`` (also when there is none), ``"altitude"``, ``"gps_time"``,
  ``"datetime_original"``, ``"offset"``):
  ``local_time`` is DateTimeOriginal ('YYYY:MM:DD HH:MM:SS', ``-`` and ``T`` also accepted) plus
  SubSecTimeOriginal (to the microsecond, truncated), naive camera-clock time; ``utc_offset``
  its OffsetTimeOriginal ('+HH:MM', '+HHMM' or 'Z', hours <= 14); ``gps_utc`` GPSDateStamp +
  GPSTimeStamp (UTC by definition). ``latitude_deg`` / ``longitude_deg`` (WGS84 degrees, north
  and east positive) need the hemisphere references and are both set or both ``None``;
  ``altitude_m`` is metres above sea level (GPSAltitudeRef odd: below). ``camera_time`` is the
  camera's own clock as RAW metadata reports it: DateTimeOriginal, else IFD0 DateTime, with
  sub-seconds, timezone-aware only when the offset is usable.
- DNG (first IFD): ``xyz_to_camera`` and ``dng_layout`` / ``tag_levels`` (:mod:`f2l.io.photo.dng_tags`).
- Parsing never raises: a malformed value is ``None`` (and a problem where one is kept).
"""

from __future__ import annotations

import math
import numbers
import re
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from types import MappingProxyType

from f2l.io.photo.dng_tags import dng_layout, dng_xyz_to_camera, tag_levels
from f2l.io.photo.tags import ExifTags, exifread_tags, pillow_tags, read_tags

__all__ = ["PhotoMetadata", "ExifTags", "metadata_from_tags", "read_metadata", "finite_number", "TAG_IDS"]

TAG_IDS = {
    "Make": 271, "Model": 272, "Orientation": 274, "DateTime": 306, "ExposureTime": 33434, "FNumber": 33437,
    "ISOSpeedRatings": 34855, "DateTimeOriginal": 36867, "OffsetTimeOriginal": 0x9011, "FocalLength": 37386,
    "SubSecTimeOriginal": 0x9291, "ExifImageWidth": 40962, "ExifImageLength": 40963, "FocalPlaneXResolution": 41486,
    "FocalPlaneResolutionUnit": 41488, "FocalLengthIn35mmFilm": 41989, "LensModel": 0xA434,
}  # fmt: skip
"""EXIF tag ids read (IFD0 and Exif sub-IFD)."""
_RATIONAL = {"ExposureTime", "FNumber", "FocalLength", "FocalPlaneXResolution"}
_LAT_REF, _LAT, _LON_REF, _LON, _ALT_REF, _ALT, _GPS_TIME, _GPS_DATE = 1, 2, 3, 4, 5, 6, 7, 29
_DATE_RE = re.compile(r"(\d{4})[:-](\d{2})[:-](\d{2})")
_DATE_TIME_RE = re.compile(r"(\d{4})[:-](\d{2})[:-](\d{2})[ T](\d{2}):(\d{2}):(\d{2})")
_OFFSET_RE = re.compile(r"([+-])(\d{2}):?(\d{2})")


@dataclass(frozen=True)
class PhotoMetadata:
    """What one file's EXIF says (conventions: module docstring). ``tags`` keeps the tags read."""

    make: str | None = None
    model: str | None = None
    lens: str | None = None
    exposure_s: float | None = None
    f_number: float | None = None
    iso: float | None = None
    focal_length_mm: float | None = None
    focal_35mm_mm: float | None = None
    focal_plane_x_resolution: float | None = None
    focal_plane_unit: int = 2
    exif_image_width: float | None = None
    exif_image_height: float | None = None
    orientation: int = 1
    datetime_original: str | None = None
    local_time: datetime | None = None
    utc_offset: timezone | None = None
    camera_time: datetime | None = None
    gps_utc: datetime | None = None
    latitude_deg: float | None = None
    longitude_deg: float | None = None
    altitude_m: float | None = None
    xyz_to_camera: tuple[float, ...] | None = None
    dng_layout: tuple[str, tuple[float, ...], float] | None = None
    tag_levels: tuple = (None, None, None)
    problems: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    tags: ExifTags = field(default_factory=ExifTags, repr=False, compare=False)

    @property
    def offset_utc(self) -> datetime | None:
        """``local_time`` at ``utc_offset``, in UTC; None unless both are known."""
        if self.local_time is None or self.utc_offset is None:
            return None
        return self.local_time.replace(tzinfo=self.utc_offset).astimezone(timezone.utc)


# --------------------------------------------------------------------------- lenient values


def _number(value, rational: bool = False) -> float | None:
    """Positive finite float of a Pillow/exifread value (IFDRational, Ratio, int, list, (num, den))."""
    if isinstance(value, (list, tuple)):
        if rational and len(value) == 2 and all(isinstance(v, int) for v in value):
            value = value[0] / value[1] if value[1] else None
        else:
            value = value[0] if value else None
    try:
        x = float(value)
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        return None
    return x if math.isfinite(x) and x > 0 else None


def _text(value) -> str | None:
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    return (value.strip("\x00 \t\r\n") if isinstance(value, str) else "") or None


def _tag(tags: ExifTags, name: str):
    return tags.get(TAG_IDS[name])


def _tag_number(tags: ExifTags, name: str) -> float | None:
    return _number(_tag(tags, name), name in _RATIONAL)


# --------------------------------------------------------------------------- strict values


class _Unusable(ValueError):
    """A value that cannot give a time or a position; the message is the reason."""


def finite_number(value, name: str) -> float:
    """``value`` as a finite float; ValueError for non-numbers (bools and strings included)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return number


def _strict_text(value, tag: str) -> str | None:
    """ASCII tag text without padding; None when absent or blank (EXIF's "    :  :  " = unknown)."""
    if value is None:
        return None
    if isinstance(value, bytes):
        try:
            value = value.decode("ascii")
        except UnicodeDecodeError:
            raise _Unusable(f"{tag} is not ASCII text ({value!r})") from None
    if not isinstance(value, str):
        raise _Unusable(f"{tag} is not text ({value!r})")
    text = value.strip("\x00 \t")
    return text if text.strip(" :") else None


def _strict_number(value, tag: str) -> float:
    if isinstance(value, list) and len(value) == 1:  # exifread's single value
        value = value[0]
    try:
        return finite_number(value, tag)
    except ValueError as exc:
        raise _Unusable(str(exc)) from None
    except (ZeroDivisionError, OverflowError):  # an exifread Ratio with denominator 0, or beyond float
        raise _Unusable(f"{tag} must be finite, got {value!r}") from None


def _values(value, tag: str, counts: range) -> list[float]:
    """A rational or sequence of rationals (Pillow collapses a single value to a scalar)."""
    parts = value if isinstance(value, (tuple, list)) else (value,)
    if len(parts) not in counts:
        expected = f"{counts.start} to {counts.stop - 1}" if len(counts) > 1 else f"{counts.start}"
        raise _Unusable(f"{tag} has {len(parts)} values, expected {expected}")
    return [_strict_number(part, tag) for part in parts]


def _degrees(gps, tag_id: int, ref_id: int, tag: str, refs: str, limit: float) -> float:
    """Signed degrees from a degrees/minutes/seconds tag and its hemisphere reference."""
    parts = _values(gps[tag_id], tag, range(1, 4))
    if any(part < 0 for part in parts):
        raise _Unusable(f"{tag} has negative components {parts}")
    magnitude = sum(part / 60.0**i for i, part in enumerate(parts))
    if magnitude > limit:
        raise _Unusable(f"{tag} {magnitude:g} is beyond {limit:g} degrees")
    ref = _strict_text(gps.get(ref_id), f"{tag}Ref")
    if ref is None:
        raise _Unusable(f"{tag}Ref is missing: hemisphere unknown")
    if ref.upper() not in refs:
        raise _Unusable(f"{tag}Ref is {ref!r}, expected {refs[0]!r} or {refs[1]!r}")
    return -magnitude if ref.upper() == refs[1] else magnitude


def _position(gps) -> tuple[float, float]:
    if gps.get(_LAT) is None or gps.get(_LON) is None:
        raise _Unusable("no GPS position in EXIF")
    latitude = _degrees(gps, _LAT, _LAT_REF, "GPSLatitude", "NS", 90.0)
    longitude = _degrees(gps, _LON, _LON_REF, "GPSLongitude", "EW", 180.0)
    return latitude, longitude


def _altitude(gps) -> float | None:
    """Metres above sea level; GPSAltitudeRef odd (1, or EXIF 3's 3) means below."""
    if gps.get(_ALT) is None:
        return None
    altitude = _strict_number(gps[_ALT], "GPSAltitude")
    ref = gps.get(_ALT_REF, 0)
    if isinstance(ref, list) and len(ref) == 1:  # exifread's single value
        ref = ref[0]
    if isinstance(ref, bytes):
        ref = ref[0] if ref else 0
    elif isinstance(ref, str) and ref.strip("\x00 ").isdigit():
        ref = int(ref.strip("\x00 "))
    if isinstance(ref, bool) or not isinstance(ref, int):
        raise _Unusable(f"GPSAltitudeRef is {ref!r}, expected 0 or 1")
    return -altitude if ref % 2 else altitude


def _gps_time(gps) -> datetime | None:
    """GPSDateStamp + GPSTimeStamp (UTC); None when either is absent."""
    date_text = _strict_text(gps.get(_GPS_DATE), "GPSDateStamp")
    if date_text is None or gps.get(_GPS_TIME) is None:
        return None
    match = _DATE_RE.fullmatch(date_text)
    if match is None:
        raise _Unusable(f"GPSDateStamp {date_text!r} is not 'YYYY:MM:DD'")
    try:
        day = datetime(*(int(g) for g in match.groups()), tzinfo=timezone.utc)
    except ValueError:
        raise _Unusable(f"GPSDateStamp {date_text!r} is not a valid date") from None
    hours, minutes, seconds = _values(gps[_GPS_TIME], "GPSTimeStamp", range(3, 4))
    if not (0 <= hours < 24 and 0 <= minutes < 60 and 0 <= seconds < 61):
        raise _Unusable(f"GPSTimeStamp {hours:g}:{minutes:g}:{seconds:g} is not a valid time of day")
    return day + timedelta(hours=hours, minutes=minutes, seconds=seconds)


def _utc_offset(value) -> timezone | None:
    """A timezone from an EXIF offset such as "+02:00" (also "+0200" and "Z"); None when absent."""
    text = _strict_text(value, "OffsetTimeOriginal")
    if text is None:
        return None
    if text.upper() == "Z":
        return timezone.utc
    match = _OFFSET_RE.fullmatch(text)
    if match is None or int(match[2]) > 14 or int(match[3]) >= 60:
        raise _Unusable(f"OffsetTimeOriginal {text!r} is not a UTC offset '+HH:MM'")
    sign = -1 if match[1] == "-" else 1
    return timezone(sign * timedelta(hours=int(match[2]), minutes=int(match[3])))


def _subseconds(value) -> timedelta:
    """SubSecTimeOriginal digits as a fraction of a second; anything else adds nothing."""
    digits = value.strip("\x00 ") if isinstance(value, str) else ""
    if not digits.isdigit():
        return timedelta(0)
    return timedelta(microseconds=int(digits[:6].ljust(6, "0")))


def _local_time(value, tag: str, subsec) -> datetime | None:
    """A naive 'YYYY:MM:DD HH:MM:SS' time plus sub-seconds; None when absent or blank."""
    text = _strict_text(value, tag)
    if text is None:
        return None
    match = _DATE_TIME_RE.fullmatch(text)
    if match is None:
        raise _Unusable(f"{tag} {text!r} is not 'YYYY:MM:DD HH:MM:SS'")
    try:
        local = datetime(*(int(g) for g in match.groups()))
    except ValueError:
        raise _Unusable(f"{tag} {text!r} is not a valid date and time") from None
    return local + _subseconds(subsec)


def _attempt(read, *args):
    """(value, None) or (None, the reason it is unusable)."""
    try:
        return read(*args), None
    except _Unusable as exc:
        return None, str(exc)


# --------------------------------------------------------------------------- the result


def metadata_from_tags(tags: ExifTags) -> PhotoMetadata:
    """The :class:`PhotoMetadata` of tags already read (never raises)."""
    problems = {}

    def keep(key: str, read, *args):
        value, problem = _attempt(read, *args)
        if problem is not None:
            problems[key] = problem
        return value

    gps, subsec = tags.gps, _tag(tags, "SubSecTimeOriginal")
    position = keep("position", _position, gps) or (None, None)
    local = keep("datetime_original", _local_time, _tag(tags, "DateTimeOriginal"), "DateTimeOriginal", subsec)
    offset = keep("offset", _utc_offset, _tag(tags, "OffsetTimeOriginal"))
    if local is None and "datetime_original" not in problems:  # no DateTimeOriginal: IFD0 DateTime
        clock = _attempt(_local_time, tags.ifd0.get(TAG_IDS["DateTime"]), "DateTime", subsec)[0]
    else:
        clock = local
    width, height = _tag_number(tags, "ExifImageWidth"), _tag_number(tags, "ExifImageLength")
    return PhotoMetadata(
        make=_text(_tag(tags, "Make")), model=_text(_tag(tags, "Model")), lens=_text(_tag(tags, "LensModel")),
        exposure_s=_tag_number(tags, "ExposureTime"), f_number=_tag_number(tags, "FNumber"),
        iso=_tag_number(tags, "ISOSpeedRatings"), focal_length_mm=_tag_number(tags, "FocalLength"),
        focal_35mm_mm=_tag_number(tags, "FocalLengthIn35mmFilm"),
        focal_plane_x_resolution=_tag_number(tags, "FocalPlaneXResolution"),
        focal_plane_unit=int(_tag_number(tags, "FocalPlaneResolutionUnit") or 2),
        exif_image_width=width, exif_image_height=height, orientation=_orientation(_tag(tags, "Orientation")),
        datetime_original=_text(_tag(tags, "DateTimeOriginal")), local_time=local, utc_offset=offset,
        camera_time=clock.replace(tzinfo=offset) if clock is not None and offset is not None else clock,
        gps_utc=keep("gps_time", _gps_time, gps), latitude_deg=position[0], longitude_deg=position[1],
        altitude_m=keep("altitude", _altitude, gps), xyz_to_camera=dng_xyz_to_camera(tags.ifd0),
        dng_layout=dng_layout(tags.ifd0), tag_levels=tag_levels(tags.ifd0),
        problems=MappingProxyType(problems), tags=tags,
    )  # fmt: skip


def _orientation(value) -> int:
    number = _number(value)
    return int(number) if number in (1, 2, 3, 4, 5, 6, 7, 8) else 1


def metadata_from_image(image, gps: bool = True) -> PhotoMetadata:
    """The metadata of an open Pillow image; broken EXIF gives an empty result."""
    try:
        tags = pillow_tags(image, gps=gps)
    except Exception:  # noqa: BLE001 - broken EXIF never makes a photo unusable
        return PhotoMetadata()
    return metadata_from_tags(tags)


def read_metadata(path, *, backend: str = "auto") -> PhotoMetadata:
    """The metadata of a file, read once (``backend``: "auto" as :func:`f2l.io.photo.tags.read_tags`,
    or "exifread"); raises what the library raises on an unreadable file."""
    path = str(path)
    return metadata_from_tags(exifread_tags(path)[0] if backend == "exifread" else read_tags(path))
