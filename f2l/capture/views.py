"""One bracket → one HDR view (the merge stage of :mod:`f2l.capture.probes`): the bracket's frames
merged in the RAW domain (:mod:`f2l.capture.merge`), turned to linear Rec.709 through the camera's
colour matrix, box-averaged to ``view_max_side`` and written as ``views/<bracket>.exr`` with its
saturation mask; :func:`load_view` reads one back, placed by its session TOML view, and
:func:`view_sun` finds the sun in it."""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from f2l.capture.probe_rows import COLOUR_SPACES, _read_mask_png, _row, _safe, _write_mask_png, camera_for, finite_row
from f2l.capture.view_spec import ViewSpec


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
    from f2l.capture.lens import lens_of
    from f2l.capture.sphere import View
    from f2l.io.exr import REC709_CHROMATICITIES, write_exr

    if merged is None:
        return error_row, None
    session, first = frames[0]["session"], frames[0]
    full_h, full_w = merged.mosaic.shape
    k, crop_y, crop_x = downsample_plan(full_h, full_w, opts.view_max_side)
    rgb, saturated = downsample_view(merged.rgb, merged.saturated, opts.view_max_side)
    warnings = list(merged.warnings)
    rgb, space = _to_colour_space(rgb, merged, opts, warnings)
    frame = (full_w, full_h, k, crop_x, crop_y)
    camera, problem, failed, spec = None, "", "", None
    try:
        spec = ViewSpec.from_json(first["view_json"])
        lens = lens_of(spec.lens, full_w, full_h, first.get("focal_length_mm"))
        camera = lens.view_camera(rgb.shape[1], rgb.shape[0], k, crop_x, crop_y, **spec.pose_deg())
        gain = lens.gain(camera, k, crop_x, crop_y, opts.root)
        if gain is not None:
            rgb = rgb / gain[..., None]
    except (ValueError, ArithmeticError) as exc:
        camera, problem = None, f"{first['path']}: {exc}"
        if first.get("session_problem"):
            problem += f" (session.toml was not used: {first['session_problem']})"
        if spec is None or spec.lens.describes_geometry:  # described, but unusable
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
    its frames (:meth:`~f2l.capture.view_spec.ViewSpec.from_json`); ValueError when the row has
    no lens model."""
    from f2l.capture.sphere import View
    from f2l.io.exr import read_exr_with_metadata

    out_dir = Path(out_dir)
    rgb, meta = read_exr_with_metadata(out_dir / row["path"])
    saturated = _read_mask_png(out_dir / row["path"].replace(".exr", ".saturated.png"))
    frame = tuple(int(v) for v in meta["f2l_view_from_frame"].split()) if "f2l_view_from_frame" in meta else None
    camera = camera_for(ViewSpec.from_json(view_json), rgb.shape[1], rgb.shape[0], frame=frame,
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
