"""Which frames of a session form one exposure bracket (the "brackets" part of
:mod:`f2l.capture.ingest`'s conventions): frames within ``bracket_gap_s`` of each other, split where
the view (session TOML orientation, lens) changes, where an exposure repeats and where the capture
time jumps; declared sky frames by their role, undeclared ones by stepped exposures of one camera
and framing."""

from __future__ import annotations

import math
from datetime import datetime
from pathlib import Path

import numpy as np

from f2l.capture.view_spec import ViewSpec


def _capture_time(row: dict) -> float:
    if row.get("timestamp_utc"):
        try:
            return datetime.fromisoformat(row["timestamp_utc"]).timestamp()
        except ValueError:
            pass
    return row["mtime_ns"] / 1e9


def split_by_time(rows: list[dict], gap_s: float) -> list[list[dict]]:
    """Consecutive groups (by capture time) whose neighbours are at most ``gap_s`` apart."""
    rows = sorted(rows, key=lambda r: (_capture_time(r), r["path"]))
    groups: list[list[dict]] = []
    for r in rows:
        if groups and _capture_time(r) - _capture_time(groups[-1][-1]) <= gap_s:
            groups[-1].append(r)
        else:
            groups.append([r])
    return groups


def _frame_key(r: dict) -> tuple:
    return (r["camera"], r["lens"], r["width"], r["height"], r["focal_length_mm"])


def _exposure(r: dict) -> float | None:
    if not (r["exposure_s"] and r["f_number"] and r["iso"]):
        return None
    return r["exposure_s"] * r["iso"] / r["f_number"] ** 2


JUMP_MIN_S = 3.0


JUMP_FACTOR = 4.0
"""Within a run, a pause longer than max(JUMP_MIN_S, JUMP_FACTOR x the run's median pause) between
frames (capture-time difference less the earlier frame's exposure time) starts a new bracket."""


def _view_key(r: dict) -> str:
    """What places a frame: its view spec's orientation and lens (:meth:`ViewSpec.placement_key`)."""
    return ViewSpec.from_json(r["view_json"]).placement_key()


def _stop(r: dict) -> float | None:
    e = _exposure(r)
    return None if not e else round(3.0 * math.log2(e)) / 3.0  # to the nearest 1/3 EV


def split_brackets(run: list[dict]) -> list[list[dict]]:
    """Split a time-ordered run of frames into brackets: a new one starts where the frame's view
    (session TOML orientation or lens) changes, where its exposure (to 1/3 EV) already occurs in
    the bracket (the sequence restarted), or where the capture time jumps (:data:`JUMP_FACTOR`)."""
    pauses = [max(0.0, _capture_time(b) - _capture_time(a) - (a["exposure_s"] or 0.0)) for a, b in zip(run, run[1:])]
    jump = max(JUMP_MIN_S, JUMP_FACTOR * float(np.median(pauses))) if pauses else 0.0
    out: list[list[dict]] = []
    for i, r in enumerate(run):
        cur = out[-1] if out else None
        if cur is not None and _view_key(r) == _view_key(cur[-1]) and pauses[i - 1] <= jump and (
                _stop(r) is None or _stop(r) not in {_stop(x) for x in cur}):
            cur.append(r)
        else:
            out.append([r])
    return out


def bracket_summary(rows: list[dict]) -> list[dict]:
    """One dict per bracket of ``rows``: id, session, frames, EV100 range, camera and view (yaw,
    pitch, roll from the session TOML), for ingest's report."""
    by: dict[str, list[dict]] = {}
    for r in rows:
        if r.get("bracket_id"):
            by.setdefault(r["bracket_id"], []).append(r)
    out = []
    for bid, frames in sorted(by.items()):
        pose = ViewSpec.from_json(frames[0]["view_json"]).pose
        evs = [r["ev100"] for r in frames if r.get("ev100") is not None]
        out.append({"bracket_id": bid, "session": frames[0]["session"], "frames": len(frames),
                    "ev100_min": min(evs) if evs else None, "ev100_max": max(evs) if evs else None,
                    "camera": frames[0]["camera"],
                    "view": pose})
    return out


def assign_brackets(rows: list[dict], gap_s: float) -> int:
    """Set ``bracket_id`` / role / status on one session's frames (module doc); returns the
    number of brackets."""
    count = 0
    frames = [r for r in rows if r["status"] == "ok" and r["kind"] in ("raw", "image")]
    declared = [r for r in frames if r["role"] == "sky_bracket"]
    free = [r for r in frames if r["role_source"] == "none"]
    for run in (b for run in split_by_time(declared, gap_s) for b in split_brackets(run)):
        keys = {_frame_key(r) for r in run}
        if len(keys) > 1:
            desc = "; ".join(f"{k[0] or 'unknown camera'} {k[2]}x{k[3]}" for k in sorted(keys, key=str))
            for r in run:
                r["status"], r["message"] = "error", (
                    f"{r['path']}: bracket mixes cameras or frame sizes ({desc})")
            continue
        if len(run) == 1:
            r = run[0]
            r["status"], r["message"] = "skipped", (
                f"{r['path']}: bracket of one frame (no other frame of its view within {gap_s:g} s and "
                f"its exposure sequence): nothing to merge")
            continue
        count += 1
        bid = f"{run[0]['session']}/{Path(run[0]['path']).stem}"
        for r in run:
            r["bracket_id"] = bid
    # undeclared frames: a bracket if same camera/framing and stepped exposures
    for run in split_by_time(free, gap_s):
        by_key: dict = {}
        for r in run:
            by_key.setdefault(_frame_key(r), []).append(r)
        for group in (b for g in by_key.values() for b in split_brackets(g)):
            exposures = {round(math.log2(e), 1) for e in map(_exposure, group) if e}
            if len(group) >= 2 and len(exposures) >= 2 and all(_exposure(r) for r in group):
                count += 1
                bid = f"{group[0]['session']}/{Path(group[0]['path']).stem}"
                for r in group:
                    r.update(bracket_id=bid, role="sky_bracket", role_source="detected")
    return count
