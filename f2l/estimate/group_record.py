"""Faces that share one light as ``estimates`` rows: the unit of work of ``f2l estimate --joint photo``.

A group (the faces of one photo) is estimated with :func:`f2l.estimate.joint.estimate_joint`: one
probe for the group (``probes/<model>/group-<id>.exr``) and one row per face, each naming the
group (``group_id``, ``group_size``), whether the group's light used the face (``group_used``), how
well the face agrees with it (``agreement``), its weight and exposure gain. A face the group left
out (it disagrees: in another's shadow, under a hat) gets its own estimate in its row, and the row's
message says why. A group of one is the single-face row of :func:`f2l.estimate.record.estimate_record`,
bit for bit. A model that cannot be estimated jointly (latent-sky) estimates the faces one by one,
and says so in each row.
"""

from __future__ import annotations

import dataclasses
import hashlib
import time
from pathlib import Path

import numpy as np

from f2l.estimate.config import EstimatorConfig
from f2l.estimate.frames import turn_observation
from f2l.estimate.joint import DISAGREE_RATIO, JointUnsupported, estimate_joint
from f2l.estimate.observation import EstimationError, FaceObservation
from f2l.estimate.record import (UNCERTAINTY_DEFAULTS, _base_row, _get_model, _safe_name, capture_sun_prior,
                                 config_hash, estimate_in_memory, estimate_record, record_absolute_scale, torch_threads, write_result)
from f2l.io.record_limits import declared_size_problem
from f2l.lighting.grid import LatLongGrid
from f2l.models.capabilities import SunAngles

JOINT_MODES = ("photo", "session", "none")
YAW_KEY = "camera_yaw_deg"  # record meta: the camera's heading in the session's frame (deg, + = right)


def joint_settings(mode: str) -> dict:
    """What a joint row's estimate depends on beyond the estimator's config."""
    return {"mode": mode, "disagree_ratio": DISAGREE_RATIO}


def group_key(record, mode: str) -> str:
    """Which faces share one light: the photo (``photo``), the record's ``meta["session"]`` (or
    ``meta["joint_group"]``; ``session``, else its photo), or the face itself (``none``)."""
    meta = record.meta if isinstance(getattr(record, "meta", None), dict) else {}
    if mode == "session":
        key = meta.get("joint_group") or meta.get("session")
        if isinstance(key, str) and key:
            return f"session:{key}"
    if mode == "none":
        return f"face:{record.face_id}"
    return f"photo:{record.source_path}"


def group_id_of(source_path: str) -> str:
    """A group's id from its photo: the file's stem and 8 hex digits of its full path."""
    digest = hashlib.sha256(str(source_path).encode("utf-8", "surrogateescape")).hexdigest()[:8]
    return f"{_safe_name(Path(str(source_path)).stem)[:64]}-{digest}"


def joint_hash(model_name: str, model_version: str, cfg: EstimatorConfig, mode: str = "photo") -> str:
    """The config hash of rows estimated in a group of several faces."""
    return config_hash(model_name, model_version, cfg, joint_settings(mode))


def estimate_alone(records: list, model_name: str, out_dir: str, cfg: EstimatorConfig) -> list[dict]:
    """Each face of ``records`` estimated by itself (``--joint none``): their single-face rows."""
    return [estimate_record(r, model_name, out_dir, cfg) for r in records]


def estimate_session(records: list, model_name: str, out_dir: str, cfg: EstimatorConfig) -> list[dict]:
    """Estimate the faces of one session (``records``, several photos) with one light: each face
    turned into the first photo's camera frame by its camera's heading (``meta["camera_yaw_deg"]``,
    f2l.estimate.frames), one exposure per photo. Where a photo's heading is unknown the session is
    not merged: each photo's faces share a light, and every row says why. One row per face."""
    photos = list(dict.fromkeys(r.source_path for r in records))
    unknown = [p for p in photos if any(_yaw(r) is None for r in records if r.source_path == p)]
    if len(photos) > 1 and unknown:
        note = (f"not merged across the session's {len(photos)} photos: the camera's heading is unknown for "
                f"{', '.join(Path(p).name for p in unknown[:3])}{' …' if len(unknown) > 3 else ''} "
                f"(record meta {YAW_KEY!r}, from session.toml [[shots]] yaw_deg)")
        rows = []
        for p in photos:
            rows += [_alone(r, r["group_id"], r["group_size"], note)
                     for r in estimate_group([r for r in records if r.source_path == p], model_name, out_dir, cfg)]
        order = {r.face_id: i for i, r in enumerate(records)}
        return sorted(rows, key=lambda row: order.get(row["face_id"], 0))
    key = (records[0].meta or {}).get("joint_group") or (records[0].meta or {}).get("session") or photos[0]
    return estimate_group(records, model_name, out_dir, cfg, mode="session", gid=group_id_of(str(key)))


def _yaw(record) -> float | None:
    value = (record.meta or {}).get(YAW_KEY) if isinstance(getattr(record, "meta", None), dict) else None
    return float(value) if isinstance(value, (int, float)) and np.isfinite(value) else None


def estimate_group(records: list, model_name: str, out_dir: str, cfg: EstimatorConfig, mode: str = "photo",
                   gid: str | None = None) -> list[dict]:
    """Estimate the faces of one photo (``records``; ``mode`` "session": of one session, turned
    into the first photo's frame, see :func:`estimate_session`) with one light; one row per face,
    in order. Never raises for a bad face or group (status and message in the rows)."""
    gid = gid or group_id_of(records[0].source_path)
    if len(records) == 1:
        return [_alone(estimate_record(records[0], model_name, out_dir, cfg), gid, 1)]
    torch_threads(cfg.threads)
    t0 = time.perf_counter()
    rows = [_base_row({"face_id": r.face_id, "source_path": r.source_path, "grid_height": r.grid_height,
                       "grid_width": r.grid_width}, model_name) for r in records]
    for row in rows:
        row.update(group_id=gid, group_size=len(records))
    usable = []
    for i, r in enumerate(records):
        problem = declared_size_problem(r.num_pixels, r.grid_height, r.grid_width, min_pixels=1)
        if problem is not None:
            rows[i].update(status="bad_record", message=f"{r.face_id}: {problem}")
        elif (r.grid_height, r.grid_width) != (records[0].grid_height, records[0].grid_width):
            rows[i] = _alone(estimate_record(r, model_name, out_dir, cfg), gid, len(records),
                             "estimated alone: its grid differs from the group's")
        else:
            usable.append(i)
    if len(usable) <= 1:
        for i in usable:
            rows[i] = _alone(estimate_record(records[i], model_name, out_dir, cfg), gid, len(records))
        return rows
    try:
        grid = LatLongGrid(records[0].grid_height, records[0].grid_width)
        model = _get_model(model_name, grid)
    except Exception as exc:  # noqa: BLE001 - one failure never stops the batch
        for i in usable:
            rows[i].update(status="error", message=f"{records[i].face_id}: {type(exc).__name__}: {exc}")
        return rows
    run_cfg, note = _with_capture_prior(records[usable[0]], model, cfg)
    group = [records[i] for i in usable]
    observations = [FaceObservation(normals=r.normals, observed_rgb=r.observed_rgb, mask=r.mask,
                                    visibility_bits=r.visibility_bits, grid=grid, face_id=r.face_id,
                                    points=getattr(r, "points", None)) for r in group]
    exposure = None
    if mode == "session":  # every face in the first photo's camera frame, an exposure per photo
        yaw0 = _yaw(group[0]) or 0.0
        observations = [turn_observation(o, (_yaw(r) or 0.0) - yaw0) for o, r in zip(observations, group)]
        exposure = [r.source_path for r in group]
        frame = f"in the camera frame of {Path(group[0].source_path).name}"
        note = "; ".join(m for m in (note, frame) if m)
    try:
        joint = estimate_joint(observations, model, run_cfg, exposure_group=exposure,
                               pixel_rc=[r.pixel_rc for r in group])
    except JointUnsupported as exc:
        for i in usable:
            rows[i] = _alone(estimate_record(records[i], model_name, out_dir, cfg), gid, len(records),
                             f"estimated alone: {exc}")
        return rows
    except EstimationError as exc:
        for i in usable:
            rows[i].update(status="bad_face", message=f"{records[i].face_id} (group {gid}): {exc}",
                           model_version=str(model.version), config_hash=joint_hash(model_name, model.version, cfg, mode))
        return rows
    scale, scale_source = record_absolute_scale(records[usable[0]])
    used_ids = [s.face_id for s in joint.faces if s.used]
    group_row = dict(rows[usable[0]])
    try:
        write_result(group_row, joint.result, scale, scale_source, model_name, out_dir, f"group-{gid}",
                     ",".join(used_ids), "")
    except Exception as exc:  # noqa: BLE001
        for i in usable:
            rows[i].update(status="error", message=f"{records[i].face_id} (group {gid}): {type(exc).__name__}: {exc}")
        return rows
    elapsed = time.perf_counter() - t0
    jhash = joint_hash(model_name, model.version, cfg, mode)
    for i, share in zip(usable, joint.faces):
        row = rows[i]
        row.update(model_version=str(model.version), config_hash=jhash, group_used=bool(share.used),
                   agreement=share.agreement, face_weight=float(share.weight) if share.used else 0.0,
                   exposure_gain=float(share.gain) if share.used else None)
        if share.used:
            for key in ("params", "param_names", "sun_direction", "loss", "iterations", "converged", "probe_path",
                        "preview_path", "timings_json", "absolute_scale_cd_m2", "absolute_scale_source", "ground_albedo",
                        *UNCERTAINTY_DEFAULTS):  # the group's sun cones
                row[key] = group_row[key]
            row.update(status="ok", albedo=[float(v) for v in share.albedo],
                       ground_albedo=None if share.ground_albedo is None else float(share.ground_albedo),
                       message="; ".join(m for m in (note, f"one light for {len(used_ids)} of {len(records)} faces "
                                                          f"(group {gid})") if m),
                       runtime_s=elapsed / len(usable))
        elif share.reason.startswith("bad_face"):
            row.update(status="bad_face", message=f"{records[i].face_id}: {share.reason[len('bad_face: '):]}")
        else:  # left out of the group: its own light
            own = estimate_in_memory(records[i], model_name, cfg)
            if own.result is None:
                row.update(status=own.status, message=f"{share.reason}; {own.message}")
                continue
            try:
                write_result(row, own.result, own.scale, own.scale_source, model_name, out_dir,
                             _safe_name(records[i].face_id), records[i].face_id,
                             f"{share.reason}; this row is the face's own estimate")
                row["runtime_s"] = own.result.runtime_s
            except Exception as exc:  # noqa: BLE001
                row.update(status="error", message=f"{records[i].face_id}: {type(exc).__name__}: {exc}")
    return rows


def _alone(row: dict, gid: str, size: int, note: str = "") -> dict:
    """A face estimated by itself, with its group's columns (and a note on why)."""
    row.update(group_id=gid, group_size=size)
    if note:
        row["message"] = "; ".join(m for m in (row["message"], note) if m)
    return row


def _with_capture_prior(record, model, cfg: EstimatorConfig) -> tuple[EstimatorConfig, str]:
    """The config with the sun-elevation prior of the photo's capture time and place, as a single
    face gets it (f2l.estimate.record.estimate_in_memory); the faces of one photo share it."""
    if not (cfg.sun_prior_from_capture and isinstance(model, SunAngles)):
        return cfg, ""
    prior, note = capture_sun_prior(record, cfg.sun_prior_sigma_rad)
    return (cfg if prior is None else dataclasses.replace(cfg, sun_elevation_prior=prior)), note
