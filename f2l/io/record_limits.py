"""How large a face record may be, checked before anything is allocated from what it declares:
a lighting grid of at most :data:`MAX_GRID_TEXELS` texels (``$F2L_MAX_GRID_TEXELS``) and at most
:data:`MAX_RECORD_PIXELS` face pixels (``$F2L_MAX_RECORD_PIXELS``). :mod:`f2l.io.shards` applies
them to every record it reads; ``f2l estimate`` refuses an empty record with them."""

from __future__ import annotations

import os
from typing import Any

import numpy as np


MAX_GRID_TEXELS = 1 << 20
"""Most texels (grid_height * grid_width) a record's lighting grid may have: 1,048,576, e.g.
1024 x 1024. f2l writes 64 x 128 (8,192) or 32 x 128; research grids are a few hundred a side.
Raise with ``$F2L_MAX_GRID_TEXELS``."""


MAX_RECORD_PIXELS = 1 << 20
"""Most face pixels one record may have: 1,048,576. fit-faces writes about 10k (a 104-px crop),
100k at most. Raise with ``$F2L_MAX_RECORD_PIXELS``."""


def _env_limit(name: str, default: int) -> int:
    value = os.environ.get(name)
    try:
        return max(1, int(float(value))) if value else default
    except (ValueError, OverflowError):
        return default


def max_grid_texels() -> int:
    """The grid limit: ``$F2L_MAX_GRID_TEXELS`` when set, else :data:`MAX_GRID_TEXELS`."""
    return _env_limit("F2L_MAX_GRID_TEXELS", MAX_GRID_TEXELS)


def max_record_pixels() -> int:
    """The pixel limit: ``$F2L_MAX_RECORD_PIXELS`` when set, else :data:`MAX_RECORD_PIXELS`."""
    return _env_limit("F2L_MAX_RECORD_PIXELS", MAX_RECORD_PIXELS)


def declared_size_problem(num_pixels: Any, grid_height: Any, grid_width: Any, *,
                          min_pixels: int = 0) -> str | None:
    """Why a record's declared sizes are refused (None when they are accepted): fewer than
    ``min_pixels`` face pixels (a shard may store an empty record; ``f2l estimate`` asks for 1),
    more than :func:`max_record_pixels`, an empty grid or one of more than :func:`max_grid_texels`
    texels. Checked before anything is allocated from them."""
    for name, value in (("num_pixels", num_pixels), ("grid_height", grid_height),
                        ("grid_width", grid_width)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            return f"{name} is {value!r}, not an integer"
    n, h, w = int(num_pixels), int(grid_height), int(grid_width)
    if n < 0:
        return f"num_pixels is negative ({n})"
    if n < min_pixels:
        return ("the record has no face pixels (num_pixels = 0)" if n == 0 else
                f"the record has {n} face pixels, fewer than the {min_pixels} needed")
    if n > max_record_pixels():
        return (f"the record declares {n} face pixels, more than the {max_record_pixels()} "
                f"accepted (F2L_MAX_RECORD_PIXELS)")
    if h < 1 or w < 1:
        return f"the lighting grid {h}x{w} is empty"
    if h * w > max_grid_texels():
        return (f"the record declares a {h}x{w} lighting grid = {h * w} texels, more than the "
                f"{max_grid_texels()} accepted (F2L_MAX_GRID_TEXELS)")
    return None


def _declared_bytes(num_pixels: int, grid_height: int, grid_width: int) -> int:
    """Bytes the bulk columns of a record of these (accepted) sizes hold, uncompressed."""
    n = int(num_pixels)
    return n * (2 * 4 + 3 * 3 * 4 + 1) + n * (-(-int(grid_height) * int(grid_width) // 8))
