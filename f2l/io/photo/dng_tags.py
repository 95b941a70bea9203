"""What a DNG's first IFD states about its sensor, from its tags alone: the colour matrix and the
CFA layout with its black and white levels.

Conventions (as :mod:`f2l.io.raw_meta` uses them): ``ifd0`` maps tag id -> value (exifread's
list); ``black_levels`` are per 2x2 CFA position, row-major; CFA patterns name the colours at
those positions (``"RGGB"``); ``xyz_to_camera`` is the 3x3 matrix taking CIE XYZ to camera RGB,
row-major. Malformed values give ``None``, never an error.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

BAYER_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
"""2x2 Bayer layouts, colours of the top-left, top-right, bottom-left, bottom-right samples."""

_D65 = 21  # EXIF LightSource / DNG CalibrationIlluminant code
_SUBFILE_TYPE, _PHOTOMETRIC, _CFA_REPEAT, _CFA_PATTERN = 0xFE, 0x106, 0x828D, 0x828E
_DNG_VERSION, _CFA_PLANE_COLOR, _CFA_LAYOUT = 0xC612, 0xC616, 0xC617
_BLACK_REPEAT, _BLACK_LEVEL, _WHITE_LEVEL = 0xC619, 0xC61A, 0xC61D
_COLOR_MATRIX_1, _COLOR_MATRIX_2, _CALIBRATION_ILLUMINANT_2 = 0xC621, 0xC622, 0xC65B
DNG_UNSUPPORTED = {"LinearizationTable": 0xC618, "BlackLevelDeltaH": 0xC61B, "BlackLevelDeltaV": 0xC61C,
                   "ActiveArea": 0xC68D, "MaskedAreas": 0xC68E}
"""DNG tags whose presence LibRaw would apply beyond the basic levels."""


def _values(ifd0: Mapping, tag: int):
    values = ifd0.get(tag)
    if values is None or isinstance(values, str) or (isinstance(values, (list, tuple)) and not values):
        return values or None
    return values if isinstance(values, (list, tuple)) else [values]


def _sequence(ifd0: Mapping, tag: int):
    values = _values(ifd0, tag)
    return None if values is None or isinstance(values, str) else values


def _ints(ifd0: Mapping, tag: int) -> list[int] | None:
    values = _sequence(ifd0, tag)
    try:
        return None if values is None else [int(v) for v in values]
    except (TypeError, ValueError):
        return None


def _number(ifd0: Mapping, tag: int) -> float | None:
    values = _sequence(ifd0, tag)
    try:
        value = float(values[0]) if values is not None else None
    except (TypeError, ValueError, ZeroDivisionError, IndexError, OverflowError):
        return None
    return value if value is not None and math.isfinite(value) and value > 0 else None


def _four_blacks(blacks) -> tuple[float, ...] | None:
    """One black level or four as four floats; None otherwise."""
    if blacks is None or len(blacks) not in (1, 4):
        return None
    try:
        return tuple(float(b) for b in list(blacks) * (4 // len(blacks)))
    except (TypeError, ValueError, ZeroDivisionError, OverflowError):
        return None


def dng_xyz_to_camera(ifd0: Mapping) -> tuple[float, ...] | None:
    """The DNG ColorMatrix for the D65 calibration (ColorMatrix2 when CalibrationIlluminant2 is
    D65, else ColorMatrix1), nine floats; None when absent or malformed."""
    illum2 = _sequence(ifd0, _CALIBRATION_ILLUMINANT_2)
    tags = [_COLOR_MATRIX_1]
    try:
        if illum2 is not None and int(illum2[0]) == _D65:
            tags.insert(0, _COLOR_MATRIX_2)
    except (TypeError, ValueError, IndexError, OverflowError):
        pass
    for tag in tags:
        values = _sequence(ifd0, tag)
        if values is not None and len(values) == 9:
            try:
                return tuple(float(v) for v in values)
            except (TypeError, ValueError, ZeroDivisionError, OverflowError):
                pass
    return None


def dng_layout(ifd0: Mapping) -> tuple[str, tuple[float, ...], float] | None:
    """(CFA, black levels per 2x2 position, white level) when a DNG's first IFD is its full-size CFA
    mosaic and its tags state the layout exactly as LibRaw applies it; else ``None`` (decode).

    Required: DNGVersion, SubfileType 0, PhotometricInterpretation CFA (32803), CFARepeatPatternDim
    2x2 with an R/G/B Bayer CFAPattern (CFAPlaneColor 0, 1, 2 and CFALayout 1 if present),
    BlackLevel of 1 value or 4 with BlackLevelRepeatDim 2x2, WhiteLevel. Refused: any of
    :data:`DNG_UNSUPPORTED` (a real camera DNG keeps its mosaic in a sub-IFD: decoded as before).
    """
    if _values(ifd0, _DNG_VERSION) is None:
        return None
    if (_ints(ifd0, _SUBFILE_TYPE) or [0]) != [0] or _ints(ifd0, _PHOTOMETRIC) != [32803]:
        return None
    if any(tag in ifd0 for tag in DNG_UNSUPPORTED.values()):
        return None
    if (_ints(ifd0, _CFA_PLANE_COLOR) or [0, 1, 2]) != [0, 1, 2] or (_ints(ifd0, _CFA_LAYOUT) or [1]) != [1]:
        return None
    cfa = _ints(ifd0, _CFA_PATTERN)
    if _ints(ifd0, _CFA_REPEAT) != [2, 2] or cfa is None or len(cfa) != 4 or max(cfa) > 2:
        return None
    pattern = "".join("RGB"[c] for c in cfa)
    blacks = _sequence(ifd0, _BLACK_LEVEL)
    white = _number(ifd0, _WHITE_LEVEL)
    if pattern not in BAYER_PATTERNS or blacks is None or len(blacks) not in (1, 4):
        return None
    if len(blacks) == 4 and _ints(ifd0, _BLACK_REPEAT) != [2, 2]:
        return None
    levels = _four_blacks(blacks)
    if levels is None or white is None or not all(math.isfinite(b) and 0 <= b < white for b in levels):
        return None
    return pattern, levels, white


def tag_levels(ifd0: Mapping) -> tuple[str | None, tuple[float, ...] | None, float | None]:
    """(CFA, black levels, white level) as far as IFD0's tags state them, each ``None`` where they
    do not: a 4-entry CFAPattern, 1 or 4 BlackLevel values, a positive WhiteLevel."""
    cfa, blacks = _sequence(ifd0, _CFA_PATTERN), _sequence(ifd0, _BLACK_LEVEL)
    try:
        cfa = "".join("RGB"[int(c)] for c in cfa) if cfa and len(cfa) == 4 else None
        blacks = _four_blacks(blacks)
    except (TypeError, ValueError, IndexError):
        cfa, blacks = None, None
    return cfa, blacks, _number(ifd0, _WHITE_LEVEL)
