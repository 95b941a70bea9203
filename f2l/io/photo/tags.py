"""A photo's EXIF tags as one table, read once: Pillow for JPEG, PNG, WebP and the other formats
it opens, ``exifread`` for TIFF-structured files (TIFF, DNG, CR2, NEF, ARW, ...) and RAW.

Conventions: :class:`ExifTags` holds three IFDs, IFD0 (``ifd0``), the Exif sub-IFD 0x8769
(``exif``) and the GPS IFD 0x8825 (``gps``), each a mapping of tag id -> the library's own value.
Pillow gives scalars (``IFDRational``, ``int``, ``str``, ``bytes``) for single values and tuples
for several; exifread a list (``Ratio`` numbers) or a ``str``/``bytes``. The parsers of
:mod:`f2l.io.photo.metadata` accept both. A reader raises what its library raises: the caller says
what an unreadable file means (no EXIF for a photo, ``RawError`` for a RAW, a status for the sun
prior).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

EXIF_IFD, GPS_IFD = 0x8769, 0x8825
_TIFF_MAGIC = (b"II*\x00", b"MM\x00*")
_EXIFREAD_IFDS = {"Image": "ifd0", "EXIF": "exif", "GPS": "gps"}
_UNKNOWN_TAG = re.compile(r"Tag 0x([0-9A-Fa-f]{4})")

# exifread warns about odd tags through its logger; without a handler that would reach stderr.
logging.getLogger("exifread").addHandler(logging.NullHandler())


@dataclass(frozen=True)
class ExifTags:
    """IFD0, Exif and GPS tags (tag id -> value as the library gives it; module docstring)."""

    ifd0: Mapping = field(default_factory=dict)
    exif: Mapping = field(default_factory=dict)
    gps: Mapping = field(default_factory=dict)

    def __post_init__(self):
        for name in ("ifd0", "exif", "gps"):
            object.__setattr__(self, name, MappingProxyType(dict(getattr(self, name))))

    def get(self, tag: int, default=None):
        """A tag of the Exif sub-IFD, else of IFD0 (the Exif value wins where both hold it)."""
        if tag in self.exif:
            return self.exif[tag]
        return self.ifd0.get(tag, default)


def pillow_tags(image, gps: bool = True) -> ExifTags:
    """The tags of an open Pillow image (no second read of the file); raises on broken EXIF.
    ``gps=False`` leaves the GPS IFD unread (a photo's decoding has no use for it)."""
    exif = image.getexif()
    return ExifTags(dict(exif), dict(exif.get_ifd(EXIF_IFD)), dict(exif.get_ifd(GPS_IFD)) if gps else {})


def _exifread_names() -> dict[str, dict[str, int]]:
    from exifread.tags.exif import EXIF_TAGS, GPS_TAGS

    ifd0 = {entry[0]: tag for tag, entry in EXIF_TAGS.items()}
    return {"ifd0": ifd0, "exif": ifd0, "gps": {entry[0]: tag for tag, entry in GPS_TAGS.items()}}


def from_exifread(tags: Mapping) -> ExifTags:
    """An :class:`ExifTags` of exifread's ``process_file`` result (``"EXIF ExposureTime"`` ->
    ``IfdTag``); tags are placed by their name (``"Tag 0xC612"`` for ones exifread does not
    name), other IFDs (thumbnail, sub-IFDs, maker notes) are left out."""
    names = _exifread_names()
    out = {"ifd0": {}, "exif": {}, "gps": {}}
    for key, tag in tags.items():
        prefix, _, name = key.partition(" ")
        ifd = _EXIFREAD_IFDS.get(prefix)
        if ifd is None or getattr(tag, "values", None) is None:
            continue
        unknown = _UNKNOWN_TAG.fullmatch(name)
        tag_id = int(unknown[1], 16) if unknown else names[ifd].get(name, getattr(tag, "tag", None))
        if isinstance(tag_id, int):
            out[ifd][tag_id] = tag.values
    return ExifTags(**out)


def exifread_tags(path: str) -> tuple[ExifTags, dict]:
    """(:class:`ExifTags`, exifread's whole result) of a file, read once by exifread (no
    thumbnail); raises what exifread raises on a malformed header."""
    import exifread

    with open(path, "rb") as fh:
        tags = exifread.process_file(fh, details=False, extract_thumbnail=False)
    return from_exifread(tags), tags


def read_tags(path: str) -> ExifTags:
    """The tags of a file: exifread for TIFF-structured files (TIFF, DNG and most RAW), Pillow
    for everything else; raises what the library raises (``FileNotFoundError`` included)."""
    with open(path, "rb") as fh:
        head = fh.read(4)
    if head in _TIFF_MAGIC:
        return exifread_tags(path)[0]
    from PIL import Image

    with Image.open(path) as image:
        return pillow_tags(image)
