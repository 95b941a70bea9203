"""When and where a photo was taken, and where the sun was then.

The estimator can use the sun's true elevation as an optional prior. A photo's heading is unknown,
so only elevation constrains the lighting; the azimuth (clockwise from true north) is returned for
reports.

Conventions:

- Times are timezone-aware ``datetime`` objects in UTC. Positions are WGS84 degrees (north and
  east positive) and metres above sea level, as EXIF and the record metadata store them.
  :func:`solar_position` returns radians, like the rest of the code.
- EXIF tags read (Pillow, JPEG/TIFF/PNG eXIf/WebP): GPS IFD (0x8825) GPSLatitudeRef/GPSLatitude,
  GPSLongitudeRef/GPSLongitude, GPSAltitudeRef/GPSAltitude, GPSDateStamp/GPSTimeStamp; Exif IFD
  (0x8769) DateTimeOriginal (0x9003), OffsetTimeOriginal (0x9011), SubSecTimeOriginal (0x9291).
- Time: GPSDateStamp + GPSTimeStamp is UTC by definition and is preferred (``"exif-gps-time"``);
  otherwise DateTimeOriginal with its OffsetTimeOriginal (``"exif-offset-time"``). A local
  DateTimeOriginal without an offset is rejected rather than guessed: each hour of error moves
  the sun by up to 15 degrees, which would make the prior confidently wrong. Guessing the zone
  from the position fails near zone borders and across daylight-saving rules, and camera
  clocks are often left on the owner's home time.
- Unusable EXIF (no position, unknown time zone, malformed values, unreadable file) never
  raises: :func:`capture_status` gives ``None`` and a reason ``"{path}: ..."``. Malformed
  optional values (altitude) are dropped and noted in the status.
- Record metadata: ``meta["capture"] = {"utc": ISO-8601 with offset or Z, "latitude_deg",
  "longitude_deg", "altitude_m" (optional)}`` (``source="meta"``); malformed values raise
  ``ValueError`` because they were written on purpose.
- :func:`solar_position` uses astral (NOAA algorithm, about 0.01 degree). Its elevation
  includes astral's standard-atmosphere refraction (NOAA formula; about 0.48 degree at the
  horizon, 0.16 degree at 5 degrees, none above 85 degrees). Altitude is not used; astral clamps
  latitudes beyond +-89.8 degrees and ignores sub-second time.
"""

from __future__ import annotations

import math
import numbers
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone

from astral import Observer
from astral.sun import azimuth as _astral_azimuth
from astral.sun import elevation as _astral_elevation
from PIL import Image

__all__ = [
    "CaptureInfo", "SOURCES", "read_capture", "capture_status", "capture_from_exif_tags",
    "capture_from_meta", "capture_to_meta", "solar_position", "capture_for_elevation",
]  # fmt: skip

SOURCES = ("exif-gps-time", "exif-offset-time", "meta")
"""Where a :class:`CaptureInfo` came from."""

_GPS_IFD = 0x8825
_EXIF_IFD = 0x8769
_GPS_LATITUDE_REF, _GPS_LATITUDE, _GPS_LONGITUDE_REF, _GPS_LONGITUDE = 1, 2, 3, 4
_GPS_ALTITUDE_REF, _GPS_ALTITUDE, _GPS_TIME_STAMP, _GPS_DATE_STAMP = 5, 6, 7, 29
_DATE_TIME_ORIGINAL, _OFFSET_TIME_ORIGINAL, _SUBSEC_TIME_ORIGINAL = 0x9003, 0x9011, 0x9291

_CLOCK_DISAGREEMENT = timedelta(minutes=5)  # about 1.25 degrees of sun movement
_DATE_RE = re.compile(r"(\d{4})[:-](\d{2})[:-](\d{2})")
_DATE_TIME_RE = re.compile(r"(\d{4})[:-](\d{2})[:-](\d{2})[ T](\d{2}):(\d{2}):(\d{2})")
_OFFSET_RE = re.compile(r"([+-])(\d{2}):?(\d{2})")


@dataclass(frozen=True)
class CaptureInfo:
    """Capture time (UTC) and position (degrees, metres) of one photo; validated on creation."""

    utc: datetime
    latitude_deg: float
    longitude_deg: float
    altitude_m: float | None = None
    source: str = "meta"

    def __post_init__(self):
        if not isinstance(self.utc, datetime) or self.utc.utcoffset() is None:
            raise ValueError(f"utc must be a timezone-aware datetime, got {self.utc!r}")
        if self.source not in SOURCES:
            raise ValueError(f"source must be one of {SOURCES}, got {self.source!r}")
        object.__setattr__(self, "utc", self.utc.astimezone(timezone.utc))
        object.__setattr__(self, "latitude_deg", _checked_degrees(self.latitude_deg, "latitude_deg", 90.0))
        object.__setattr__(self, "longitude_deg", _checked_degrees(self.longitude_deg, "longitude_deg", 180.0))
        if self.altitude_m is not None:
            object.__setattr__(self, "altitude_m", _finite(self.altitude_m, "altitude_m"))


def _finite(value, name: str) -> float:
    """``value`` as a finite float; ValueError for non-numbers (bools and strings included)."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return number


def _checked_degrees(value, name: str, limit: float) -> float:
    number = _finite(value, name)
    if not -limit <= number <= limit:
        raise ValueError(f"{name} must be in [-{limit:g}, {limit:g}], got {number:g}")
    return number


# --------------------------------------------------------------------------- EXIF


class _Unusable(ValueError):
    """An EXIF value that cannot give a capture time or position; the message is the reason."""


class _NoOffset(_Unusable):
    """DateTimeOriginal is present but its time zone is not."""


def _text(value, tag: str) -> str | None:
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


def _number(value, tag: str) -> float:
    try:
        return _finite(value, tag)
    except ValueError as exc:
        raise _Unusable(str(exc)) from None


def _values(value, tag: str, counts: range) -> list[float]:
    """A rational or tuple of rationals (Pillow collapses a single value to a scalar)."""
    parts = value if isinstance(value, (tuple, list)) else (value,)
    if len(parts) not in counts:
        expected = f"{counts.start} to {counts.stop - 1}" if len(counts) > 1 else f"{counts.start}"
        raise _Unusable(f"{tag} has {len(parts)} values, expected {expected}")
    return [_number(part, tag) for part in parts]


def _degrees(gps: Mapping, tag_id: int, ref_id: int, tag: str, refs: str, limit: float) -> float:
    """Signed degrees from a degrees/minutes/seconds tag and its hemisphere reference."""
    parts = _values(gps[tag_id], tag, range(1, 4))
    if any(part < 0 for part in parts):
        raise _Unusable(f"{tag} has negative components {parts}")
    magnitude = sum(part / 60.0**i for i, part in enumerate(parts))
    if magnitude > limit:
        raise _Unusable(f"{tag} {magnitude:g} is beyond {limit:g} degrees")
    ref = _text(gps.get(ref_id), f"{tag}Ref")
    if ref is None:
        raise _Unusable(f"{tag}Ref is missing: hemisphere unknown")
    if ref.upper() not in refs:
        raise _Unusable(f"{tag}Ref is {ref!r}, expected {refs[0]!r} or {refs[1]!r}")
    return -magnitude if ref.upper() == refs[1] else magnitude


def _position(gps: Mapping) -> tuple[float, float]:
    if gps.get(_GPS_LATITUDE) is None or gps.get(_GPS_LONGITUDE) is None:
        raise _Unusable("no GPS position in EXIF")
    latitude = _degrees(gps, _GPS_LATITUDE, _GPS_LATITUDE_REF, "GPSLatitude", "NS", 90.0)
    longitude = _degrees(gps, _GPS_LONGITUDE, _GPS_LONGITUDE_REF, "GPSLongitude", "EW", 180.0)
    return latitude, longitude


def _altitude(gps: Mapping) -> float | None:
    """Metres above sea level; GPSAltitudeRef odd (1, or EXIF 3's 3) means below."""
    if gps.get(_GPS_ALTITUDE) is None:
        return None
    altitude = _number(gps[_GPS_ALTITUDE], "GPSAltitude")
    ref = gps.get(_GPS_ALTITUDE_REF, 0)
    if isinstance(ref, bytes):
        ref = ref[0] if ref else 0
    elif isinstance(ref, str) and ref.strip("\x00 ").isdigit():
        ref = int(ref.strip("\x00 "))
    if isinstance(ref, bool) or not isinstance(ref, int):
        raise _Unusable(f"GPSAltitudeRef is {ref!r}, expected 0 or 1")
    return -altitude if ref % 2 else altitude


def _gps_time(gps: Mapping) -> datetime | None:
    """GPSDateStamp + GPSTimeStamp (UTC); None when either is absent."""
    date_text = _text(gps.get(_GPS_DATE_STAMP), "GPSDateStamp")
    if date_text is None or gps.get(_GPS_TIME_STAMP) is None:
        return None
    match = _DATE_RE.fullmatch(date_text)
    if match is None:
        raise _Unusable(f"GPSDateStamp {date_text!r} is not 'YYYY:MM:DD'")
    try:
        day = datetime(*(int(g) for g in match.groups()), tzinfo=timezone.utc)
    except ValueError:
        raise _Unusable(f"GPSDateStamp {date_text!r} is not a valid date") from None
    hours, minutes, seconds = _values(gps[_GPS_TIME_STAMP], "GPSTimeStamp", range(3, 4))
    if not (0 <= hours < 24 and 0 <= minutes < 60 and 0 <= seconds < 61):
        raise _Unusable(f"GPSTimeStamp {hours:g}:{minutes:g}:{seconds:g} is not a valid time of day")
    return day + timedelta(hours=hours, minutes=minutes, seconds=seconds)


def _utc_offset(text: str) -> timezone:
    """A timezone from an EXIF offset such as "+02:00" (also "+0200" and "Z")."""
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


def _offset_time(exif_ifd: Mapping) -> datetime | None:
    """DateTimeOriginal shifted by OffsetTimeOriginal to UTC; None when there is no DateTimeOriginal."""
    text = _text(exif_ifd.get(_DATE_TIME_ORIGINAL), "DateTimeOriginal")
    if text is None:
        return None
    match = _DATE_TIME_RE.fullmatch(text)
    if match is None:
        raise _Unusable(f"DateTimeOriginal {text!r} is not 'YYYY:MM:DD HH:MM:SS'")
    try:
        local = datetime(*(int(g) for g in match.groups()))
    except ValueError:
        raise _Unusable(f"DateTimeOriginal {text!r} is not a valid date and time") from None
    offset = _text(exif_ifd.get(_OFFSET_TIME_ORIGINAL), "OffsetTimeOriginal")
    if offset is None:
        raise _NoOffset("DateTimeOriginal has no OffsetTimeOriginal")
    local += _subseconds(exif_ifd.get(_SUBSEC_TIME_ORIGINAL))
    return local.replace(tzinfo=_utc_offset(offset)).astimezone(timezone.utc)


def _attempt(read, mapping: Mapping) -> tuple[datetime | None, _Unusable | None]:
    try:
        return read(mapping), None
    except _Unusable as exc:
        return None, exc


def _capture_time(gps: Mapping, exif_ifd: Mapping) -> tuple[datetime, str, list[str]]:
    """(UTC time, source, notes), preferring GPS time; raises _Unusable with every reason."""
    gps_utc, gps_problem = _attempt(_gps_time, gps)
    local_utc, local_problem = _attempt(_offset_time, exif_ifd)
    if gps_utc is not None:
        notes = []
        if local_utc is not None and abs(local_utc - gps_utc) > _CLOCK_DISAGREEMENT:
            hours = (local_utc - gps_utc).total_seconds() / 3600.0
            notes.append(f"DateTimeOriginal+OffsetTimeOriginal differs from GPS time by {hours:+.2f} h")
        return gps_utc, "exif-gps-time", notes
    gps_note = [f"GPS time ignored: {gps_problem}"] if gps_problem else []
    if local_utc is not None:
        return local_utc, "exif-offset-time", gps_note
    if isinstance(local_problem, _NoOffset):
        usable = "usable " if gps_problem else ""
        raise _Unusable("; ".join(gps_note + [f"{local_problem} and there is no {usable}GPS time: time zone unknown"]))
    if local_problem or gps_problem:
        raise _Unusable("; ".join(str(p) for p in (gps_problem, local_problem) if p))
    raise _Unusable("no capture time in EXIF (no GPSDateStamp/GPSTimeStamp, no DateTimeOriginal)")


def capture_from_exif_tags(gps: Mapping, exif_ifd: Mapping, name) -> tuple[CaptureInfo | None, str]:
    """Capture info from already-read GPS and Exif IFDs (tag id -> value), with a status line.

    ``name`` (the file) starts the status: ``"{name}: reason"`` when unusable, otherwise
    ``"{name}: {source} {utc} at {lat}, {lon}"`` plus notes on ignored values. Never raises for
    bad tag values.
    """
    try:
        latitude, longitude = _position(gps)
        utc, source, notes = _capture_time(gps, exif_ifd)
    except _Unusable as exc:
        return None, f"{name}: {exc}"
    altitude, altitude_problem = _attempt(_altitude, gps)
    if altitude_problem:
        notes.append(f"altitude ignored: {altitude_problem}")
    info = CaptureInfo(utc, latitude, longitude, altitude, source)
    status = f"{name}: {source} {utc.isoformat()} at {latitude:.6f}, {longitude:.6f}"
    return info, "; ".join([status] + notes)


def capture_status(path) -> tuple[CaptureInfo | None, str]:
    """Read capture info from an image's EXIF: ``(info, status)``, or ``(None, "{path}: reason")``."""
    try:
        with Image.open(path) as image:
            exif = image.getexif()
            gps = dict(exif.get_ifd(_GPS_IFD))
            exif_ifd = dict(exif.get_ifd(_EXIF_IFD))
    except FileNotFoundError:
        return None, f"{os.fspath(path)}: cannot read EXIF (file not found)"
    except Exception as exc:  # Pillow raises OSError, SyntaxError, struct.error, ... on corrupt files
        return None, f"{os.fspath(path)}: cannot read EXIF ({type(exc).__name__}: {exc})"
    return capture_from_exif_tags(gps, exif_ifd, os.fspath(path))


def read_capture(path) -> CaptureInfo | None:
    """Capture info from an image's EXIF, or None when unusable (see :func:`capture_status`)."""
    return capture_status(path)[0]


# --------------------------------------------------------------------------- record metadata


def _parse_utc(text) -> datetime:
    if not isinstance(text, str):
        raise ValueError(f"capture utc must be an ISO-8601 string, got {text!r}")
    try:
        moment = datetime.fromisoformat(text)
    except ValueError:
        raise ValueError(f"capture utc {text!r} is not ISO-8601") from None
    if moment.utcoffset() is None:
        raise ValueError(f"capture utc {text!r} has no UTC offset (add 'Z' or '+HH:MM')")
    return moment


def capture_from_meta(meta: Mapping) -> CaptureInfo | None:
    """CaptureInfo from ``meta["capture"]``; None when absent, ValueError when malformed."""
    block = meta.get("capture")
    if block is None:
        return None
    if not isinstance(block, Mapping):
        raise ValueError(f"meta['capture'] must be a mapping, got {type(block).__name__}")
    missing = [key for key in ("utc", "latitude_deg", "longitude_deg") if key not in block]
    if missing:
        raise ValueError(f"meta['capture'] is missing {', '.join(missing)}")
    return CaptureInfo(_parse_utc(block["utc"]), block["latitude_deg"], block["longitude_deg"],
                       block.get("altitude_m"), "meta")


def capture_to_meta(info: CaptureInfo) -> dict:
    """``{"capture": {...}}`` for record metadata; :func:`capture_from_meta` reads it back."""
    block = {
        "utc": info.utc.isoformat().removesuffix("+00:00") + "Z",
        "latitude_deg": info.latitude_deg,
        "longitude_deg": info.longitude_deg,
    }
    if info.altitude_m is not None:
        block["altitude_m"] = info.altitude_m
    return {"capture": block}


# --------------------------------------------------------------------------- sun


def solar_position(info: CaptureInfo) -> tuple[float, float]:
    """(apparent elevation, azimuth) of the sun in radians; azimuth clockwise from true north.

    The elevation includes atmospheric refraction (astral's default ``with_refraction=True``).
    """
    observer = Observer(latitude=info.latitude_deg, longitude=info.longitude_deg)
    elevation = _astral_elevation(observer, info.utc, with_refraction=True)
    azimuth = _astral_azimuth(observer, info.utc) % 360.0
    return math.radians(elevation), math.radians(azimuth)


def capture_for_elevation(elevation_rad: float, latitude_deg: float = 10.0, longitude_deg: float = 0.0,
                          day: datetime | None = None) -> CaptureInfo:
    """A capture (morning of ``day``, default 2024-06-21 UTC, at the given place) at which the sun
    stands at ``elevation_rad`` (apparent): for synthetic records that carry a consistent time and
    place. Found by bisection on :func:`solar_position` between solar midnight and noon (to
    ~0.01 deg: astral ignores fractions of a second); raises ValueError when the sun never gets
    that high there on that day."""
    day = day or datetime(2024, 6, 21, tzinfo=timezone.utc)
    noon = day.replace(hour=12, minute=0, second=0, microsecond=0) - timedelta(hours=longitude_deg / 15.0)

    def elevation_at(t: datetime) -> float:
        return solar_position(CaptureInfo(utc=t, latitude_deg=latitude_deg, longitude_deg=longitude_deg))[0]

    lo, hi = noon - timedelta(hours=12), noon
    if not elevation_at(lo) < elevation_rad < elevation_at(hi):
        raise ValueError(f"the sun does not reach {math.degrees(elevation_rad):.2f} deg at "
                         f"({latitude_deg}, {longitude_deg}) on {day.date()}")
    for _ in range(40):
        mid = lo + (hi - lo) / 2
        lo, hi = (mid, hi) if elevation_at(mid) < elevation_rad else (lo, mid)
    return CaptureInfo(utc=lo + (hi - lo) / 2, latitude_deg=latitude_deg, longitude_deg=longitude_deg, source="meta")
