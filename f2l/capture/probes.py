"""Merge and sphere stages over an ingested capture tree: brackets → HDR views → one lat-long
probe per session (``f2l make-probes``).

For each ``bracket_id`` of ``WORK/captures.parquet`` (frames with status ok), in path order:

1. :func:`f2l.capture.merge.merge_bracket` in the RAW domain (one bracket in memory at a time),
   box-averaged by an integer factor to at most ``view_max_side`` px (radiance-preserving; a block
   is saturated if any of its pixels is; 1024 px keeps ~0.2° per pixel on a 180° fisheye),
   converted to linear Rec.709 with the camera's colour matrix (:class:`ViewOptions`), its
   fall-off divided out, written to ``WORK/views/<bracket>.exr`` (float32; 1.0 = full scale at
   EV100 0; ``chromaticities`` and ``f2l_view_from_frame`` = "W H k crop_x crop_y" in the header)
   with its saturated mask ``WORK/views/<bracket>.saturated.png``. Only these small views stay in
   memory until their session is assembled;
2. the view's lens, fall-off and orientation from the row's ``view_json`` (the session TOML,
   :mod:`f2l.capture.lens`), mapped from the full frame to the box-averaged view. A bracket
   without a lens cannot be placed on the sphere and is reported (``unplaced``), not guessed.

Then per session, :func:`f2l.capture.sphere.assemble` blends the session's placed views into
``WORK/probes/<session>.exr`` (DESIGN lat-long convention, float32, default 128 x 256) with the
coverage mask ``WORK/probes/<session>.coverage.png`` (white = seen; the rest, e.g. the ground under
an up-looking fisheye, is 0 in the probe and never invented). The sun's direction comes from the
views (:func:`view_sun`), sub-texel. ``WORK/probes.parquet`` (schema ``probes``) has one row per
bracket and per session probe, a ``skipped`` row saying what a session without a probe lacks, and
the already-merged probes (role ``probe``) with their path.

Hostile input never gives an "ok" probe and never loses the batch. A probe that is black, sees
less than a quarter of the sky or is not finite (:func:`f2l.lighting.plausibility.probe_problem`
on the radiance and the coverage mask), or a given probe that is unreadable, no lat-long or fails
the same check, is an ``error`` row naming its session and file (no probe file is written for
it). A view whose lens or orientation is described but unusable (a NaN angle, an implausible
focal length) is an ``error`` row; one with no lens description stays ``unplaced``. A NaN or an
infinity in a row's numbers makes that row an ``error`` naming the column, every row is checked
against the schema before the table is built (:func:`checked_rows`), and an exception in one
bracket or session becomes that row's ``error``: the other rows and probes.parquet are written.
"""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

COLOUR_SPACES = ("rec709", "camera")


@dataclass
class ProbesSummary:
    work: str
    brackets: int = 0
    views: int = 0
    probes: int = 0
    errors: int = 0
    seconds: float = 0.0
    rows: list = field(default_factory=list)

    def to_json(self) -> dict:
        out = {k: v for k, v in self.__dict__.items() if k != "rows"}
        out["by_status"] = {}
        for r in self.rows:
            out["by_status"][r["status"]] = out["by_status"].get(r["status"], 0) + 1
        return out


POSE_KEYS = ("yaw_deg", "pitch_deg", "roll_deg")
LENS_KEYS = ("projection", "colmap_model")


def pose_problem(view: dict) -> str | None:
    """Why a row's ``view_json`` orientation cannot place a view (an angle that is not a finite
    number), or None."""
    for key in POSE_KEYS:
        value = view.get(key, 0.0)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"{key} = {value!r} is not a number"
        if not math.isfinite(float(value)):
            return f"{key} = {value} is not a finite angle"
    return None


def camera_for(view: dict, width: int, height: int, *, frame: tuple | None = None,
               exif_focal_mm: float | None = None):
    """The :class:`~f2l.capture.cameras.ViewCamera` a row's ``view_json`` describes for a view of
    ``width`` x ``height`` px (:mod:`f2l.capture.lens`; ValueError naming what is missing).

    ``frame``: (full-frame width, height, k, crop_x, crop_y) when the view was box-averaged by k
    after a centred crop (:func:`downsample_view`); None: the view is the full frame."""
    from f2l.capture.lens import lens_from_view

    fw, fh, k, cx, cy = frame if frame is not None else (width, height, 1, 0, 0)
    problem = pose_problem(view)
    if problem:
        raise ValueError(problem)
    pose = {key: float(view.get(key, 0.0)) for key in POSE_KEYS}
    return lens_from_view(view, int(fw), int(fh), exif_focal_mm).view_camera(width, height, int(k), int(cx), int(cy),
                                                                             **pose)


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


def downsample_plan(height: int, width: int, max_side: int) -> tuple[int, int, int]:
    """(k, crop_y, crop_x) of :func:`downsample_view` for a frame of ``height`` x ``width``."""
    k = max(1, -(-max(height, width) // int(max_side)))
    return k, (height - height // k * k) // 2, (width - width // k * k) // 2


def downsample_view(rgb: np.ndarray, saturated: np.ndarray, max_side: int):
    """Box-average (h, w, 3) by the smallest integer factor k with max(h, w) / k <= max_side
    (a centred crop drops the h % k, w % k remainder); saturated if any pixel of the block is.

    The k * k strided sub-images are summed in float32 (k * k terms of one sign: relative error
    below k * k * 6e-8), 25x faster than a float64 ``mean`` over a reshaped view."""
    h, w = rgb.shape[:2]
    k, r0, c0 = downsample_plan(h, w, max_side)
    if k == 1:
        return rgb, saturated
    hh, ww = h // k * k, w // k * k
    crop, sat = rgb[r0:r0 + hh, c0:c0 + ww], saturated[r0:r0 + hh, c0:c0 + ww]
    total, flag = np.zeros((hh // k, ww // k, 3), np.float32), np.zeros((hh // k, ww // k), bool)
    for a in range(k):
        for b in range(k):
            total += crop[a::k, b::k]
            flag |= sat[a::k, b::k]
    total *= np.float32(1.0 / (k * k))
    return total, flag


@dataclass(frozen=True)
class ViewOptions:
    """How a merged bracket becomes a view: box-averaged to at most ``view_max_side`` px;
    ``colour_space`` "rec709" (the camera's colour matrix, DNG ColorMatrix or LibRaw's table) or
    "camera" (camera RGB kept); ``root``: the capture root (flat-field files are relative to it)."""

    view_max_side: int = 1024
    colour_space: str = "rec709"
    root: Path | None = None

    def __post_init__(self) -> None:
        if self.colour_space not in COLOUR_SPACES:
            raise ValueError(f"colour space must be one of {', '.join(COLOUR_SPACES)}, got {self.colour_space!r}")


def _merge_one(root: Path, work: Path, bid: str, frames: list[dict], opts: ViewOptions) -> tuple[dict, object | None]:
    """Merge one bracket → (row, placed view or None)."""
    return _finish_one(work, bid, frames, opts, *_merge_frames(root, bid, frames))


def _merge_frames(root: Path, bid: str, frames: list[dict], started=None):
    """The bracket merge itself: (merged or None, error row or None, start time). ``started``: the
    bracket's :class:`~f2l.capture.merge.BracketStart` when its decoding has already begun."""
    from f2l.capture.merge import merge_bracket

    t0 = time.perf_counter()
    try:
        return merge_bracket(started if started is not None else [root / f["path"] for f in frames]), None, t0
    except Exception as exc:  # BracketError / RawError name the files
        return None, _row("view", bid, frames[0]["session"], "error", str(exc), frames=len(frames)), t0


def _to_colour_space(rgb: np.ndarray, merged, opts: ViewOptions, warnings: list[str]) -> tuple[np.ndarray, str]:
    from f2l.io.raw_meta import camera_to_rec709

    if opts.colour_space == "camera":
        return rgb, "camera"
    if merged.xyz_to_camera is None:
        warnings.append(f"{merged.reference}: no colour matrix (neither DNG ColorMatrix nor LibRaw's table): "
                        "left in camera RGB")
        return rgb, "camera"
    return camera_to_rec709(rgb, merged.xyz_to_camera), "rec709"


def _finish_one(work: Path, bid: str, frames: list[dict], opts: ViewOptions, merged, error_row,
                t0: float) -> tuple[dict, object | None]:
    """Downsampling, colour, fall-off and the view's files for a merged bracket → (row, placed
    view or None). The lens is read first: a view without one is written as merged (unplaced)."""
    from f2l.capture.sphere import View
    from f2l.io.exr import REC709_CHROMATICITIES, write_exr

    if merged is None:
        return error_row, None
    session, first = frames[0]["session"], frames[0]
    info = json.loads(first["view_json"] or "{}")
    full_h, full_w = merged.mosaic.shape
    k, crop_y, crop_x = downsample_plan(full_h, full_w, opts.view_max_side)
    rgb, saturated = downsample_view(merged.rgb, merged.saturated, opts.view_max_side)
    warnings = list(merged.warnings)
    rgb, space = _to_colour_space(rgb, merged, opts, warnings)
    frame = (full_w, full_h, k, crop_x, crop_y)
    camera, problem, failed = None, "", ""
    try:
        camera = camera_for(info, rgb.shape[1], rgb.shape[0], frame=frame, exif_focal_mm=first.get("focal_length_mm"))
        from f2l.capture.lens import lens_from_view

        gain = lens_from_view(info, full_w, full_h, first.get("focal_length_mm")).gain(camera, k, crop_x, crop_y,
                                                                                      opts.root)
        if gain is not None:
            rgb = rgb / gain[..., None]
    except (ValueError, ArithmeticError) as exc:
        camera, problem = None, f"{first['path']}: {exc}"
        if first.get("session_problem"):
            problem += f" (session.toml was not used: {first['session_problem']})"
        if pose_problem(info) or any(key in info for key in LENS_KEYS):  # described, but unusable
            failed = f"session {session}: bracket {bid}: the view cannot be placed: {problem}"
    rel = f"views/{_safe(bid)}.exr"
    units = "linear Rec.709" if space == "rec709" else "camera RGB"
    write_exr(work / rel, rgb, metadata={"f2l_bracket": bid, "f2l_units": f"{units}, 1.0 = full scale at EV100 0",
                                         "f2l_colour_space": space, "f2l_view_from_frame": " ".join(map(str, frame))},
              compression="none", chromaticities=REC709_CHROMATICITIES if space == "rec709" else None)
    _write_mask_png(work / rel.replace(".exr", ".saturated.png"), saturated)
    row = _row("view", bid, session, "ok", "; ".join(warnings), path=rel, frames=len(frames),
               saturated_fraction=float(merged.saturated_fraction), colour_space=space,
               seconds=round(time.perf_counter() - t0, 3))
    if camera is None:
        row.update(status="error" if failed else "unplaced", message=failed or problem)
        return row, None
    view = View(image=rgb, camera=camera, saturated=saturated, name=bid)
    _set_sun(row, [view])
    finite_row(row)
    return row, (view if row["status"] == "ok" else None)


def merge_bracket_view(root: str | os.PathLike, out_dir: str | os.PathLike, bracket_id: str,
                       frames: list[dict], view_max_side: int = 1024,
                       colour_space: str = "rec709") -> tuple[dict, object | None]:
    """Merge one bracket (its ``captures`` rows, any order) into ``out_dir/views/<bracket>.exr``
    and ``.saturated.png``; returns (the ``probes`` row, the placed
    :class:`~f2l.capture.sphere.View` or None when it failed or has no lens model)."""
    (Path(out_dir) / "views").mkdir(parents=True, exist_ok=True)
    frames = sorted(frames, key=lambda f: f["path"])
    return _merge_one(Path(root), Path(out_dir), bracket_id, frames,
                      ViewOptions(view_max_side, colour_space, Path(root)))


def load_view(out_dir: str | os.PathLike, row: dict, view_json: str, exif_focal_mm: float | None = None):
    """The placed :class:`~f2l.capture.sphere.View` of a merged bracket from its files under
    ``out_dir`` (``row`` from :func:`merge_bracket_view`, status ``ok``) and the ``view_json`` of
    its frames; ValueError when the row has no lens model."""
    from f2l.capture.sphere import View
    from f2l.io.exr import read_exr_with_metadata

    out_dir = Path(out_dir)
    rgb, meta = read_exr_with_metadata(out_dir / row["path"])
    saturated = _read_mask_png(out_dir / row["path"].replace(".exr", ".saturated.png"))
    frame = tuple(int(v) for v in meta["f2l_view_from_frame"].split()) if "f2l_view_from_frame" in meta else None
    camera = camera_for(json.loads(view_json or "{}"), rgb.shape[1], rgb.shape[0], frame=frame,
                        exif_focal_mm=exif_focal_mm)
    return View(image=rgb, camera=camera, saturated=saturated, name=row["name"])


def view_sun(view) -> tuple[np.ndarray, float] | None:
    """(world direction, blend weight there) of the sun in one view, or None: the centroid of the
    largest blob saturated in every frame, else of the pixels above half the brightest pixel's
    luminance around it (only if that peak is 100x the view's median). Sub-pixel: a few pixels'
    error is a fraction of a probe texel."""
    from scipy import ndimage

    lum = view.image @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
    valid = view.camera.valid_pixel_mask()
    sat = np.zeros(lum.shape, bool) if view.saturated is None else view.saturated & valid
    if sat.any():
        labels, n = ndimage.label(sat)
        sizes = ndimage.sum_labels(np.ones_like(lum), labels, index=np.arange(1, n + 1))
        blob = labels == 1 + int(np.argmax(sizes))
        weights = blob.astype(np.float64)
    else:
        masked = np.where(valid, lum, 0.0)
        peak = float(masked.max())
        median = float(np.median(lum[valid])) if valid.any() else 0.0
        if not (peak > 0 and peak > 100.0 * median):
            return None
        labels, _ = ndimage.label(masked >= 0.5 * peak)
        i, j = np.unravel_index(int(np.argmax(masked)), masked.shape)
        blob = labels == labels[i, j]
        weights = np.where(blob, masked, 0.0)
    yy, xx = np.nonzero(blob)
    w = weights[yy, xx]
    px = np.array([[float((xx + 0.5) @ w / w.sum()), float((yy + 0.5) @ w / w.sum())]])
    d, ok = view.camera.pixel_to_direction(px)
    if not ok[0]:
        return None
    d_cam = d @ view.camera.rotation
    return d[0], float(view.camera.blend_weight(d_cam, px)[0])


def _set_sun(row: dict, views: list) -> None:
    """Sun elevation/azimuth (grid convention) from the view that sees it most centrally."""
    found = [s for s in (view_sun(v) for v in views) if s is not None]
    if not found:
        return
    d = max(found, key=lambda s: s[1])[0]
    row["sun_elevation_deg"] = math.degrees(math.asin(float(np.clip(d[1], -1, 1))))
    row["sun_azimuth_deg"] = math.degrees(math.atan2(float(d[0]), float(-d[2])))


FULL_PROBE_MAX_HEIGHT = 512  # 0.35° texels; assembly time grows with the texels (~13 s per 0.4-MP view)


def full_probe_height(views: list) -> int:
    """Probe rows matching the finest view's pixel angle at its principal point (even, at most
    :data:`FULL_PROBE_MAX_HEIGHT`): the probe that keeps what the views resolve."""
    finest = 180.0
    for v in views:
        cam = v.camera
        cx, cy = float(cam.colmap.principal_point_x), float(cam.colmap.principal_point_y)
        d, ok = cam.pixel_to_cam_direction(np.array([[cx, cy], [cx + 1.0, cy]]))
        if ok.all():
            finest = min(finest, math.degrees(math.acos(float(np.clip(d[0] @ d[1], -1, 1)))))
    return int(min(FULL_PROBE_MAX_HEIGHT, 2 * math.ceil(90.0 / finest)))


def write_full_probe(session: str, views: list, out_dir: str | os.PathLike, colour_space: str) -> tuple[str, int]:
    """``out_dir/probes/<session>.full.exr`` at :func:`full_probe_height` (+ its coverage PNG);
    returns (its path relative to ``out_dir``, its height)."""
    from f2l.capture.sphere import assemble
    from f2l.io.exr import REC709_CHROMATICITIES, write_exr

    height = full_probe_height(views)
    probe = assemble(views, height, 2 * height)
    rel = f"probes/{_safe(session)}.full.exr"
    write_exr(Path(out_dir) / rel, probe.radiance, metadata={"f2l_session": session, "f2l_colour_space": colour_space},
              chromaticities=REC709_CHROMATICITIES if colour_space == "rec709" else None)
    _write_mask_png(Path(out_dir) / rel.replace(".exr", ".coverage.png"), probe.coverage)
    return rel, height


def assemble_session(session: str, views: list, out_dir: str | os.PathLike, grid_height: int = 128,
                     grid_width: int = 256, colour_spaces: list[str] | None = None,
                     restore_sun: bool = False, full_probe: bool = False) -> dict:
    """Blend one session's placed views into ``out_dir/probes/<session>.exr`` (+ coverage PNG);
    returns its ``probes`` row: status ``error`` with the reason, naming the session, when
    assembly fails or the probe is not one (:func:`f2l.lighting.plausibility.probe_problem` on the
    radiance and the coverage mask: black, less than a quarter of the sky seen, NaN/inf), and
    then no probe file is written.
    ``colour_spaces``: each view's (views in different spaces are not blended). ``restore_sun``:
    a sun saturated in every frame gets its energy back from the sky
    (:mod:`f2l.capture.sun_restore`; flagged in ``sun_restored`` and the message). ``full_probe``:
    also the probe at the views' own resolution (:func:`write_full_probe`, ``full_path``)."""
    from f2l.capture.sphere import assemble
    from f2l.io.exr import REC709_CHROMATICITIES, write_exr
    from f2l.lighting.grid import LatLongGrid
    from f2l.lighting.plausibility import probe_problem

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    spaces = sorted(set(colour_spaces or ["rec709"]))
    if len(spaces) > 1:
        by = {sp: [v.name for v, c in zip(views, colour_spaces) if c == sp] for sp in spaces}
        return _row("probe", session, session, "error", "views in different colour spaces ("
                    + "; ".join(f"{sp}: {', '.join(names)}" for sp, names in by.items()) + ")")
    names = ", ".join(v.name for v in views)
    try:
        with np.errstate(all="ignore"):
            probe = assemble(views, grid_height, grid_width)
    except (ValueError, ArithmeticError) as exc:
        return _row("probe", session, session, "error", f"session {session}: probe not assembled from "
                    f"{names}: {exc}", frames=len(views))
    grid = LatLongGrid(grid_height, grid_width)
    rel = f"probes/{_safe(session)}.exr"
    (out_dir / "probes").mkdir(parents=True, exist_ok=True)
    sa = grid.solid_angles.reshape(grid.height, grid.width)
    row = _row("probe", session, session, "ok", "", path=rel, frames=len(views),
               saturated_fraction=float((sa * probe.saturated).sum() / sa.sum()),
               coverage_fraction=float((sa * probe.coverage).sum() / sa.sum()), colour_space=spaces[0])
    problem = probe_problem(probe.radiance, coverage=probe.coverage)
    if problem:  # never an "ok" probe (nor ground truth) that is black, uncovered or not finite
        row.update(status="error", path=None, message=f"session {session}: probe refused ({names}): {problem}",
                   seconds=round(time.perf_counter() - t0, 3))
        return finite_row(row)
    _set_sun(row, views)
    if row["sun_elevation_deg"] is None and probe.coverage[: grid.height // 2].any():
        from f2l.lighting.sun import sun_direction

        d = sun_direction(probe.radiance, grid)
        row["sun_elevation_deg"] = math.degrees(math.asin(float(np.clip(d[1], -1, 1))))
        row["sun_azimuth_deg"] = math.degrees(math.atan2(float(d[0]), float(-d[2])))
    radiance, meta = probe.radiance, {"f2l_session": session, "f2l_views": str(len(views)),
                                      "f2l_colour_space": spaces[0]}
    if restore_sun:
        radiance = _restore_sun(row, probe, grid, meta)
        problem = probe_problem(radiance, coverage=probe.coverage)
        if problem:
            row.update(status="error", path=None, sun_restored=None,
                       message=f"session {session}: probe refused after the sun's restoration ({names}): {problem}")
    if finite_row(row)["status"] != "ok":
        row.update(path=None, seconds=round(time.perf_counter() - t0, 3))
        return row
    write_exr(out_dir / rel, radiance, metadata=meta,
              chromaticities=REC709_CHROMATICITIES if spaces[0] == "rec709" else None)
    _write_mask_png(out_dir / rel.replace(".exr", ".coverage.png"), probe.coverage)
    if full_probe:
        row["full_path"], height = write_full_probe(session, views, out_dir, spaces[0])
        row["message"] = "; ".join(m for m in (row["message"], f"full-resolution probe {height}x{2 * height}") if m)
    row["seconds"] = round(time.perf_counter() - t0, 3)
    return row


def _restore_sun(row: dict, probe, grid, meta: dict) -> np.ndarray:
    """The probe with its clipped sun restored (row and EXR header say what was done)."""
    from f2l.capture.sun_restore import restore_sun
    from f2l.lighting.grid import direction_from_angles

    if row["sun_elevation_deg"] is None:
        row["sun_restored"], row["message"] = False, "sun not restored: no sun found in the views"
        return probe.radiance
    sun = direction_from_angles(math.radians(row["sun_elevation_deg"]), math.radians(row["sun_azimuth_deg"]))
    radiance, result = restore_sun(probe.radiance, probe.saturated, probe.coverage, sun, grid)
    row["sun_restored"] = result.restored
    row["message"] = "; ".join(m for m in (row["message"], result.message()) if m)
    meta["f2l_sun_restored"] = result.message()
    return radiance


def given_probe_on_grid(probe: np.ndarray, label: str, grid_height: int, grid_width: int,
                        source_hw: tuple[int, int] | None = None) -> tuple[np.ndarray, str]:
    """A given probe (role ``probe``, already read) on the ``grid_height`` x ``grid_width`` grid,
    area-resampled when its size differs, and a note saying so (``source_hw``: the file's size
    when the reader already area-averaged it to the grid); ValueError ``"<label>: reason"``
    when it cannot serve as a probe or ground truth (not a full-sphere lat-long, or
    :func:`f2l.lighting.plausibility.probe_problem`: black, NaN/inf, negative, too little sky)."""
    from f2l.lighting.plausibility import probe_problem
    from f2l.lighting.resample import resample

    probe = np.asarray(probe)
    if probe.ndim != 3 or probe.shape[2] != 3:
        raise ValueError(f"{label}: not an RGB image (shape {probe.shape})")
    h, w = probe.shape[:2]
    if w != 2 * h:
        raise ValueError(f"{label}: a {h}x{w} probe is not a full-sphere lat-long (width = 2 x height)")
    problem = None if np.isfinite(probe).all() else "NaN or infinite values"
    sh, sw = source_hw if source_hw is not None else (h, w)
    note = "" if (sh, sw) == (grid_height, grid_width) else f"resampled from {sh}x{sw} to {grid_height}x{grid_width}"
    if problem is None and (h, w) != (grid_height, grid_width):
        probe = resample(probe, grid_height, grid_width)
    problem = problem or probe_problem(probe)
    if problem:
        raise ValueError(f"{label}: {problem}")
    return np.asarray(probe, np.float32), note


def read_given_probe(path: str | os.PathLike, grid_height: int, grid_width: int) -> np.ndarray:
    """A given probe's pixels, in memory bounded by the grid: its size is read from the header
    first (a file that is no full-sphere lat-long, W = 2H, is refused before any decoding), then
    :func:`f2l.io.probe_io.read_hdr_image` with the grid as its target (an image over the decode
    limit comes back area-averaged to the grid, decoded in bands). ValueError naming the file."""
    from f2l.io.probe_io import hdr_image_size, read_hdr_image

    h, w = hdr_image_size(path)
    if w != 2 * h:
        raise ValueError(f"{path}: a {h}x{w} probe is not a full-sphere lat-long (width = 2 x height)")
    return read_hdr_image(path, (int(grid_height), int(grid_width)))


def _given_row(root: Path, r: dict, grid_height: int, grid_width: int) -> dict:
    """The ``given`` row of an already-merged probe: ingest's status, or ``error`` (naming the
    session and the file) when it is unreadable or no probe (:func:`given_probe_on_grid`)."""
    row = _row("given", r["path"], r["session"], r["status"], r["message"], path=str(root / r["path"]))
    if r["status"] != "ok":
        return row
    from f2l.io.probe_io import hdr_image_size

    try:
        _, note = given_probe_on_grid(read_given_probe(root / r["path"], grid_height, grid_width), r["path"],
                                      grid_height, grid_width, hdr_image_size(root / r["path"]))
        row["message"] = "; ".join(m for m in (row["message"], note) if m)
    except (ValueError, ArithmeticError) as exc:
        reason = str(exc).replace(str(root).rstrip("/") + "/", "")
        row.update(status="error", message=f"session {r['session']}: given probe refused: {reason}")
    except Exception as exc:  # noqa: BLE001 - memory, a library that cannot load: this row, not the batch
        row.update(status="error", message=f"session {r['session']}: given probe {r['path']} not read: "
                                           f"{type(exc).__name__}: {exc}")
    return row


def _sessions_without_probe(captures: list[dict], rows: list[dict]) -> list[dict]:
    """A ``skipped`` probe row for each session with no merged bracket and no given probe, saying
    exactly what the session lacks."""
    done = {r["session"] for r in rows}
    out = []
    for session in sorted({r["session"] for r in captures} - done):
        members = [r for r in captures if r["session"] == session]
        sky = [r for r in members if r["role"] == "sky_bracket"]
        lacks = []
        if sky:
            lacks.append("no sky bracket could be merged: " + "; ".join(sorted({r["message"] for r in sky})))
        else:
            lacks.append("no sky bracket: no frames in a sky/ folder or with role sky_bracket in session.toml, "
                         "and no frames of one camera with stepped exposures")
        views = [json.loads(r["view_json"] or "{}") for r in members]
        if not any(("projection" in v or "colmap_model" in v) for v in views):
            problem = next((r["session_problem"] for r in members if r.get("session_problem")), "")
            lacks.append("session.toml was not used: " + problem if problem else
                         "no lens description (session.toml [lens] projection or colmap_model) to place a view")
        out.append(_row("probe", session, session, "skipped", f"session {session}: " + "; ".join(lacks)))
    return out


def make_probes(root: str | os.PathLike, work: str | os.PathLike, *, grid_height: int = 128,
                grid_width: int | None = None, view_max_side: int = 1024, colour_space: str = "rec709",
                restore_sun: bool = False, full_probe: bool = False, progress: bool = False) -> ProbesSummary:
    """Run the merge and sphere stages for every session of ``work/captures.parquet`` (probe grid
    ``grid_height`` x ``grid_width``, default 2 x height; ``restore_sun``, ``full_probe``: see
    :func:`assemble_session`)."""
    import pyarrow.parquet as pq

    from f2l.io.tables import rows_to_table, write_table_atomic

    t_start = time.perf_counter()
    root, work = Path(root), Path(work)
    grid_width = 2 * grid_height if grid_width is None else grid_width
    opts = ViewOptions(view_max_side, colour_space, root)
    table = work / "captures.parquet"
    if not table.is_file():
        raise FileNotFoundError(f"{table}: not found (run `f2l ingest {root} --work {work}` first)")
    captures = pq.read_table(table).to_pylist()
    (work / "views").mkdir(exist_ok=True)
    (work / "probes").mkdir(exist_ok=True)
    summary = ProbesSummary(work=str(work))
    brackets: dict[str, list[dict]] = {}
    for r in captures:
        if r["bracket_id"] and r["status"] == "ok":
            brackets.setdefault(r["bracket_id"], []).append(r)
    # Session by session (its views are blended as soon as its last bracket is merged, then
    # dropped: memory holds one session's views, never the dataset's). One bracket is merged at
    # a time; the previous one's downsampling and files are written by a thread meanwhile, and
    # the next one's first two frames are decoded as soon as this one's last is under way.
    items = sorted(brackets.items(), key=lambda item: (item[1][0]["session"], item[0]))
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(items), desc="merge", unit="bracket")
    views: list = []
    spaces: list = []

    def collect(pending) -> None:
        finished, bid, frames = pending
        try:
            row, view = finished.result()
        except Exception as exc:  # noqa: BLE001 - one bracket never loses the batch
            row, view = _row("view", bid, frames[0]["session"], "error",
                             f"session {frames[0]['session']}: bracket {bid} ({frames[0]['path']}, ...): "
                             f"{type(exc).__name__}: {exc}", frames=len(frames)), None
        summary.rows.append(row)
        summary.brackets += 1
        if view is not None:
            summary.views += 1
            views.append(view)
            spaces.append(row["colour_space"])
        if bar is not None:
            bar.update(1)

    def assemble(session: str) -> None:
        if views:
            try:
                row = assemble_session(session, views, work, grid_height, grid_width, spaces, restore_sun,
                                       full_probe)
            except Exception as exc:  # noqa: BLE001 - one session never loses the batch
                row = _row("probe", session, session, "error", f"session {session}: probe not assembled: "
                           f"{type(exc).__name__}: {exc}", frames=len(views))
            summary.rows.append(row)
            summary.probes += row["status"] == "ok"
        views.clear()
        spaces.clear()

    from f2l.capture.merge import BracketStart

    for _, frames in items:
        frames.sort(key=lambda f: f["path"])
    starts: dict[int, BracketStart] = {}

    def start(k: int) -> None:  # begin decoding bracket k (frames go to the shared decode pool)
        if k < len(items) and k not in starts:
            starts[k] = BracketStart([root / f["path"] for f in items[k][1]], decoder, prefetch=2)
            starts[k].when_all_submitted(lambda: start(k + 1))

    with ThreadPoolExecutor(max_workers=1) as writer, ThreadPoolExecutor(max_workers=2) as decoder:
        pending, session = None, None
        for k, (bid, frames) in enumerate(items):
            if frames[0]["session"] != session:
                if pending is not None:
                    collect(pending)
                    pending = None
                assemble(session)
                session = frames[0]["session"]
            start(k)
            merged = _merge_frames(root, bid, frames, starts.pop(k))
            if pending is not None:
                collect(pending)
            pending = (writer.submit(_finish_one, work, bid, frames, opts, *merged), bid, frames)
            del merged
        if pending is not None:
            collect(pending)
        assemble(session)
    if bar is not None:
        bar.close()
    for r in captures:  # already-merged probes
        if r["role"] == "probe" and r["kind"] == "hdr":
            summary.rows.append(_given_row(root, r, grid_height, grid_width))
    summary.rows.extend(_sessions_without_probe(captures, summary.rows))
    summary.rows = checked_rows(summary.rows, str(work / "probes.parquet"))
    summary.probes = sum(r["kind"] == "probe" and r["status"] == "ok" for r in summary.rows)
    summary.errors = sum(r["status"] == "error" for r in summary.rows)
    write_table_atomic(rows_to_table(summary.rows, "probes"), work / "probes.parquet", "probes")
    summary.seconds = round(time.perf_counter() - t_start, 3)
    return summary
