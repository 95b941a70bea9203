"""Capture metadata (EXIF GPS + time, record meta) and the sun's position from it."""

import json
import math
from dataclasses import replace
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest
from astral import Observer
from astral.sun import elevation as astral_elevation
from PIL import Image
from PIL.TiffImagePlugin import IFDRational

from f2l.io.capture import (
    CaptureInfo,
    capture_from_exif_tags,
    capture_from_meta,
    capture_status,
    capture_to_meta,
    read_capture,
    solar_position,
)

GPS_IFD, EXIF_IFD = 0x8825, 0x8769
LAT_REF, LAT, LON_REF, LON, ALT_REF, ALT, GPS_TIME, GPS_DATE = 1, 2, 3, 4, 5, 6, 7, 29
DATE_TIME_ORIGINAL, OFFSET_TIME_ORIGINAL, SUBSEC_TIME_ORIGINAL = 0x9003, 0x9011, 0x9291
UTC = timezone.utc
GREENWICH = 51.4769


def rational(value):
    return IFDRational(value)


def dms(degrees, minutes, seconds):
    return tuple(rational(v) for v in (degrees, minutes, seconds))


# Southern/eastern (Sydney) and northern/western (New York harbour) positions.
SOUTH_EAST = {LAT_REF: "S", LAT: dms(33, 51, 35.51), LON_REF: "E", LON: dms(151, 12, 54.25)}
NORTH_WEST = {LAT_REF: "N", LAT: dms(40, 41, 21), LON_REF: "W", LON: dms(74, 2, 40.2)}


def write_image(path, gps=None, exif_ifd=None, fmt="JPEG"):
    """An 8x8 image whose EXIF holds the given GPS and Exif IFD tags (tag id -> value)."""
    exif = Image.Exif()
    if gps:
        exif.get_ifd(GPS_IFD).update(gps)
    if exif_ifd:
        exif.get_ifd(EXIF_IFD).update(exif_ifd)
    # Passing bytes makes every format (TIFF included) serialise the sub-IFDs.
    Image.new("RGB", (8, 8), (90, 120, 150)).save(path, fmt, exif=exif.tobytes())
    return path


def gps_time(day, hours, minutes, seconds):
    return {GPS_DATE: day, GPS_TIME: (rational(hours), rational(minutes), rational(seconds))}


# --------------------------------------------------------------------------- EXIF: usable


@pytest.mark.parametrize("fmt, suffix", [("JPEG", ".jpg"), ("TIFF", ".tif"), ("PNG", ".png")])
def test_gps_position_and_gps_time(tmp_path, fmt, suffix):
    gps = {**SOUTH_EAST, **gps_time("2024:06:20", 12, 2, 30.5), ALT_REF: b"\x00", ALT: rational(123.4)}
    path = write_image(tmp_path / f"IMG_1{suffix}", gps, fmt=fmt)
    info = read_capture(path)
    assert info is not None
    assert info.source == "exif-gps-time"
    assert info.latitude_deg == pytest.approx(-(33 + 51 / 60 + 35.51 / 3600), abs=1e-12)
    assert info.longitude_deg == pytest.approx(151 + 12 / 60 + 54.25 / 3600, abs=1e-12)
    assert info.altitude_m == pytest.approx(123.4, abs=1e-12)
    assert info.utc == datetime(2024, 6, 20, 12, 2, 30, 500000, tzinfo=UTC)
    assert info.utc.tzinfo == UTC


def test_west_longitude_and_below_sea_level(tmp_path):
    gps = {**NORTH_WEST, **gps_time("2024:01:05", 0, 0, 0), ALT_REF: b"\x01", ALT: rational(28)}
    info = read_capture(write_image(tmp_path / "below_sea_level.jpg", gps))
    assert info.latitude_deg == pytest.approx(40 + 41 / 60 + 21 / 3600, abs=1e-12)
    assert info.longitude_deg == pytest.approx(-(74 + 2 / 60 + 40.2 / 3600), abs=1e-12)
    assert info.altitude_m == -28.0
    assert info.utc == datetime(2024, 1, 5, tzinfo=UTC)


def test_offset_time_with_subseconds(tmp_path):
    exif_ifd = {DATE_TIME_ORIGINAL: "2024:06:20 14:02:30", OFFSET_TIME_ORIGINAL: "+02:00", SUBSEC_TIME_ORIGINAL: "25"}
    info, status = capture_status(write_image(tmp_path / "local.jpg", SOUTH_EAST, exif_ifd))
    assert info.source == "exif-offset-time"
    assert info.utc == datetime(2024, 6, 20, 12, 2, 30, 250000, tzinfo=UTC)
    assert info.altitude_m is None
    assert "local.jpg" in status and "exif-offset-time" in status


def test_negative_offset_crosses_the_year(tmp_path):
    exif_ifd = {DATE_TIME_ORIGINAL: "2023:12:31 22:15:00", OFFSET_TIME_ORIGINAL: "-05:00"}
    info = read_capture(write_image(tmp_path / "nye.jpg", NORTH_WEST, exif_ifd))
    assert info.utc == datetime(2024, 1, 1, 3, 15, tzinfo=UTC)


def test_gps_time_preferred_over_local_time(tmp_path):
    gps = {**SOUTH_EAST, **gps_time("2024:06:20", 12, 0, 0)}
    close = {DATE_TIME_ORIGINAL: "2024:06:20 14:01:00", OFFSET_TIME_ORIGINAL: "+02:00"}
    info, status = capture_status(write_image(tmp_path / "both.jpg", gps, close))
    assert info.source == "exif-gps-time"
    assert info.utc == datetime(2024, 6, 20, 12, 0, tzinfo=UTC)
    assert "differs" not in status
    # A camera clock on home time (3 h off) is overruled by GPS, and the status says so.
    far = {DATE_TIME_ORIGINAL: "2024:06:20 17:00:00", OFFSET_TIME_ORIGINAL: "+02:00"}
    info, status = capture_status(write_image(tmp_path / "home_clock.jpg", gps, far))
    assert info.utc == datetime(2024, 6, 20, 12, 0, tzinfo=UTC)
    assert "differs from GPS time by +3.00 h" in status


def test_local_time_without_offset_is_fine_when_gps_time_exists(tmp_path):
    gps = {**SOUTH_EAST, **gps_time("2024:03:01", 23, 59, 59)}
    info = read_capture(write_image(tmp_path / "gps_only.jpg", gps, {DATE_TIME_ORIGINAL: "2024:03:02 10:59:59"}))
    assert info.source == "exif-gps-time"
    assert info.utc == datetime(2024, 3, 1, 23, 59, 59, tzinfo=UTC)


def test_malformed_gps_time_falls_back_to_offset_time(tmp_path):
    gps = {**SOUTH_EAST, **gps_time("2024:13:40", 12, 0, 0)}
    exif_ifd = {DATE_TIME_ORIGINAL: "2024:06:20 14:00:00", OFFSET_TIME_ORIGINAL: "+02:00"}
    info, status = capture_status(write_image(tmp_path / "bad_gps_date.jpg", gps, exif_ifd))
    assert info.source == "exif-offset-time"
    assert info.utc == datetime(2024, 6, 20, 12, 0, tzinfo=UTC)
    assert "GPS time ignored" in status and "GPSDateStamp" in status


def test_malformed_altitude_is_dropped_with_a_note(tmp_path):
    gps = {**SOUTH_EAST, **gps_time("2024:06:20", 12, 0, 0), ALT: IFDRational(5, 0)}
    info, status = capture_status(write_image(tmp_path / "bad_alt.jpg", gps))
    assert info is not None and info.altitude_m is None
    assert "altitude ignored" in status and "GPSAltitude" in status


# --------------------------------------------------------------------------- EXIF: unusable

UNUSABLE_FILES = [
    ("no_gps.jpg", None, {DATE_TIME_ORIGINAL: "2024:06:20 14:00:00", OFFSET_TIME_ORIGINAL: "+02:00"},
     "no GPS position in EXIF"),
    ("no_exif.jpg", None, None, "no GPS position in EXIF"),
    ("no_zone.jpg", SOUTH_EAST, {DATE_TIME_ORIGINAL: "2024:06:20 14:00:00"},
     "DateTimeOriginal has no OffsetTimeOriginal and there is no GPS time: time zone unknown"),
    ("blank_zone.jpg", SOUTH_EAST, {DATE_TIME_ORIGINAL: "2024:06:20 14:00:00", OFFSET_TIME_ORIGINAL: "   :  "},
     "time zone unknown"),
    ("no_time.jpg", SOUTH_EAST, None, "no capture time in EXIF"),
    ("nan_lat.jpg", {**SOUTH_EAST, LAT: (IFDRational(1, 0), IFDRational(0, 0), rational(1))}, None,
     "GPSLatitude must be finite"),
    ("bad_ref.jpg", {**SOUTH_EAST, LAT_REF: "X"}, None, "GPSLatitudeRef is 'X'"),
    ("no_ref.jpg", {LAT: dms(10, 0, 0), LON_REF: "E", LON: dms(10, 0, 0)}, None, "GPSLatitudeRef is missing"),
    ("lat_95.jpg", {**SOUTH_EAST, LAT: dms(95, 0, 0)}, None, "GPSLatitude 95 is beyond 90 degrees"),
    ("lon_4_values.jpg", {**SOUTH_EAST, LON: (rational(1), rational(2), rational(3), rational(4))}, None,
     "GPSLongitude has 4 values"),
    ("bad_date_time.jpg", SOUTH_EAST, {DATE_TIME_ORIGINAL: "garbage", OFFSET_TIME_ORIGINAL: "+02:00"},
     "DateTimeOriginal 'garbage' is not 'YYYY:MM:DD HH:MM:SS'"),
    ("hour_25.jpg", SOUTH_EAST, {DATE_TIME_ORIGINAL: "2024:06:20 25:00:00", OFFSET_TIME_ORIGINAL: "+02:00"},
     "not a valid date and time"),
    ("bad_offset.jpg", SOUTH_EAST, {DATE_TIME_ORIGINAL: "2024:06:20 14:00:00", OFFSET_TIME_ORIGINAL: "+99:00"},
     "OffsetTimeOriginal '+99:00'"),
    ("gps_hour_25.jpg", {**SOUTH_EAST, **gps_time("2024:06:20", 25, 0, 0)}, None, "GPSTimeStamp"),
    ("gps_bad_date_no_zone.jpg", {**SOUTH_EAST, **gps_time("2024:02:30", 12, 0, 0)},
     {DATE_TIME_ORIGINAL: "2024:06:20 14:00:00"}, "no usable GPS time: time zone unknown"),
]


@pytest.mark.parametrize("name, gps, exif_ifd, reason", UNUSABLE_FILES, ids=[case[0] for case in UNUSABLE_FILES])
def test_unusable_exif_gives_none_and_a_reason_naming_the_file(tmp_path, name, gps, exif_ifd, reason):
    path = write_image(tmp_path / name, gps, exif_ifd)
    info, status = capture_status(path)
    assert info is None
    assert read_capture(path) is None
    assert status.startswith(f"{path}: ")
    assert reason in status


def test_unreadable_files_do_not_raise(tmp_path):
    not_an_image = tmp_path / "notes.jpg"
    not_an_image.write_text("not a JPEG")
    for path in (not_an_image, tmp_path / "missing.jpg"):
        info, status = capture_status(path)
        assert info is None
        assert status.startswith(f"{path}: cannot read EXIF")
    assert capture_status(tmp_path / "missing.jpg")[1].endswith("(file not found)")


GARBAGE_TAGS = [
    ({**SOUTH_EAST, LAT: "garbage"}, {}, "GPSLatitude must be a number"),
    ({**SOUTH_EAST, LAT: [1.0, None, 2.0]}, {}, "GPSLatitude must be a number"),
    ({**SOUTH_EAST, LAT: (True, 0, 0)}, {}, "GPSLatitude must be a number"),
    ({**SOUTH_EAST, LON: ()}, {}, "GPSLongitude has 0 values"),
    ({**SOUTH_EAST, LAT_REF: b"\xff"}, {}, "GPSLatitudeRef is not ASCII text"),
    ({**SOUTH_EAST, LON_REF: 7}, {}, "GPSLongitudeRef is not text"),
    ({**SOUTH_EAST, GPS_DATE: "2024:06:20", GPS_TIME: "12:00:00"}, {}, "GPSTimeStamp"),
    ({**SOUTH_EAST, GPS_DATE: 20240620, GPS_TIME: (12.0, 0.0, 0.0)}, {}, "GPSDateStamp is not text"),
    ({**SOUTH_EAST, GPS_DATE: "2024:06:20", GPS_TIME: (12.0, 0.0)}, {}, "GPSTimeStamp has 2 values, expected 3"),
    (SOUTH_EAST, {DATE_TIME_ORIGINAL: 20240620, OFFSET_TIME_ORIGINAL: "+02:00"}, "DateTimeOriginal is not text"),
    (SOUTH_EAST, {DATE_TIME_ORIGINAL: "2024:06:20 14:00:00", OFFSET_TIME_ORIGINAL: ["+02:00"]},
     "OffsetTimeOriginal is not text"),
]


@pytest.mark.parametrize("gps, exif_ifd, reason", GARBAGE_TAGS)
def test_garbage_tag_values_give_none_and_a_reason(gps, exif_ifd, reason):
    info, status = capture_from_exif_tags(gps, exif_ifd, "IMG_7.jpg")
    assert info is None
    assert status.startswith("IMG_7.jpg: ")
    assert reason in status


def test_garbage_optional_values_are_ignored():
    gps = {**SOUTH_EAST, **gps_time("2024:06:20", 12, 0, 0), ALT: 100.0, ALT_REF: "below"}
    info, status = capture_from_exif_tags(gps, {SUBSEC_TIME_ORIGINAL: b"\xff"}, "IMG_8.jpg")
    assert info.utc == datetime(2024, 6, 20, 12, tzinfo=UTC)
    assert info.altitude_m is None
    assert "GPSAltitudeRef" in status


# --------------------------------------------------------------------------- record metadata


def test_meta_round_trip():
    info = CaptureInfo(datetime(2024, 6, 20, 12, 2, 30, 250000, tzinfo=UTC), -33.86, 151.215, 42.5, "exif-gps-time")
    meta = capture_to_meta(info)
    assert meta["capture"]["utc"] == "2024-06-20T12:02:30.250000Z"
    back = capture_from_meta(json.loads(json.dumps(meta)))
    assert back == replace(info, source="meta")
    no_altitude = replace(info, altitude_m=None, source="meta")
    assert "altitude_m" not in capture_to_meta(no_altitude)["capture"]
    assert capture_from_meta(capture_to_meta(no_altitude)) == no_altitude


def test_meta_offsets_are_normalised_to_utc():
    meta = {"capture": {"utc": "2024-06-20T14:02:00+02:00", "latitude_deg": 10, "longitude_deg": -20}}
    info = capture_from_meta(meta)
    assert info.utc == datetime(2024, 6, 20, 12, 2, tzinfo=UTC) and info.utc.tzinfo == UTC
    assert (info.latitude_deg, info.longitude_deg, info.altitude_m, info.source) == (10.0, -20.0, None, "meta")
    assert capture_from_meta({"capture": {**meta["capture"], "utc": "2024-06-20T12:02:00Z"}}).utc == info.utc


def test_meta_without_capture_is_none():
    assert capture_from_meta({}) is None
    assert capture_from_meta({"capture": None, "other": 1}) is None


@pytest.mark.parametrize(
    "change, message",
    [
        ({"latitude_deg": 90.5}, "latitude_deg must be in [-90, 90]"),
        ({"latitude_deg": -91}, "latitude_deg must be in [-90, 90]"),
        ({"longitude_deg": 180.01}, "longitude_deg must be in [-180, 180]"),
        ({"latitude_deg": "51.5"}, "latitude_deg must be a number"),
        ({"latitude_deg": True}, "latitude_deg must be a number"),
        ({"longitude_deg": float("nan")}, "longitude_deg must be finite"),
        ({"altitude_m": float("inf")}, "altitude_m must be finite"),
        ({"utc": "2024-06-20T12:00:00"}, "has no UTC offset"),
        ({"utc": "yesterday"}, "is not ISO-8601"),
        ({"utc": 1718884800}, "must be an ISO-8601 string"),
    ],
)
def test_meta_rejects_bad_values(change, message):
    block = {"utc": "2024-06-20T12:00:00Z", "latitude_deg": 51.5, "longitude_deg": 0.0, **change}
    with pytest.raises(ValueError, match=message.replace("[", r"\[").replace("]", r"\]")):
        capture_from_meta({"capture": block})


def test_meta_rejects_missing_keys_and_non_mappings():
    with pytest.raises(ValueError, match="missing latitude_deg, longitude_deg"):
        capture_from_meta({"capture": {"utc": "2024-06-20T12:00:00Z"}})
    with pytest.raises(ValueError, match="must be a mapping"):
        capture_from_meta({"capture": [1, 2]})


def test_capture_info_validates():
    with pytest.raises(ValueError, match="timezone-aware"):
        CaptureInfo(datetime(2024, 6, 20, 12), 0.0, 0.0)
    with pytest.raises(ValueError, match="source"):
        CaptureInfo(datetime(2024, 6, 20, 12, tzinfo=UTC), 0.0, 0.0, None, "guess")


# --------------------------------------------------------------------------- sun position


def sun_at(utc, latitude, longitude):
    elevation, azimuth = solar_position(CaptureInfo(utc, latitude, longitude))
    return math.degrees(elevation), math.degrees(azimuth)


def test_june_solstice_noon_at_greenwich():
    elevation, azimuth = sun_at(datetime(2024, 6, 20, 12, 2, tzinfo=UTC), GREENWICH, 0.0)
    assert elevation == pytest.approx(90.0 - GREENWICH + 23.44, abs=0.3)
    assert azimuth == pytest.approx(180.0, abs=1.0)  # due south


def test_equinox_noon_at_the_equator_is_near_zenith():
    elevation, _ = sun_at(datetime(2024, 3, 20, 12, 7, tzinfo=UTC), 0.0, 0.0)
    assert elevation > 89.0


def test_december_midnight_at_greenwich_is_night():
    elevation, azimuth = sun_at(datetime(2024, 12, 21, 0, 0, tzinfo=UTC), GREENWICH, 0.0)
    assert elevation < 0.0
    assert elevation == pytest.approx(-(90.0 - GREENWICH) - 23.44, abs=0.5)
    assert min(azimuth, 360.0 - azimuth) < 2.0  # due north
    assert 0.0 <= azimuth < 360.0


def test_sun_from_exif_end_to_end(tmp_path):
    gps = {LAT_REF: "N", LAT: dms(51, 28, 36.84), LON_REF: "E", LON: dms(0, 0, 0), **gps_time("2024:06:20", 12, 2, 0)}
    info = read_capture(write_image(tmp_path / "greenwich.jpg", gps))
    elevation, _ = solar_position(info)
    assert math.degrees(elevation) == pytest.approx(61.96, abs=0.3)


def saemundsson_refraction(geometric_deg):
    """Atmospheric refraction in degrees for a geometric elevation (Saemundsson 1986, 10 C, 101 kPa)."""
    return 1.02 / math.tan(math.radians(geometric_deg + 10.3 / (geometric_deg + 5.11))) / 60.0


def reference_sun(utc, latitude, longitude):
    """Geometric (no refraction) sun elevation and azimuth in degrees, written independently of astral.

    The Astronomical Almanac's low-precision solar coordinates (Michalsky 1988, about 0.01 degree):
    mean longitude and anomaly -> ecliptic longitude -> right ascension and declination, and the
    hour angle from Greenwich mean sidereal time. (The NOAA/Spencer Fourier series was tried first:
    it is off by up to 0.6 degree in elevation and 2.6 degrees in azimuth over 2000-2040, too coarse
    to check astral's ~0.01 degree.)
    """
    days = (utc - datetime(2000, 1, 1, 12, tzinfo=UTC)).total_seconds() / 86400.0  # since J2000.0
    mean_longitude = 280.460 + 0.9856474 * days
    anomaly = math.radians(357.528 + 0.9856003 * days)
    ecliptic_longitude = math.radians(mean_longitude + 1.915 * math.sin(anomaly) + 0.020 * math.sin(2 * anomaly))
    obliquity = math.radians(23.439 - 0.0000004 * days)
    right_ascension = math.atan2(math.cos(obliquity) * math.sin(ecliptic_longitude), math.cos(ecliptic_longitude))
    decl = math.asin(math.sin(obliquity) * math.sin(ecliptic_longitude))
    sidereal_hours = 18.697374558 + 24.06570982441908 * days
    hour_angle = math.radians(sidereal_hours * 15.0 + longitude) - right_ascension
    lat = math.radians(latitude)
    sin_el = math.sin(lat) * math.sin(decl) + math.cos(lat) * math.cos(decl) * math.cos(hour_angle)
    azimuth = math.atan2(-math.sin(hour_angle) * math.cos(decl),
                         math.cos(lat) * math.sin(decl) - math.sin(lat) * math.cos(decl) * math.cos(hour_angle))
    return math.degrees(math.asin(sin_el)), math.degrees(azimuth) % 360.0


def test_reference_sun_sanity():
    # Equinox (2024-03-20 03:06 UTC): declination ~0, so the sun at the equator culminates at the zenith.
    elevation, _ = reference_sun(datetime(2024, 3, 20, 12, 7, tzinfo=UTC), 0.0, 0.0)
    assert elevation > 89.5
    elevation, azimuth = reference_sun(datetime(2024, 6, 20, 12, 2, tzinfo=UTC), GREENWICH, 0.0)
    assert elevation == pytest.approx(90.0 - GREENWICH + 23.44, abs=0.05)
    assert azimuth == pytest.approx(180.0, abs=1.0)


def test_matches_an_independent_implementation():
    rng = np.random.default_rng(20240620)
    start = datetime(2000, 1, 1, tzinfo=UTC)
    span = (datetime(2040, 1, 1, tzinfo=UTC) - start).total_seconds()
    checked = 0
    for _ in range(50):
        utc = start + timedelta(seconds=float(rng.uniform(0, span)))
        latitude, longitude = float(rng.uniform(-85, 85)), float(rng.uniform(-180, 180))
        elevation, azimuth = sun_at(utc, latitude, longitude)
        geometric, ref_azimuth = reference_sun(utc, latitude, longitude)
        if abs(geometric) > 1.0:
            assert (elevation > 0) == (geometric > 0), (utc, latitude, longitude)
        if geometric > 5.0:
            checked += 1
            # Within 0.5 degree even ignoring refraction; within 0.05 once refraction is added.
            assert elevation == pytest.approx(geometric, abs=0.5), (utc, latitude, longitude)
            apparent = geometric + saemundsson_refraction(geometric)
            assert elevation == pytest.approx(apparent, abs=0.05), (utc, latitude, longitude)
            if geometric < 80.0:  # azimuth is ill-conditioned near the zenith
                difference = (azimuth - ref_azimuth + 180.0) % 360.0 - 180.0
                assert abs(difference) < 0.1, (utc, latitude, longitude)
    assert checked >= 10


def test_elevation_includes_refraction():
    """Apparent minus geometric elevation follows Saemundsson's refraction formula."""
    observer = Observer(latitude=GREENWICH, longitude=0.0)
    compared = 0
    for minutes in range(0, 24 * 60, 20):
        utc = datetime(2024, 6, 20, tzinfo=UTC) + timedelta(minutes=minutes)
        geometric = astral_elevation(observer, utc, with_refraction=False)
        if not 0.5 <= geometric <= 60.0:
            continue
        compared += 1
        apparent, _ = sun_at(utc, GREENWICH, 0.0)
        assert apparent - geometric == pytest.approx(saemundsson_refraction(geometric), abs=0.03), geometric
    assert compared > 20
