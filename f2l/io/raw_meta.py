"""Camera RAW files: metadata, the visible Bayer mosaic, CFA helpers; one clear error type.

Conventions:

- EXIF (exposure, aperture, ISO, time, camera, lens, focal length, orientation, GPS, DNG colour
  matrices and levels) comes from the one metadata reader, :mod:`f2l.io.photo.metadata` through
  ``exifread`` (:func:`exif_fields`, no pixel decode, about 1 ms); ``rawpy``
  (LibRaw) supplies the sensor layout: visible size, black levels, white level, CFA pattern. LibRaw
  reports the layout only after decoding the pixels (a Canon black level is measured on masked
  pixels), so :func:`read_raw` returns metadata and mosaic from one decode. Where EXIF lacks
  exposure, aperture, ISO or time, LibRaw's own parse (``RawPy.other``, rawpy >= 0.25) fills in.
- ``black_levels`` are per 2x2 CFA position in row-major order (top-left, top-right, bottom-left,
  bottom-right of the visible mosaic), ``cfa_pattern`` names the colours at those positions
  (``"RGGB"``); a non-2x2 layout (X-Trans) gives its full pattern, row-major.
- Exposure factor ``e = t * (ISO / 100) / N**2`` (t in seconds, N the f-number), ``EV100 =
  -log2(e)``; ``(raw - black) / (white - black) / e`` is then independent of the exposure
  settings (see :mod:`f2l.capture.merge`).
- ``timestamp`` is DateTimeOriginal (else DateTime) plus SubSecTimeOriginal; it is timezone-aware
  only when the file records a usable OffsetTimeOriginal, otherwise naive camera-local time
  (``PhotoMetadata.camera_time``). GPS fields need their hemisphere references (else ``None``).
- ``xyz_to_camera`` is the DNG ColorMatrix for the D65 calibration (ColorMatrix2 when
  CalibrationIlluminant2 is D65, else ColorMatrix1), or LibRaw's built-in table for other formats:
  the 3x3 matrix taking CIE XYZ to camera RGB, row-major; ``None`` when unknown.
- Missing, empty, truncated or undecodable files raise ``RawError(f"{path}: reason")``, never a
  bare LibRaw exception. LibRaw silently zero-fills truncated TIFF-based files (DNG, CR2, NEF,
  ARW...), so the strip/tile extents recorded in every IFD are checked against the file size.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from datetime import datetime

import numpy as np

from f2l.io.photo.dng_tags import BAYER_PATTERNS
from f2l.io.photo.metadata import PhotoMetadata, metadata_from_tags
from f2l.io.photo.tags import exifread_tags

__all__ = [
    "RawError", "RawMeta", "RawFrame", "raw_frame", "exif_fields", "read_raw", "read_raw_metadata",
    "read_raw_mosaic", "bayer_mosaic", "quad_mean", "demosaic_bilinear", "camera_to_rec709", "rec709_to_camera_matrix", "BAYER_PATTERNS",
    "XYZ_TO_REC709",
]  # fmt: skip

_COLOUR_INDEX = {"R": 0, "G": 1, "B": 2}

XYZ_TO_REC709 = np.array(
    [[3.2404542, -1.5371385, -0.4985314], [-0.9692660, 1.8760108, 0.0415560], [0.0556434, -0.2040259, 1.0572252]]
)  # fmt: skip
"""CIE XYZ (D65) to linear Rec.709/sRGB primaries (IEC 61966-2-1)."""


class RawError(IOError):
    """A RAW file could not be read; the message is ``f"{path}: reason"``."""


@dataclass(frozen=True)
class RawMeta:
    """What one RAW frame records about itself (see the module docstring for conventions)."""

    path: str
    make: str
    model: str
    width: int
    height: int
    black_levels: tuple[float, float, float, float] | None
    white_level: float | None
    cfa_pattern: str | None
    exposure_s: float | None = None
    f_number: float | None = None
    iso: float | None = None
    timestamp: datetime | None = None
    lens: str | None = None
    focal_length_mm: float | None = None
    orientation: int = 1
    gps_latitude_deg: float | None = None
    gps_longitude_deg: float | None = None
    gps_altitude_m: float | None = None
    xyz_to_camera: tuple[float, ...] | None = None

    @property
    def camera(self) -> str:
        return f"{self.make} {self.model}".strip()

    @property
    def exposure_factor(self) -> float | None:
        """``t * (ISO / 100) / N**2``; ``None`` when any of the three is unknown."""
        if not (self.exposure_s and self.f_number and self.iso):
            return None
        return self.exposure_s * (self.iso / 100.0) / self.f_number**2

    @property
    def ev100(self) -> float | None:
        e = self.exposure_factor
        return None if e is None else -math.log2(e)


@dataclass(frozen=True)
class RawFrame:
    """An already-decoded frame: the visible mosaic (H, W) uint16 and its metadata."""

    mosaic: np.ndarray
    meta: RawMeta


def raw_frame(
    mosaic: np.ndarray, *, exposure_s: float, f_number: float, iso: float, black_level=0, white_level: float = 65535,
    cfa: str = "RGGB", name: str = "frame", make: str = "", model: str = "",
) -> RawFrame:  # fmt: skip
    """Wrap a decoded uint16 mosaic and its exposure settings as a :class:`RawFrame`."""
    mosaic = np.asarray(mosaic)
    blacks = (float(black_level),) * 4 if np.ndim(black_level) == 0 else tuple(float(b) for b in black_level)
    meta = RawMeta(path=name, make=make, model=model, width=mosaic.shape[-1], height=mosaic.shape[0],
                   black_levels=blacks, white_level=float(white_level), cfa_pattern=cfa,
                   exposure_s=exposure_s, f_number=f_number, iso=iso)  # fmt: skip
    return RawFrame(mosaic, meta)


def _open_rawpy(path: str, unpack: bool):
    import rawpy

    from f2l.io.native_stderr import native_output_to_log

    try:
        with native_output_to_log(logging.getLogger("f2l.capture.raw"), path):  # LibRaw's own messages
            raw = rawpy.RawPy()
            raw.open_file(path)
            if unpack:
                raw.unpack()
        return raw
    except rawpy.LibRawError as exc:
        reason = exc.args[0].decode(errors="replace") if exc.args and isinstance(exc.args[0], bytes) else str(exc)
        raise RawError(f"{path}: not a readable RAW file ({type(exc).__name__}: {reason})") from exc


def _check_file(path: str) -> int:
    try:
        size = os.path.getsize(path)
    except OSError as exc:
        raise RawError(f"{path}: cannot open ({exc.strerror or exc})") from exc
    if size == 0:
        raise RawError(f"{path}: empty file (0 bytes)")
    return size


def _check_extents(path: str, tags: dict, size: int) -> None:
    """Raise if any IFD's strips or tiles extend past the end of the file."""
    for key in tags:
        for kind in ("StripOffsets", "TileOffsets"):
            if not key.endswith(" " + kind):
                continue
            counts = tags.get(key[: -len("Offsets")] + "ByteCounts")
            if counts is None:
                continue
            ends = [int(o) + int(c) for o, c in zip(tags[key].values, counts.values)]
            if ends and max(ends) > size:
                raise RawError(f"{path}: truncated: image data needs {max(ends)} bytes, file has {size}")


def exif_fields(path: str | os.PathLike) -> dict:
    """The EXIF part of :class:`RawMeta` (no pixel decode, about a millisecond), as a dict.

    Checks the file is non-empty, has a parsable header and is not truncated (RawError otherwise).
    Fields EXIF lacks are ``None``; :func:`read_raw` fills them from LibRaw where it can.
    """
    return _exif(os.fspath(path))[0]


def _exif(path: str) -> tuple[dict, PhotoMetadata]:
    """The EXIF part of :class:`RawMeta` and the metadata it comes from (one read of the file)."""
    size = _check_file(path)
    try:
        tags, everything = exifread_tags(path)
    except Exception as exc:  # exifread raises assorted errors on malformed headers
        raise RawError(f"{path}: malformed EXIF/TIFF header ({type(exc).__name__}: {exc})") from exc
    _check_extents(path, everything, size)
    m = metadata_from_tags(tags)
    return {
        "make": m.make or "", "model": m.model or "", "exposure_s": m.exposure_s, "f_number": m.f_number,
        "iso": m.iso, "timestamp": m.camera_time, "lens": m.lens, "focal_length_mm": m.focal_length_mm,
        "orientation": m.orientation, "gps_latitude_deg": m.latitude_deg, "gps_longitude_deg": m.longitude_deg,
        "gps_altitude_m": m.altitude_m, "xyz_to_camera": m.xyz_to_camera,
    }, m  # fmt: skip


def read_raw(
    path: str | os.PathLike, *, exif: dict | None = None, mosaic: bool = True
) -> tuple[RawMeta, np.ndarray | None]:
    """Metadata and visible mosaic ((height, width) uint16, exactly as stored) with one decode.

    LibRaw decodes the pixels before it reports levels or the CFA, so metadata costs a decode too.
    ``exif`` reuses an :func:`exif_fields` result for the same file.
    """
    path = os.fspath(path)
    fields = dict(_exif(path)[0] if exif is None else exif)
    raw = _open_rawpy(path, unpack=True)
    try:
        pattern = np.asarray(raw.raw_pattern)
        desc = raw.color_desc.decode(errors="replace")
        cfa = "".join(desc[int(i)] if int(i) < len(desc) else "?" for i in pattern.ravel())
        per_channel = list(raw.black_level_per_channel)
        blacks = [float(per_channel[int(i)]) for i in pattern.ravel()[:4]] if pattern.shape == (2, 2) else [
            float(np.mean(per_channel))] * 4  # fmt: skip
        other = getattr(raw, "other", None)  # rawpy >= 0.25: LibRaw's own EXIF parse
        if other is not None:
            libraw = {"exposure_s": other.shutter_speed, "f_number": other.aperture, "iso": other.iso_speed}
            for key, value in libraw.items():
                fields[key] = fields[key] or (float(value) if value > 0 else None)
            fields["timestamp"] = fields["timestamp"] or getattr(other, "timestamp", None)
        lens_info = getattr(raw, "lens", None)
        fields["lens"] = fields["lens"] or (lens_info.model if lens_info and lens_info.model else None)
        if fields["xyz_to_camera"] is None:
            matrix = np.asarray(raw.rgb_xyz_matrix, dtype=float)[:3]
            fields["xyz_to_camera"] = tuple(float(v) for v in matrix.ravel()) if np.any(matrix) else None
        meta = RawMeta(path=path, width=int(raw.sizes.width), height=int(raw.sizes.height), black_levels=tuple(blacks),
                       white_level=float(raw.white_level), cfa_pattern=cfa, **fields)  # fmt: skip
        pixels = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True) if mosaic else None
    except RawError:
        raise
    except Exception as exc:
        raise RawError(f"{path}: cannot decode ({type(exc).__name__}: {exc})") from exc
    finally:
        raw.close()
    if pixels is not None and (pixels.ndim != 2 or pixels.shape != (meta.height, meta.width)):
        raise RawError(f"{path}: not a single-plane CFA mosaic of its stated size (shape {pixels.shape})")
    return meta, pixels


def read_raw_metadata(path: str | os.PathLike, *, levels: bool = True) -> RawMeta:
    """Exposure, camera and sensor-layout metadata of one RAW file (conventions above).

    LibRaw reports black/white levels and the CFA only after decoding the pixels (a Canon black
    level is measured on masked pixels), so for most formats this costs a decode. A DNG whose
    first IFD holds the CFA mosaic and states its layout completely (:func:`f2l.io.photo.dng_tags.dng_layout`: 2x2 Bayer
    CFAPattern, BlackLevel, WhiteLevel; no per-row/column black deltas, no linearisation table) is
    read from its tags alone, about a millisecond: LibRaw takes those very tags. ``levels=False``
    never decodes: CFA and levels come from DNG tags when the file has them, else ``None``;
    exposure, aperture and ISO then come from EXIF alone.
    """
    path = os.fspath(path)
    fields, m = _exif(path)
    layout = m.dng_layout
    if levels and layout is None:
        return read_raw(path, exif=fields, mosaic=False)[0]
    raw = _open_rawpy(path, unpack=False)
    try:
        width, height = int(raw.sizes.width), int(raw.sizes.height)
    finally:
        raw.close()
    if layout is not None:
        cfa, blacks, white = layout
        return RawMeta(path=path, width=width, height=height, black_levels=blacks, white_level=white, cfa_pattern=cfa,
                       **fields)  # fmt: skip
    cfa, blacks, white = m.tag_levels
    return RawMeta(path=path, width=width, height=height, black_levels=blacks, white_level=white, cfa_pattern=cfa,
                   **fields)  # fmt: skip


def read_raw_mosaic(path: str | os.PathLike) -> np.ndarray:
    """The visible Bayer mosaic, (height, width) uint16, exactly as stored (no scaling)."""
    return read_raw(path)[1]


def bayer_mosaic(rgb: np.ndarray, cfa: str = "RGGB") -> np.ndarray:
    """Sample an (H, W, 3) image on a 2x2 Bayer pattern; returns (H, W) of the same dtype."""
    if cfa not in BAYER_PATTERNS:
        raise ValueError(f"cfa must be one of {BAYER_PATTERNS}, got {cfa!r}")
    rgb = np.asarray(rgb)
    out = np.empty(rgb.shape[:2], dtype=rgb.dtype)
    for k, letter in enumerate(cfa):
        dy, dx = divmod(k, 2)
        out[dy::2, dx::2] = rgb[dy::2, dx::2, _COLOUR_INDEX[letter]]
    return out


def demosaic_bilinear(mosaic: np.ndarray, cfa: str = "RGGB") -> np.ndarray:
    """Bilinear demosaic of an (H, W) Bayer mosaic (H, W even) to (H, W, 3) float32 RGB.

    Each missing colour is the mean of its nearest same-colour samples (2 or 4), mirroring at the
    borders; known samples are kept exactly. Other patterns are mirror-padded to RGGB.
    """
    if cfa not in BAYER_PATTERNS:
        raise ValueError(f"cfa must be one of {BAYER_PATTERNS}, got {cfa!r}")
    m = np.asarray(mosaic, dtype=np.float32)
    if m.ndim != 2 or m.shape[0] % 2 or m.shape[1] % 2:
        raise ValueError(f"mosaic must be 2-D with even sides, got shape {m.shape}")
    oy, ox = divmod(cfa.index("R"), 2)
    if oy or ox:
        padded = np.pad(m, ((oy, oy), (ox, ox)), mode="reflect")
        return demosaic_bilinear(padded, "RGGB")[oy : oy + m.shape[0], ox : ox + m.shape[1]]
    r, g1, g2, b = m[0::2, 0::2], m[0::2, 1::2], m[1::2, 0::2], m[1::2, 1::2]
    h, w = r.shape
    out = np.empty((h, 2, w, 2, 3), np.float32)
    half = np.float32(0.5)
    rp = np.pad(r, ((0, 1), (0, 1)), mode="edge")
    rh = (rp[:, :-1] + rp[:, 1:]) * half
    out[:, 0, :, 0, 0], out[:, 0, :, 1, 0] = r, rh[:-1]
    out[:, 1, :, 0, 0], out[:, 1, :, 1, 0] = (rp[:-1, :-1] + rp[1:, :-1]) * half, (rh[:-1] + rh[1:]) * half
    bp = np.pad(b, ((1, 0), (1, 0)), mode="edge")
    bh = (bp[:, :-1] + bp[:, 1:]) * half
    out[:, 1, :, 1, 2], out[:, 1, :, 0, 2] = b, bh[1:]
    out[:, 0, :, 1, 2], out[:, 0, :, 0, 2] = (bp[:-1, 1:] + bp[1:, 1:]) * half, (bh[:-1] + bh[1:]) * half
    g1p, g2p = np.pad(g1, ((0, 1), (1, 0)), mode="edge"), np.pad(g2, ((1, 0), (0, 1)), mode="edge")
    quarter = np.float32(0.25)
    out[:, 0, :, 1, 1], out[:, 1, :, 0, 1] = g1, g2
    out[:, 0, :, 0, 1] = (g1p[:-1, :-1] + g1p[:-1, 1:] + g2p[:-1, :-1] + g2p[1:, :-1]) * quarter
    out[:, 1, :, 1, 1] = (g2p[1:, :-1] + g2p[1:, 1:] + g1p[:-1, 1:] + g1p[1:, 1:]) * quarter
    return out.reshape(2 * h, 2 * w, 3)


def quad_mean(mosaic: np.ndarray) -> np.ndarray:
    """Mean of each 2x2 CFA quad of a (2h, 2w) mosaic, (h, w), in the mosaic's float dtype."""
    rows = mosaic.reshape(mosaic.shape[0] // 2, 2, mosaic.shape[1])
    pair = rows[:, 0] + rows[:, 1]
    return (pair[:, 0::2] + pair[:, 1::2]) * pair.dtype.type(0.25)


def rec709_to_camera_matrix(xyz_to_camera: np.ndarray) -> np.ndarray:
    """(3, 3) float64 taking linear Rec.709 to camera RGB, the inverse of :func:`camera_to_rec709`'s
    matrix: ColorMatrix scaled so D65 white (Y = 1) gives a camera neutral with maximum 1."""
    xyz_to_camera = np.asarray(xyz_to_camera, dtype=np.float64).reshape(3, 3)
    white = xyz_to_camera @ np.linalg.solve(XYZ_TO_REC709, np.ones(3))
    return (xyz_to_camera / white.max()) @ np.linalg.inv(XYZ_TO_REC709)


def camera_to_rec709(rgb: np.ndarray, xyz_to_camera: np.ndarray) -> np.ndarray:
    """Camera RGB (..., 3) -> linear Rec.709 through XYZ, float32, negatives (out of gamut) clipped.

    ``xyz_to_camera`` (3x3) is first scaled so that D65 white (Y = 1) maps to a camera neutral with
    maximum 1, as the DNG specification normalises ColorMatrix; no white balance is applied, so the
    result stays radiometric (a blue sky stays blue).
    """
    matrix = np.linalg.inv(rec709_to_camera_matrix(xyz_to_camera)).astype(np.float32)
    out = np.asarray(rgb, dtype=np.float32).reshape(-1, 3) @ matrix.T
    return np.maximum(out, 0, out=out).reshape(np.shape(rgb))
