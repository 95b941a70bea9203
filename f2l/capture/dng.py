"""Synthetic RAW brackets written as real DNG files (pidng), deterministic from a seed.

Sensor model of :func:`write_bracket`, per frame with exposure factor ``e = t * (ISO / 100) / N**2``
(t, N and ISO exactly as stored in the file's rationals):

- ``signal_dn = (white - black_p) * (radiance / full_scale_radiance) * e`` for the CFA colour of
  each sample, black_p the black level of its 2x2 CFA position. So ``full_scale_radiance`` is the
  calibration constant: the radiance that just reaches the white level at EV100 = 0 (1 s, f/1,
  ISO 100), and :func:`f2l.capture.merge.merge_bracket` returns ``radiance / full_scale_radiance``.
- Shot noise: ``Poisson(signal_dn / gain) * gain`` with ``gain = (white - mean black) * ISO /
  (100 * full_well_e)`` DN per electron (``full_well_e`` electrons reach white at ISO 100).
- Read noise: Gaussian, ``read_noise_dn`` standard deviation. Then ``+ black``, rounding, clipping to
  [0, white] and uint16: a pixel brighter than white reads exactly ``white_level``.

Files are 16-bit DNG 1.4, uncompressed or (``compression="ljpeg"``) lossless-JPEG (ITU T.81 process
14, "LJ92", as camera RAWs and Adobe's DNG Converter store them; encoded by ``imagecodecs``), CFA in IFD0, exposure/ISO/time/lens in an EXIF sub-IFD,
optional GPS sub-IFD. Nothing depends on the clock: the same arguments give the same bytes.
``camera_matrix`` is ColorMatrix1 (CIE XYZ -> camera RGB, D65); the default makes camera RGB equal
linear Rec.709, so scenes can be given directly in Rec.709.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from datetime import datetime, timedelta
from fractions import Fraction
from pathlib import Path

import sys
import types
from unittest import mock

import numpy as np
from pidng.core import RAW2DNG, DNGTags, Tag
from pidng.defs import CalibrationIlluminant, PhotometricInterpretation
from pidng.dng import Type, dngIFD, dngTag

from f2l.io.raw_meta import BAYER_PATTERNS, XYZ_TO_REC709, bayer_mosaic
from f2l.io.atomic import atomic_path

__all__ = ["write_dng", "write_bracket", "synthetic_sky_scene"]

COMPRESSIONS = ("none", "ljpeg")

_COLOUR_INDEX = {"R": 0, "G": 1, "B": 2}
_GPS_IFD = (34853, Type.IFD)
_OFFSET_TIME_ORIGINAL = (36881, Type.Ascii)


class _IfdTag(dngTag):
    """pidng's IFD-pointer tag (its own concatenates str and bytes and fails)."""

    def setValue(self, value):  # noqa: N802 (pidng's name)
        if self.DataType == Type.IFD:
            self.Value, self.subIFD = b"\x00\x00\x00\x00", value[0]
        else:
            super().setValue(value)


def _lj92_tile(raw: np.ndarray, width: int, height: int, bits: int, *_unused) -> bytes:
    """pidng's lossless-JPEG hook (its own C extension fails to import on Python >= 3.10): the
    mosaic re-read as ``height`` rows of ``width`` samples (pidng passes two CFA rows per JPEG row),
    one component, predictor 1."""
    import imagecodecs

    return imagecodecs.ljpeg_encode(np.ascontiguousarray(raw).reshape(height, width), bitspersample=bits)


_LJ92 = types.ModuleType("ljpegCompress")  # the module pidng imports when compress=True
_LJ92.pack16tolj = _lj92_tile


def _rational(value: float, max_denominator: int = 1_000_000) -> list[int]:
    frac = Fraction(float(value)).limit_denominator(max_denominator)
    if frac <= 0 or frac.numerator >= 2**32:
        raise ValueError(f"cannot store {value!r} as a positive TIFF rational")
    return [frac.numerator, frac.denominator]


def _per_frame(value, n: int, name: str) -> list[float]:
    values = [float(v) for v in value] if isinstance(value, Sequence) else [float(value)] * n
    if len(values) != n or not all(math.isfinite(v) and v > 0 for v in values):
        raise ValueError(f"{name} must be positive, one value or one per frame ({n}), got {value!r}")
    return values


def _frame_dn(mosaic, e, iso, blacks, white, full_well_e, read_noise_dn, rng) -> np.ndarray:
    """Noisy uint16 DN of one frame (sensor model in the module docstring)."""
    black = np.asarray(blacks, dtype=np.float64).reshape(2, 2)
    h, w = mosaic.shape
    black_map = np.tile(black, (h // 2 + 1, w // 2 + 1))[:h, :w]
    signal_dn = (white - black_map) * mosaic * e
    gain = (white - black.mean()) * iso / (100.0 * full_well_e)
    electrons = np.minimum(signal_dn / gain, 4.0 * white / gain)  # beyond white it saturates anyway
    dn = rng.poisson(electrons) * gain + rng.normal(0.0, read_noise_dn, mosaic.shape) + black_map
    return np.clip(np.rint(dn), 0, white).astype(np.uint16)


def _gps_ifd(gps: tuple[float, float, float | None]) -> dngIFD:
    ifd = dngIFD()

    def dms(deg: float) -> list[list[int]]:
        deg = abs(deg)
        d, m = int(deg), int((deg - int(deg)) * 60)
        return [[d, 1], [m, 1], [round((deg - d - m / 60) * 3600 * 1000), 1000]]

    lat, lon, alt = gps
    ifd.tags += [dngTag((0, Type.Byte), [2, 3, 0, 0]), dngTag((1, Type.Ascii), "N" if lat >= 0 else "S"),
                 dngTag((2, Type.Rational), dms(lat)), dngTag((3, Type.Ascii), "E" if lon >= 0 else "W"),
                 dngTag((4, Type.Rational), dms(lon))]  # fmt: skip
    if alt is not None:
        ifd.tags += [dngTag((5, Type.Byte), [0 if alt >= 0 else 1]),
                     dngTag((6, Type.Rational), [_rational(abs(alt), 1000)])]  # fmt: skip
    return ifd


def write_dng(
    path: str | os.PathLike,
    raw: np.ndarray,
    *,
    exposure_s: float,
    f_number: float,
    iso: float,
    black_level: int | Sequence[int] = 256,
    white_level: int = 4095,
    cfa: str = "RGGB",
    camera_matrix: np.ndarray | None = None,
    make: str = "f2l",
    model: str = "Synthetic Bayer",
    lens: str | None = None,
    focal_length_mm: float | None = None,
    timestamp: datetime = datetime(2024, 6, 21, 12, 0, 0),
    gps: tuple[float, float, float | None] | None = None,
    compression: str = "none",
) -> Path:
    """Write a (H, W) uint16 CFA mosaic as a DNG, atomically; returns the path.

    Exposure values are stored as TIFF rationals (denominators up to 1e6 for seconds, 1e3 for the
    f-number); ``black_level`` is one value or four (per 2x2 CFA position, row-major); an aware
    ``timestamp`` also records OffsetTimeOriginal; ``gps`` is (latitude_deg, longitude_deg,
    altitude_m or None). ``compression``: "none" or "ljpeg" (lossless; LibRaw decodes it bit-exactly).
    """
    if compression not in COMPRESSIONS:
        raise ValueError(f"compression must be one of {COMPRESSIONS}, got {compression!r}")
    raw = np.asarray(raw)
    blacks = [int(black_level)] * 4 if np.ndim(black_level) == 0 else [int(b) for b in black_level]
    if raw.dtype != np.uint16 or raw.ndim != 2 or min(raw.shape) < 2:
        raise ValueError(f"raw must be a 2-D uint16 mosaic, got {raw.dtype} {raw.shape}")
    if len(blacks) != 4 or not 0 <= min(blacks) <= max(blacks) < white_level <= 65535:
        raise ValueError(f"need 0 <= black_level < white_level <= 65535, got {black_level!r}, {white_level!r}")
    if cfa not in BAYER_PATTERNS:
        raise ValueError(f"cfa must be one of {BAYER_PATTERNS}, got {cfa!r}")
    matrix = XYZ_TO_REC709 if camera_matrix is None else np.asarray(camera_matrix, dtype=np.float64).reshape(3, 3)
    tags = DNGTags()
    stamp = timestamp.strftime("%Y:%m:%d %H:%M:%S")
    for tag, value in [
        (Tag.ImageWidth, raw.shape[1]), (Tag.ImageLength, raw.shape[0]), (Tag.TileWidth, raw.shape[1]),
        (Tag.TileLength, raw.shape[0]), (Tag.Orientation, 1), (Tag.SamplesPerPixel, 1), (Tag.BitsPerSample, 16),
        (Tag.PhotometricInterpretation, PhotometricInterpretation.Color_Filter_Array),
        (Tag.CFARepeatPatternDim, [2, 2]), (Tag.CFAPattern, [_COLOUR_INDEX[c] for c in cfa]),
        (Tag.BlackLevelRepeatDim, [2, 2]), (Tag.BlackLevel, blacks), (Tag.WhiteLevel, int(white_level)),
        (Tag.ColorMatrix1, [[round(v * 10000), 10000] for v in matrix.ravel()]),
        (Tag.CalibrationIlluminant1, CalibrationIlluminant.D65), (Tag.Make, make), (Tag.Model, model),
        (Tag.UniqueCameraModel, f"{make} {model}"), (Tag.DateTime, stamp),
    ]:  # fmt: skip
        tags.set(tag, value)
    neutral = matrix @ np.linalg.solve(XYZ_TO_REC709, np.ones(3))  # camera response to D65 white
    tags.set(Tag.AsShotNeutral, [_rational(v / neutral.max(), 10000) for v in neutral])
    exif = dngIFD()
    exif.tags += [dngTag(Tag.ExposureTime, [_rational(exposure_s)]), dngTag(Tag.FNumber, [_rational(f_number, 1000)]),
                  dngTag(Tag.ExposureProgram, [1]), dngTag(Tag.PhotographicSensitivity, [int(round(iso))]),
                  dngTag(Tag.ExifVersion, [48, 50, 51, 48]), dngTag(Tag.DateTimeOriginal, stamp)]  # fmt: skip
    if timestamp.utcoffset() is not None:
        minutes = int(timestamp.utcoffset().total_seconds() // 60)
        offset = f"{'+' if minutes >= 0 else '-'}{abs(minutes) // 60:02d}:{abs(minutes) % 60:02d}"
        exif.tags.append(dngTag(_OFFSET_TIME_ORIGINAL, offset))
    if focal_length_mm:
        exif.tags.append(dngTag(Tag.FocalLength, [_rational(focal_length_mm, 1000)]))
    if lens:
        exif.tags.append(dngTag(Tag.EXIFPhotoLensModel, lens))
    tags.__tags__[Tag.EXIF_IFD] = _IfdTag(Tag.EXIF_IFD, [exif])  # pidng's DNGTags has no public hook
    if gps is not None:
        tags.__tags__[_GPS_IFD] = _IfdTag(_GPS_IFD, [_gps_ifd(gps)])
    writer = RAW2DNG()
    writer.options(tags, path="", compress=compression == "ljpeg")
    path = Path(path)
    with mock.patch.dict(sys.modules, {"ljpegCompress": _LJ92}), atomic_path(path) as tmp:
        Path(tmp).write_bytes(bytes(writer.convert(raw)))
    return path


def write_bracket(
    out_dir: str | os.PathLike,
    scene_rgb: np.ndarray | Sequence[np.ndarray],
    exposures_s: Sequence[float],
    *,
    f_number: float | Sequence[float] = 8.0,
    iso: float | Sequence[float] = 100,
    black_level: int | Sequence[int] = 256,
    white_level: int = 4095,
    cfa: str = "RGGB",
    read_noise_dn: float = 2.0,
    full_well_e: float = 20000.0,
    full_scale_radiance: float = 1.0,
    seed: int = 0,
    timestamp: datetime = datetime(2024, 6, 21, 12, 0, 0),
    interval_s: float = 1.0,
    prefix: str = "frame",
    **dng_kwargs,
) -> list[Path]:
    """Write one DNG per exposure of a linear camera-RGB HDR scene; returns the paths in order.

    ``scene_rgb`` is (H, W, 3) radiance (>= 0, any absolute scale, see ``full_scale_radiance``) or
    one such image per frame (to simulate motion). ``f_number`` and ``iso`` are one value or one per
    frame. Frame ``i`` is ``f"{prefix}_{i:02d}.dng"`` taken at ``timestamp + i * interval_s``.
    ``dng_kwargs`` (camera_matrix, make, model, lens, focal_length_mm, gps, compression) go to
    :func:`write_dng`.
    """
    n = len(exposures_s)
    scenes = [np.asarray(s, dtype=np.float64) for s in scene_rgb] if not isinstance(scene_rgb, np.ndarray) or (
        scene_rgb.ndim == 4) else [np.asarray(scene_rgb, dtype=np.float64)] * n  # fmt: skip
    if n < 1 or len(scenes) != n:
        raise ValueError(f"need one scene or one per exposure; got {len(scenes)} scenes for {n} exposures")
    shape = scenes[0].shape
    for scene in scenes:
        if scene.ndim != 3 or scene.shape != shape or shape[2] != 3 or min(shape[:2]) < 2:
            raise ValueError(f"scene_rgb must be (H, W, 3) with H, W >= 2, all frames alike; got {scene.shape}")
        if not np.all(np.isfinite(scene)) or scene.min() < 0:
            raise ValueError("scene_rgb must be finite and non-negative")
    times = [float(Fraction(*_rational(t))) for t in _per_frame(exposures_s, n, "exposures_s")]
    stops = [float(Fraction(*_rational(v, 1000))) for v in _per_frame(f_number, n, "f_number")]
    isos = [int(round(v)) for v in _per_frame(iso, n, "iso")]
    blacks = [int(black_level)] * 4 if np.ndim(black_level) == 0 else [int(b) for b in black_level]
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(n)]
    paths = []
    for i in range(n):
        mosaic = bayer_mosaic(scenes[i], cfa) / float(full_scale_radiance)
        e = times[i] * isos[i] / 100.0 / stops[i] ** 2
        dn = _frame_dn(mosaic, e, isos[i], blacks, white_level, full_well_e, read_noise_dn, rngs[i])
        paths.append(write_dng(Path(out_dir) / f"{prefix}_{i:02d}.dng", dn, exposure_s=times[i], f_number=stops[i],
                               iso=isos[i], black_level=blacks, white_level=white_level, cfa=cfa,
                               timestamp=timestamp + timedelta(seconds=i * interval_s), **dng_kwargs))  # fmt: skip
    return paths


def synthetic_sky_scene(height: int = 96, width: int = 128, *, seed: int = 0) -> np.ndarray:
    """An outdoor HDR test scene in camera RGB, (height, width, 3) float64, radiance >= 1.

    Rows above 60% are sky (blue-ish, 2e3 at the horizon to 8e3 at the top, with smooth cloud
    texture) holding a sun disk of radiance 1e9 (radius 4% of the smaller side, at 25% height and
    70% width) inside an aureole peaking at 2e5; the rest is textured ground (about 300-800) with a dark
    shadow box (0.5-3). Unclipped dynamic range (aureole peak / shadow floor) is about 4e5.
    """
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    texture = gaussian_filter(rng.standard_normal((height, width)), 2.5)
    texture = 1.0 + 0.3 * texture / (np.abs(texture).max() + 1e-12)
    horizon = int(0.6 * height)
    sky = (8e3 - 6e3 * yy / horizon) * texture
    radius = 0.04 * min(height, width)
    r = np.hypot(yy - 0.25 * height, xx - 0.7 * width)
    sky = sky + 2e5 * np.exp(-np.maximum(r - radius, 0.0) / (0.05 * width))
    ground = 600.0 * texture
    lum = np.where(yy < horizon, sky, ground)
    shadow = (yy >= horizon + 0.1 * height) & (yy < 0.95 * height) & (xx >= 0.1 * width) & (xx < 0.4 * width)
    lum = np.where(shadow, 0.7 + 2.3 * (texture - 0.7) / 0.6, lum)
    colour = np.where((yy < horizon)[..., None], [0.6, 0.8, 1.0], [1.0, 0.85, 0.7])
    scene = lum[..., None] * colour
    scene[r <= radius] = 1e9 * np.array([1.0, 0.97, 0.93])
    return np.maximum(scene, 0.5)
