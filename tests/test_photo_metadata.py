"""The one metadata reader (f2l.io.photo.metadata): its three callers, Photo.exif (f2l.io.photo),
RawMeta (f2l.io.raw_meta) and the sun prior's capture info (f2l.io.capture), read the same values
from the same file, and Pillow and exifread give the same PhotoMetadata."""

import dataclasses
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from PIL.TiffImagePlugin import IFDRational

from f2l.capture.dng import write_dng
from f2l.io.capture import capture_status
from f2l.io.photo import load_photo
from f2l.io.photo.metadata import PhotoMetadata, metadata_from_image, read_metadata
from f2l.io.photo.tags import exifread_tags
from f2l.io.raw_meta import exif_fields, read_raw_metadata

CR2 = Path(__file__).resolve().parents[2] / "shared/data/raw/IMG_5952.CR2"
GPS_IFD, EXIF_IFD = 0x8825, 0x8769
R = IFDRational
TZ = timezone(timedelta(hours=2))


def _photo_with_exif(path, fmt):
    exif = Image.Exif()
    exif.update({271: "Maker", 272: "Cam 1", 274: 1})
    exif.get_ifd(EXIF_IFD).update({
        33434: R(1, 250), 33437: R(28, 10), 34855: 200, 37386: R(35), 36867: "2024:06:20 14:02:30",
        0x9011: "+02:00", 0x9291: "25", 0xA434: "Lens 35",
    })  # fmt: skip
    exif.get_ifd(GPS_IFD).update({
        1: "S", 2: (R(33), R(51), R(35.51)), 3: "E", 4: (R(151), R(12), R(54.25)), 5: b"\x00", 6: R(123.4),
    })  # fmt: skip
    Image.new("RGB", (24, 16), (90, 120, 150)).save(path, fmt, exif=exif.tobytes())
    return path


def _assert_callers_agree(path, photo=None):
    """Photo.exif, RawMeta fields and capture info of one file against its PhotoMetadata."""
    meta = read_metadata(path)
    photo = photo or load_photo(path, stream=False)
    fields = exif_fields(path)
    for key in ("exposure_s", "f_number", "focal_length_mm"):
        assert photo.exif.get(key) == fields[key] == getattr(meta, key)
    assert photo.exif["iso"] == round(fields["iso"]) and fields["iso"] == meta.iso
    assert (photo.exif["make"], photo.exif["model"]) == (fields["make"], fields["model"]) == (meta.make, meta.model)
    assert photo.exif["datetime_original"] == fields["timestamp"].strftime("%Y:%m:%d %H:%M:%S")
    assert photo.orientation == fields["orientation"] == meta.orientation
    position = (fields["gps_latitude_deg"], fields["gps_longitude_deg"], fields["gps_altitude_m"])
    assert position == (meta.latitude_deg, meta.longitude_deg, meta.altitude_m)
    info, status = capture_status(path)
    if position[0] is None:
        assert info is None and status.endswith("no GPS position in EXIF")
    else:
        assert (info.latitude_deg, info.longitude_deg, info.altitude_m) == position, status
        if fields["timestamp"].tzinfo is not None:
            assert info.source == "exif-offset-time" and info.utc == fields["timestamp"]
    return meta, fields, info


@pytest.mark.parametrize("fmt, suffix", [("JPEG", ".jpg"), ("PNG", ".png"), ("TIFF", ".tif")])
def test_three_callers_agree_on_a_photo_with_gps(tmp_path, fmt, suffix):
    path = _photo_with_exif(tmp_path / f"IMG_1{suffix}", fmt)
    meta, fields, info = _assert_callers_agree(path)
    assert fields["timestamp"] == datetime(2024, 6, 20, 14, 2, 30, 250000, tzinfo=TZ)
    assert info.utc == datetime(2024, 6, 20, 12, 2, 30, 250000, tzinfo=timezone.utc)
    assert meta.latitude_deg == pytest.approx(-(33 + 51 / 60 + 35.51 / 3600))
    assert meta.lens == fields["lens"] == "Lens 35"


def test_pillow_and_exifread_read_the_same_metadata(tmp_path):
    for fmt, suffix in [("JPEG", ".jpg"), ("PNG", ".png"), ("TIFF", ".tif")]:
        path = _photo_with_exif(tmp_path / f"IMG_2{suffix}", fmt)
        with Image.open(path) as image:
            by_pillow = metadata_from_image(image)
        by_exifread = read_metadata(path, backend="exifread")
        assert by_pillow == by_exifread  # every typed field; the raw tags differ in type only
        assert by_pillow.latitude_deg is not None and by_pillow.offset_utc is not None


def test_three_callers_agree_on_a_dng_with_gps_and_offset_time(tmp_path):
    mosaic = np.random.default_rng(0).integers(256, 4000, (64, 64)).astype(np.uint16)
    path = write_dng(tmp_path / "gps.dng", mosaic, exposure_s=1 / 8, f_number=4, iso=400, make="Acme", model="R1",
                     focal_length_mm=24, timestamp=datetime(2024, 6, 21, 12, 0, 0, tzinfo=TZ),
                     gps=(46.5, -6.25, 1200.0))  # fmt: skip
    meta, fields, info = _assert_callers_agree(path)
    assert info is not None and info.utc == datetime(2024, 6, 21, 10, 0, tzinfo=timezone.utc)
    assert (meta.latitude_deg, meta.longitude_deg) == pytest.approx((46.5, -6.25))
    raw = read_raw_metadata(path, levels=False)
    assert (raw.timestamp, raw.gps_latitude_deg, raw.gps_altitude_m) == (info.utc, info.latitude_deg, info.altitude_m)
    assert (raw.cfa_pattern, raw.white_level) == ("RGGB", 4095.0) and meta.dng_layout is not None


def test_three_callers_agree_on_the_real_canon_raw():
    if not CR2.exists():
        pytest.skip(f"real Canon RAW not available at {CR2}")
    meta, fields, info = _assert_callers_agree(CR2)
    assert (meta.exposure_s, meta.f_number, meta.iso, meta.focal_length_mm) == (1 / 400, 22.0, 640.0, 22.0)
    assert (meta.make, meta.model) == ("Canon", "Canon EOS 30D")
    assert fields["timestamp"] == meta.camera_time == meta.local_time == datetime(2009, 7, 21, 13, 3, 20)
    assert meta.utc_offset is None and info is None  # no GPS, no time zone: no sun prior
    quick = read_raw_metadata(CR2, levels=False)
    assert (quick.exposure_s, quick.f_number, quick.iso, quick.timestamp) == (
        meta.exposure_s, meta.f_number, meta.iso, meta.camera_time)
    tags, everything = exifread_tags(str(CR2))
    assert tags.exif[33434] == everything["EXIF ExposureTime"].values  # placed by tag id, values as exifread's


def test_unusable_gps_is_refused_alike_by_every_caller(tmp_path):
    exif = Image.Exif()
    exif.get_ifd(EXIF_IFD).update({36867: "2024:06:20 14:02:30", 0x9011: "+02:00"})
    exif.get_ifd(GPS_IFD).update({2: (R(33), R(51), R(0)), 3: "E", 4: (R(151), R(12), R(0))})  # no LatitudeRef
    path = tmp_path / "no_ref.jpg"
    Image.new("RGB", (24, 16)).save(path, exif=exif.tobytes())
    meta = read_metadata(path)
    assert meta.latitude_deg is None and meta.problems["position"] == "GPSLatitudeRef is missing: hemisphere unknown"
    assert exif_fields(path)["gps_latitude_deg"] is None
    assert capture_status(path) == (None, f"{path}: GPSLatitudeRef is missing: hemisphere unknown")


def test_metadata_is_frozen_and_empty_without_exif(tmp_path):
    path = tmp_path / "plain.png"
    Image.new("RGB", (24, 16)).save(path)
    meta = read_metadata(path)
    assert dataclasses.replace(meta, problems=PhotoMetadata().problems) == PhotoMetadata()
    assert meta.orientation == 1 and dict(meta.problems) == {"position": "no GPS position in EXIF"}
    with pytest.raises(dataclasses.FrozenInstanceError):
        meta.exposure_s = 1.0
