"""Merge and sphere stages over an ingested capture tree: brackets → HDR views → one lat-long
probe per session (``f2l make-probes``).

For each ``bracket_id`` of ``WORK/captures.parquet`` (frames with status ok), in path order:

1. :func:`f2l.capture.merge.merge_bracket` in the RAW domain (one bracket in memory at a time),
   vignetting divided out, then box-averaged by an integer factor to at most ``view_max_side``
   px (radiance-preserving; a block is saturated if any of its pixels is; 1024 px keeps ~0.2°
   per pixel on a 180° fisheye, 14× finer than a 64 × 128 probe texel), written to
   ``WORK/views/<bracket>.exr`` (float32 camera RGB; 1.0 = full scale at EV100 0) with its
   saturated mask ``WORK/views/<bracket>.saturated.png``. Only these small views stay in
   memory until their session is assembled;
2. the view's lens and orientation from the row's ``view_json`` (the session TOML): projection
   (``equidistant`` / ``equisolid`` fisheye, ``rectilinear``), ``fov_deg``, ``yaw_deg``,
   ``pitch_deg``, ``roll_deg``, ``vignetting`` (divided out). A bracket without a lens model
   cannot be placed on the sphere and is reported, not guessed.

Then per session, :func:`f2l.capture.sphere.assemble` blends the session's placed views into
``WORK/probes/<session>.exr`` (DESIGN lat-long convention, float32) with the coverage mask
``WORK/probes/<session>.coverage.png`` (white = seen; the rest, e.g. the ground under an
up-looking fisheye, is 0 in the probe and never invented). ``WORK/probes.parquet`` (schema
``probes``) has one row per bracket and per session probe. Already-merged probes (role
``probe``) are listed with their path. Values stay in camera RGB: colour calibration
(:mod:`f2l.colour`) maps them to Rec.709.
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

PROJECTIONS = ("equidistant", "equisolid", "rectilinear")


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


def camera_for(view: dict, width: int, height: int):
    """The :class:`~f2l.capture.cameras.ViewCamera` a row's ``view_json`` describes (ValueError
    naming what is missing)."""
    from f2l.capture.cameras import ViewCamera

    projection = view.get("projection")
    if projection not in PROJECTIONS:
        raise ValueError(f"no usable lens projection (got {projection!r}; session.toml [lens] "
                         f"projection must be one of {', '.join(PROJECTIONS)})")
    if "fov_deg" not in view:
        raise ValueError("no field of view (session.toml [lens] fov_deg)")
    pose = {k: float(view.get(k, 0.0)) for k in ("yaw_deg", "pitch_deg", "roll_deg")}
    fov = float(view["fov_deg"])
    if projection == "rectilinear":
        return ViewCamera.pinhole(fov, width, height, **pose)
    make = ViewCamera.equidistant if projection == "equidistant" else ViewCamera.equisolid
    return make(fov, width, height, **pose)


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
           "sun_elevation_deg": None, "sun_azimuth_deg": None, "seconds": 0.0}
    row.update(kw)
    return row


def downsample_view(rgb: np.ndarray, saturated: np.ndarray, max_side: int):
    """Box-average (h, w, 3) by the smallest integer factor k with max(h, w) / k <= max_side
    (a centred crop drops the h % k, w % k remainder); saturated if any pixel of the block is.

    The k * k strided sub-images are summed in float32 (k * k terms of one sign: relative error
    below k * k * 6e-8), 25x faster than a float64 ``mean`` over a reshaped view."""
    h, w = rgb.shape[:2]
    k = max(1, -(-max(h, w) // int(max_side)))
    if k == 1:
        return rgb, saturated
    hh, ww = h // k * k, w // k * k
    r0, c0 = (h - hh) // 2, (w - ww) // 2
    crop, sat = rgb[r0:r0 + hh, c0:c0 + ww], saturated[r0:r0 + hh, c0:c0 + ww]
    total, flag = np.zeros((hh // k, ww // k, 3), np.float32), np.zeros((hh // k, ww // k), bool)
    for a in range(k):
        for b in range(k):
            total += crop[a::k, b::k]
            flag |= sat[a::k, b::k]
    total *= np.float32(1.0 / (k * k))
    return total, flag


def _merge_one(root: Path, work: Path, bid: str, frames: list[dict],
               view_max_side: int) -> tuple[dict, object | None]:
    """Merge one bracket → (row, placed view or None)."""
    return _finish_one(work, bid, frames, view_max_side, *_merge_frames(root, bid, frames))


def _merge_frames(root: Path, bid: str, frames: list[dict], started=None):
    """The bracket merge itself: (merged or None, error row or None, start time). ``started``: the
    bracket's :class:`~f2l.capture.merge.BracketStart` when its decoding has already begun."""
    from f2l.capture.merge import merge_bracket

    t0 = time.perf_counter()
    try:
        return merge_bracket(started if started is not None else [root / f["path"] for f in frames]), None, t0
    except Exception as exc:  # BracketError / RawError name the files
        return None, _row("view", bid, frames[0]["session"], "error", str(exc), frames=len(frames)), t0


def _finish_one(work: Path, bid: str, frames: list[dict], view_max_side: int, merged, error_row,
                t0: float) -> tuple[dict, object | None]:
    """Vignetting, downsampling and the view's files for a merged bracket → (row, placed view or None)."""
    from f2l.capture.cameras import Vignetting, correct_vignetting
    from f2l.capture.sphere import View
    from f2l.io.exr import write_exr

    if merged is None:
        return error_row, None
    session = frames[0]["session"]
    info = json.loads(frames[0]["view_json"] or "{}")
    rgb = merged.rgb
    if info.get("vignetting"):
        k = list(info["vignetting"]) + [0.0] * (3 - len(info["vignetting"]))
        rgb = correct_vignetting(rgb, Vignetting(*k))
    rgb, saturated = downsample_view(rgb, merged.saturated, view_max_side)
    rel = f"views/{_safe(bid)}.exr"
    write_exr(work / rel, rgb, metadata={"f2l_bracket": bid, "f2l_units": "camera RGB, 1.0 = full scale at EV100 0"},
              compression="none")  # an intermediate: float32 noise leaves ZIP 5% at 15x the time
    _write_mask_png(work / rel.replace(".exr", ".saturated.png"), saturated)
    warnings = "; ".join(merged.warnings) if merged.warnings else ""
    row = _row("view", bid, session, "ok", warnings, path=rel, frames=len(frames),
               saturated_fraction=float(merged.saturated_fraction),
               seconds=round(time.perf_counter() - t0, 3))
    try:
        camera = camera_for(info, rgb.shape[1], rgb.shape[0])
    except ValueError as exc:
        row.update(status="unplaced", message=f"{frames[0]['path']}: {exc}")
        return row, None
    return row, View(image=rgb, camera=camera, saturated=saturated, name=bid)


def merge_bracket_view(root: str | os.PathLike, out_dir: str | os.PathLike, bracket_id: str,
                       frames: list[dict], view_max_side: int = 1024) -> tuple[dict, object | None]:
    """Merge one bracket (its ``captures`` rows, any order) into ``out_dir/views/<bracket>.exr``
    and ``.saturated.png``; returns (the ``probes`` row, the placed
    :class:`~f2l.capture.sphere.View` or None when it failed or has no lens model)."""
    (Path(out_dir) / "views").mkdir(parents=True, exist_ok=True)
    frames = sorted(frames, key=lambda f: f["path"])
    return _merge_one(Path(root), Path(out_dir), bracket_id, frames, view_max_side)


def load_view(out_dir: str | os.PathLike, row: dict, view_json: str):
    """The placed :class:`~f2l.capture.sphere.View` of a merged bracket from its files under
    ``out_dir`` (``row`` from :func:`merge_bracket_view`, status ``ok``) and the ``view_json`` of
    its frames; ValueError when the row has no lens model."""
    from f2l.capture.sphere import View
    from f2l.io.exr import read_exr

    out_dir = Path(out_dir)
    rgb = read_exr(out_dir / row["path"])
    saturated = _read_mask_png(out_dir / row["path"].replace(".exr", ".saturated.png"))
    camera = camera_for(json.loads(view_json or "{}"), rgb.shape[1], rgb.shape[0])
    return View(image=rgb, camera=camera, saturated=saturated, name=row["name"])


def assemble_session(session: str, views: list, out_dir: str | os.PathLike, grid_height: int = 64,
                     grid_width: int = 128) -> dict:
    """Blend one session's placed views into ``out_dir/probes/<session>.exr`` (+ coverage PNG);
    returns its ``probes`` row (status ``error`` with the reason when assembly fails)."""
    from f2l.capture.sphere import assemble
    from f2l.io.exr import write_exr
    from f2l.lighting.grid import LatLongGrid
    from f2l.metrics.lighting import sun_direction

    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    try:
        probe = assemble(views, grid_height, grid_width)
    except ValueError as exc:
        return _row("probe", session, session, "error", str(exc))
    grid = LatLongGrid(grid_height, grid_width)
    rel = f"probes/{_safe(session)}.exr"
    (out_dir / "probes").mkdir(parents=True, exist_ok=True)
    write_exr(out_dir / rel, probe.radiance, metadata={"f2l_session": session,
                                                       "f2l_views": str(len(views))})
    _write_mask_png(out_dir / rel.replace(".exr", ".coverage.png"), probe.coverage)
    sa = grid.solid_angles.reshape(grid.height, grid.width)
    coverage = float((sa * probe.coverage).sum() / sa.sum())
    elev = azim = None
    if probe.coverage[: grid.height // 2].any():
        d = sun_direction(probe.radiance, grid)
        elev = math.degrees(math.asin(float(np.clip(d[1], -1, 1))))
        azim = math.degrees(math.atan2(float(d[0]), float(-d[2])))
    return _row("probe", session, session, "ok", "", path=rel, frames=len(views),
                saturated_fraction=float((sa * probe.saturated).sum() / sa.sum()),
                coverage_fraction=coverage, sun_elevation_deg=elev, sun_azimuth_deg=azim,
                seconds=round(time.perf_counter() - t0, 3))


def make_probes(root: str | os.PathLike, work: str | os.PathLike, *, grid_height: int = 64,
                grid_width: int = 128, view_max_side: int = 1024,
                progress: bool = False) -> ProbesSummary:
    """Run the merge and sphere stages for every session of ``work/captures.parquet``."""
    import pyarrow.parquet as pq

    from f2l.io.tables import rows_to_table, write_table_atomic

    t_start = time.perf_counter()
    root, work = Path(root), Path(work)
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

    def collect(finished) -> None:
        row, view = finished.result()
        summary.rows.append(row)
        summary.brackets += 1
        if view is not None:
            summary.views += 1
            views.append(view)
        if bar is not None:
            bar.update(1)

    def assemble(session: str) -> None:
        if views:
            row = assemble_session(session, views, work, grid_height, grid_width)
            summary.rows.append(row)
            summary.probes += row["status"] == "ok"
        views.clear()

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
            pending = writer.submit(_finish_one, work, bid, frames, view_max_side, *merged)
            del merged
        if pending is not None:
            collect(pending)
        assemble(session)
    if bar is not None:
        bar.close()
    for r in captures:  # already-merged probes
        if r["role"] == "probe" and r["kind"] == "hdr":
            summary.rows.append(_row("given", r["path"], r["session"], r["status"], r["message"],
                                     path=str(root / r["path"])))
    summary.errors = sum(r["status"] == "error" for r in summary.rows)
    write_table_atomic(rows_to_table(summary.rows, "probes"), work / "probes.parquet", "probes")
    summary.seconds = round(time.perf_counter() - t_start, 3)
    return summary
