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
2. the view's lens, fall-off and orientation from the row's ``view_json`` (the session TOML's
   :class:`~f2l.capture.view_spec.ViewSpec`, :mod:`f2l.capture.lens`), mapped from the full
   frame to the box-averaged view. A bracket without a lens cannot be placed on the sphere and is
   reported (``unplaced``), not guessed.

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

from concurrent.futures import ThreadPoolExecutor
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from f2l.capture.probe_rows import _row, _safe, _write_mask_png, checked_rows, finite_row
from f2l.capture.view_spec import ViewSpec, ViewSpecError
from f2l.capture.views import ViewOptions, _finish_one, _merge_frames, _set_sun
from f2l.io.progress import Progress, ProgressCallback


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


def _describes_lens(row: dict) -> bool:
    """Whether a captures row's view spec gives a lens geometry (an undecodable one is described,
    but unusable: its brackets' rows say why)."""
    try:
        return ViewSpec.from_json(row["view_json"]).lens.describes_geometry
    except ViewSpecError:
        return True


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
        if not any(_describes_lens(r) for r in members):
            problem = next((r["session_problem"] for r in members if r.get("session_problem")), "")
            lacks.append("session.toml was not used: " + problem if problem else
                         "no lens description (session.toml [lens] projection or colmap_model) to place a view")
        out.append(_row("probe", session, session, "skipped", f"session {session}: " + "; ".join(lacks)))
    return out


def make_probes(root: str | os.PathLike, work: str | os.PathLike, *, grid_height: int = 128,
                grid_width: int | None = None, view_max_side: int = 1024, colour_space: str = "rec709",
                restore_sun: bool = False, full_probe: bool = False,
                progress: ProgressCallback | None = None) -> ProbesSummary:
    """Run the merge and sphere stages for every session of ``work/captures.parquet`` (probe grid
    ``grid_height`` x ``grid_width``, default 2 x height; ``restore_sun``, ``full_probe``: see
    :func:`assemble_session`). ``progress``: a callback told of each bracket merged
    (:mod:`f2l.io.progress`)."""
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
    bar = Progress(progress, "merge", "bracket", len(items))
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
        bar.advance()

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
