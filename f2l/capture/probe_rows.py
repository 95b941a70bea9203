"""The rows of ``probes.parquet`` and what every probe stage shares: a view's camera from its
view spec, mask PNGs, and rows checked (finite numbers, the ``probes`` schema) before the table
is built. See :mod:`f2l.capture.probes` for the table."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from f2l.capture.view_spec import ViewSpec


COLOUR_SPACES = ("rec709", "camera")


def camera_for(spec: ViewSpec, width: int, height: int, *, frame: tuple | None = None,
               exif_focal_mm: float | None = None):
    """The :class:`~f2l.capture.cameras.ViewCamera` a row's view spec (its lens and orientation)
    describes for a view of ``width`` x ``height`` px (:func:`f2l.capture.lens.lens_of`;
    ValueError naming what is missing).

    ``frame``: (full-frame width, height, k, crop_x, crop_y) when the view was box-averaged by k
    after a centred crop (:func:`downsample_view`); None: the view is the full frame."""
    from f2l.capture.lens import lens_of

    fw, fh, k, cx, cy = frame if frame is not None else (width, height, 1, 0, 0)
    return lens_of(spec.lens, int(fw), int(fh), exif_focal_mm).view_camera(width, height, int(k), int(cx), int(cy),
                                                                          **spec.pose_deg())


def _write_mask_png(path: Path, mask: np.ndarray) -> None:
    from PIL import Image

    from f2l.io.atomic import atomic_path

    with atomic_path(path) as tmp:
        Image.fromarray(np.where(mask, 255, 0).astype(np.uint8)).save(tmp, format="PNG")


def _read_mask_png(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        return np.asarray(im) > 127


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "._-" else "_" for c in name)


def _row(kind: str, name: str, session: str, status: str, message: str, **kw) -> dict:
    row = {"kind": kind, "name": name, "session": session, "status": status, "message": message,
           "path": None, "frames": 0, "saturated_fraction": None, "coverage_fraction": None,
           "sun_elevation_deg": None, "sun_azimuth_deg": None, "colour_space": None, "sun_restored": None,
           "full_path": None, "seconds": 0.0}
    row.update(kw)
    return row


FLOAT_COLUMNS = ("saturated_fraction", "coverage_fraction", "sun_elevation_deg", "sun_azimuth_deg")


def finite_row(row: dict) -> dict:
    """``row`` (changed in place) with status ``error`` and the columns named in its message
    (then null) where a number of :data:`FLOAT_COLUMNS` is NaN or infinite: no such number
    reaches probes.parquet or a cache entry's JSON."""
    bad = [key for key in FLOAT_COLUMNS if row.get(key) is not None
           and not (isinstance(row[key], (int, float)) and math.isfinite(float(row[key])))]
    if bad:
        what = ", ".join(f"{key} = {row[key]!r}" for key in bad)
        reason = (f"session {row['session']}: {row['kind']} {row['name']}: {what} "
                  f"{'is' if len(bad) == 1 else 'are'} not finite (its view or probe cannot be computed)")
        row.update({key: None for key in bad})
        row.update(status="error", message="; ".join(m for m in (reason, row.get("message") or "") if m))
    if not (isinstance(row.get("seconds"), (int, float)) and math.isfinite(float(row["seconds"]))):
        row["seconds"] = 0.0
    return row


def checked_rows(rows: list[dict], source: str) -> list[dict]:
    """``rows`` with every row that would not pass the ``probes`` schema on its own (a NaN, a
    value out of range, a wrong type) turned into an ``error`` row naming what: one bad row never
    stops the table from being written."""
    from f2l.io.schema import table_errors
    from f2l.io.tables import rows_to_table

    out = []
    for row in rows:
        row = finite_row(dict(row))
        try:
            errors = table_errors(rows_to_table([row], "probes"), "probes", source)
        except Exception as exc:  # noqa: BLE001 - a value arrow cannot convert: the row's error
            errors = [f"{type(exc).__name__}: {exc}"]
        if errors:
            keep = {k: row.get(k) if isinstance(row.get(k), str) else str(row.get(k))
                    for k in ("kind", "name", "session")}
            kind = keep["kind"] if keep["kind"] in ("view", "probe", "given") else "probe"
            row = _row(kind, keep["name"], keep["session"], "error",
                       f"session {keep['session']}: {kind} {keep['name']}: row not valid: " + "; ".join(errors))
        out.append(row)
    return out
