"""When and where a photo was taken, and where the sun was then.

The estimator can use the sun's true elevation as an optional prior. A photo's heading is unknown,
so only elevation constrains the lighting; the azimuth (clockwise from true north) is returned for
reports.

Conventions:

- Times are timezone-aware ``datetime`` objects in UTC. Positions are WGS84 degrees (north and
  east positive) and metres above sea level, as EXIF and the record metadata store them.
  :func:`solar_position` returns radians, like the rest of the code.
- EXIF tags read, through the one metadata reader (:mod:`f2l.io.photo.metadata`: Pillow for
  JPEG/PNG eXIf/WebP, exifread for TIFF, DNG and TIFF-based RAW): GPS IFD (0x8825)
  GPSLatitudeRef/GPSLatitude, GPSLongitudeRef/GPSLongitude, GPSAltitudeRef/GPSAltitude,
  GPSDateStamp/GPSTimeStamp; Exif IFD (0x8769) DateTimeOriginal (0x9003), OffsetTimeOriginal
  (0x9011), SubSecTimeOriginal (0x9291). The values are parsed there; this module decides which
  clock to trust.
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
import os
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone

from astral import Observer
from astral.sun import azimuth as _astral_azimuth
from astral.sun import elevation as _astral_elevation

from f2l.io.photo.metadata import ExifTags, PhotoMetadata, finite_number, metadata_from_tags, read_metadata

__all__ = [
    "CaptureInfo", "SOURCES", "read_capture", "capture_status", "capture_from_exif_tags",
    "capture_from_meta", "capture_to_meta", "solar_position", "capture_for_elevation",
]  # fmt: skip

SOURCES = ("exif-gps-time", "exif-offset-time", "meta")
"""Where a :class:`CaptureInfo` came from."""

_CLOCK_DISAGREEMENT = timedelta(minutes=5)  # about 1.25 degrees of sun movement


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
            object.__setattr__(self, "altitude_m", finite_number(self.altitude_m, "altitude_m"))


def _checked_degrees(value, name: str, limit: float) -> float:
    number = finite_number(value, name)
    if not -limit <= number <= limit:
        raise ValueError(f"{name} must be in [-{limit:g}, {limit:g}], got {number:g}")
    return number


# --------------------------------------------------------------------------- EXIF


class _Unusable(ValueError):
    """EXIF that cannot give a capture time or position; the message is the reason."""


def _offset_time(meta: PhotoMetadata) -> datetime | None:
    """DateTimeOriginal shifted by OffsetTimeOriginal to UTC; None when there is no DateTimeOriginal."""
    if meta.local_time is None and "datetime_original" not in meta.problems:
        return None
    for key in ("datetime_original", "offset"):
        if key in meta.problems:
            raise _Unusable(meta.problems[key])
    return meta.offset_utc


def _capture_time(meta: PhotoMetadata) -> tuple[datetime, str, list[str]]:
    """(UTC time, source, notes), preferring GPS time; raises _Unusable with every reason."""
    gps_utc, gps_problem = meta.gps_utc, meta.problems.get("gps_time")
    try:
        local_utc, local_problem = _offset_time(meta), None
    except _Unusable as exc:
        local_utc, local_problem = None, str(exc)
    if gps_utc is not None:
        notes = []
        if local_utc is not None and abs(local_utc - gps_utc) > _CLOCK_DISAGREEMENT:
            hours = (local_utc - gps_utc).total_seconds() / 3600.0
            notes.append(f"DateTimeOriginal+OffsetTimeOriginal differs from GPS time by {hours:+.2f} h")
        return gps_utc, "exif-gps-time", notes
    gps_note = [f"GPS time ignored: {gps_problem}"] if gps_problem else []
    if local_utc is not None:
        return local_utc, "exif-offset-time", gps_note
    if local_problem is None and meta.local_time is not None:  # DateTimeOriginal without its zone
        usable = "usable " if gps_problem else ""
        no_offset = "DateTimeOriginal has no OffsetTimeOriginal"
        raise _Unusable("; ".join(gps_note + [f"{no_offset} and there is no {usable}GPS time: time zone unknown"]))
    if local_problem or gps_problem:
        raise _Unusable("; ".join(str(p) for p in (gps_problem, local_problem) if p))
    raise _Unusable("no capture time in EXIF (no GPSDateStamp/GPSTimeStamp, no DateTimeOriginal)")


def _capture_from_metadata(meta: PhotoMetadata, name) -> tuple[CaptureInfo | None, str]:
    if meta.latitude_deg is None:
        return None, f"{name}: {meta.problems.get('position', 'no GPS position in EXIF')}"
    try:
        utc, source, notes = _capture_time(meta)
    except _Unusable as exc:
        return None, f"{name}: {exc}"
    if "altitude" in meta.problems:
        notes.append(f"altitude ignored: {meta.problems['altitude']}")
    latitude, longitude = meta.latitude_deg, meta.longitude_deg
    info = CaptureInfo(utc, latitude, longitude, meta.altitude_m, source)
    status = f"{name}: {source} {utc.isoformat()} at {latitude:.6f}, {longitude:.6f}"
    return info, "; ".join([status] + notes)


def capture_from_exif_tags(gps: Mapping, exif_ifd: Mapping, name) -> tuple[CaptureInfo | None, str]:
    """Capture info from already-read GPS and Exif IFDs (tag id -> value), with a status line.

    ``name`` (the file) starts the status: ``"{name}: reason"`` when unusable, otherwise
    ``"{name}: {source} {utc} at {lat}, {lon}"`` plus notes on ignored values. Never raises for
    bad tag values.
    """
    return _capture_from_metadata(metadata_from_tags(ExifTags(exif=exif_ifd, gps=gps)), name)


def capture_status(path) -> tuple[CaptureInfo | None, str]:
    """Read capture info from an image's EXIF: ``(info, status)``, or ``(None, "{path}: reason")``."""
    try:
        meta = read_metadata(path)
    except FileNotFoundError:
        return None, f"{os.fspath(path)}: cannot read EXIF (file not found)"
    except Exception as exc:  # Pillow and exifread raise OSError, SyntaxError, struct.error, ... on corrupt files
        return None, f"{os.fspath(path)}: cannot read EXIF ({type(exc).__name__}: {exc})"
    return _capture_from_metadata(meta, os.fspath(path))


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
