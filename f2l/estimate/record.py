"""One (face record, model) estimate as an ``estimates`` row: the unit of work of ``f2l estimate``,
shared by the local process pool (:mod:`f2l.estimate.runner`) and Ray (:mod:`f2l.estimate.ray_executor`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
from dataclasses import asdict
from pathlib import Path
from typing import NamedTuple

import numpy as np

from f2l import __version__
from f2l.estimate.estimator import EstimationError, EstimatorConfig, FaceObservation, estimate
from f2l.models.capabilities import SunAngles, declared

_MODEL_CACHE: dict = {}
# the joint estimate's columns of a face estimated alone (f2l.estimate.group_record fills them)
GROUP_DEFAULTS = {"group_id": "", "group_size": 1, "group_used": None, "agreement": None, "face_weight": None,
                  "exposure_gain": None}
# the sun's uncertainty (f2l.estimate.uncertainty): null without a compact-sun estimate
UNCERTAINTY_DEFAULTS = {"sun_cone68_deg": None, "sun_cone90_deg": None, "predicted_mae_s": None}


def config_hash(model_name: str, model_version: str, cfg: EstimatorConfig, joint: dict | None = None) -> str:
    """The settings an estimate depends on, hashed: model name and version, f2l's version, the
    estimator's configuration and, for faces estimated together, the joint estimate's settings."""
    settings = {"model": model_name, "version": model_version, "f2l": __version__, "cfg": asdict(cfg)}
    if joint:
        settings["joint"] = joint
    payload = json.dumps(settings, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def _get_model(name: str, grid):
    from f2l.models.registry import load_model

    key = (name, grid.height, grid.width)
    if key not in _MODEL_CACHE:
        _MODEL_CACHE[key] = load_model(name, grid)
    return _MODEL_CACHE[key]


def _base_row(record_like: dict, model: str) -> dict:
    return {
        "face_id": record_like.get("face_id") or "",
        "source_path": record_like.get("source_path") or "",
        "model": model,
        "model_version": "",
        "params": [],
        "param_names": [],
        "albedo": [],
        "ground_albedo": None,
        "sun_direction": None,
        "loss": None,
        "iterations": 0,
        "converged": False,
        "status": "error",
        "message": "",
        "runtime_s": 0.0,
        "probe_path": None,
        "preview_path": None,
        "grid_height": int(record_like.get("grid_height") or 0),
        "grid_width": int(record_like.get("grid_width") or 0),
        "absolute_scale_cd_m2": None,
        "absolute_scale_source": "",
        "config_hash": "",
        "timings_json": "{}",
        **GROUP_DEFAULTS,
        **UNCERTAINTY_DEFAULTS,
    }


class InMemoryEstimate(NamedTuple):
    """One face's estimate before anything is written: ``result`` (None unless ``status`` is
    "ok"), the absolute scale and its source, the status and message, the model (None when it
    could not be built)."""

    result: object
    scale: float | None
    scale_source: str
    status: str
    message: str
    model: object


def estimate_in_memory(record, model_name: str, cfg: EstimatorConfig) -> InMemoryEstimate:
    """Estimate one face with one model in memory; never raises for a bad face (status
    ``bad_record``, ``bad_face`` or ``error`` with the message)."""
    from f2l.io.record_limits import declared_size_problem
    from f2l.lighting.grid import LatLongGrid

    torch_threads(cfg.threads)
    # the record's own sizes before anything is allocated from them (the model's grid, transport):
    # a record beyond them is refused as the record's fault, not the model's
    problem = declared_size_problem(record.num_pixels, record.grid_height, record.grid_width,
                                    min_pixels=1)
    if problem is not None:
        return InMemoryEstimate(None, None, "", "bad_record", f"{record.face_id}: {problem}", None)
    model = None
    try:
        grid = LatLongGrid(record.grid_height, record.grid_width)
        model = _get_model(model_name, grid)
        obs = FaceObservation(
            normals=record.normals, observed_rgb=record.observed_rgb, mask=record.mask,
            visibility_bits=record.visibility_bits, grid=grid, face_id=record.face_id,
            points=getattr(record, "points", None),
        )
        run_cfg, prior_note = cfg, ""
        if cfg.sun_prior_from_capture and isinstance(model, SunAngles):  # capability sun-angles
            prior, prior_note = capture_sun_prior(record, cfg.sun_prior_sigma_rad)
            if prior is not None:
                run_cfg = dataclasses.replace(cfg, sun_elevation_prior=prior)
        result = estimate(obs, model, run_cfg)
        scale, scale_source = record_absolute_scale(record)
        return InMemoryEstimate(result, scale, scale_source, "ok", prior_note, model)
    except EstimationError as exc:
        return InMemoryEstimate(None, None, "", "bad_face", f"{record.face_id}: {exc}", model)
    except Exception as exc:  # noqa: BLE001 - one failure never stops the batch
        who = "" if model is None else (f" (model {model_name!r}, {type(model).__module__}:{type(model).__qualname__}, "
                                        f"capabilities: {', '.join(declared(model)) or 'none'})")
        return InMemoryEstimate(None, None, "", "error", f"{record.face_id}{who}: {type(exc).__name__}: {exc}", model)


def estimate_record(record, model_name: str, out_dir: str, cfg: EstimatorConfig) -> dict:
    """Estimate one face with one model and write its probe and preview; never raises for a bad
    face (status in the row)."""
    row = _base_row({"face_id": record.face_id, "source_path": record.source_path,
                     "grid_height": record.grid_height, "grid_width": record.grid_width}, model_name)
    t0 = time.perf_counter()
    done = estimate_in_memory(record, model_name, cfg)
    if done.model is not None:
        row["model_version"] = str(done.model.version)
        row["config_hash"] = config_hash(model_name, done.model.version, cfg)
    if done.result is None:
        row.update(status=done.status, message=done.message)
        if done.status != "bad_record":
            row["runtime_s"] = time.perf_counter() - t0
        return row
    try:
        write_result(row, done.result, done.scale, done.scale_source, model_name, out_dir, _safe_name(record.face_id),
                     record.face_id, done.message)
    except Exception as exc:  # noqa: BLE001 - one failure never stops the batch
        row.update(status="error", message=f"{record.face_id}: {type(exc).__name__}: {exc}")
    row["runtime_s"] = time.perf_counter() - t0
    return row


def write_result(row: dict, result, scale: float | None, scale_source: str, model_name: str, out_dir,
                 name: str, face_ids: str, message: str) -> None:
    """Write ``result``'s probe (``probes/<model>/<name>.exr``, in cd/m² when ``scale`` is known)
    and its preview, and fill ``row`` with the estimate (status ok, ``message``)."""
    from f2l.io.exr import write_exr
    from f2l.io.preview import save_png, tonemap

    probe_rel = f"probes/{model_name}/{name}.exr"
    preview_rel = f"previews/{model_name}/{name}.png"
    (Path(out_dir) / probe_rel).parent.mkdir(parents=True, exist_ok=True)
    (Path(out_dir) / preview_rel).parent.mkdir(parents=True, exist_ok=True)
    probe = result.probe if scale is None else (result.probe * scale).astype(np.float32)
    uncertainty = uncertainty_columns(result)
    write_exr(Path(out_dir) / probe_rel, probe,
              metadata={"f2l_model": model_name, "f2l_face_id": face_ids, "f2l_convention": "latlong,+Y up,centre=-Z",
                        "f2l_units": "relative: the photo's linear values (1 = full scale)" if scale is None
                        else "cd/m2 (Rec.709 Y of the RGB is the luminance)",
                        "f2l_absolute_scale_cd_m2": "" if scale is None else repr(float(scale)),
                        "f2l_absolute_scale_source": scale_source,
                        **{f"f2l_{k}": "" if v is None else repr(v) for k, v in uncertainty.items()},
                        **spread_header(result)})
    save_png(Path(out_dir) / preview_rel, tonemap(probe))
    row.update(
        params=[float(v) for v in result.params],
        param_names=list(result.param_names),
        albedo=[float(v) for v in result.albedo],
        ground_albedo=result.ground_albedo,
        sun_direction=None if result.sun_direction is None else [float(v) for v in result.sun_direction],
        loss=float(result.loss),
        iterations=int(result.iterations),
        converged=bool(result.converged),
        status="ok",
        message=message,
        probe_path=probe_rel,
        preview_path=preview_rel,
        timings_json=json.dumps({k: round(float(v), 6) for k, v in result.timings.items()}),
        absolute_scale_cd_m2=None if scale is None else float(scale),
        absolute_scale_source=scale_source,
        **uncertainty,
    )


def uncertainty_columns(result) -> dict:
    """The row's sun-uncertainty columns (UNCERTAINTY_DEFAULTS) from ``result.sun_uncertainty``
    (f2l.estimate.uncertainty.SunUncertainty; nulls without one)."""
    u = getattr(result, "sun_uncertainty", None)
    if u is None:
        return dict(UNCERTAINTY_DEFAULTS)
    return {"sun_cone68_deg": float(u.cone68_deg), "sun_cone90_deg": float(u.cone90_deg),
            "predicted_mae_s": float(u.predicted_mae_s)}


def spread_header(result) -> dict:
    """EXR header keys of a probe whose sun is spread over its direction posterior
    (f2l.estimate.sun_spread): the written lobe's kappa; none for the sharp sun as fitted."""
    kappa = getattr(result, "sun_spread_kappa", None)
    return {} if kappa is None else {"f2l_sun_lobe": "spread over the sun direction's posterior",
                                     "f2l_sun_spread_kappa": repr(float(kappa))}


def record_absolute_scale(record) -> tuple[float | None, str]:
    """(cd/m² per unit of the record's linear values, source) from its photo's EXIF exposure
    (:func:`f2l.io.exposure.absolute_scale`); None where the EXIF lacks it or a colour correction
    changed the photo's exposure scale."""
    from f2l.io.exposure import absolute_scale

    meta = record.meta if isinstance(getattr(record, "meta", None), dict) else {}
    colour = meta.get("colour") if isinstance(meta.get("colour"), dict) else {}
    if colour.get("keep_exposure") is False:
        return None, "relative (no absolute scale: the colour correction rescaled the exposure)"
    exif = meta.get("exif")
    if not isinstance(exif, dict):
        return None, "relative (no absolute scale: the record holds no EXIF)"
    return absolute_scale(exif)


def capture_sun_prior(record, sigma_rad: float) -> tuple[tuple[float, float] | None, str]:
    """(elevation_rad, sigma_rad) of the sun when the record says when and where it was taken
    (``meta["capture"]``, else the EXIF of its source photo; f2l.io.capture), and a note.

    The camera's heading is unknown, so only the elevation is used; the grid's +Y is taken as
    the world's up. A sun below the horizon at capture time gives no prior (the note says so).
    """
    from f2l.io.capture import capture_from_meta, capture_status, solar_position

    try:
        info = capture_from_meta(record.meta or {})
    except ValueError as exc:
        return None, f"sun prior: bad meta capture ({exc})"
    source = "meta"
    if info is None:
        path = Path(record.source_path or "")
        if not path.is_file():
            return None, ""
        info, status = capture_status(path)
        if info is None:
            return None, f"sun prior: none ({status})"
        source = info.source
    elevation, _ = solar_position(info)
    if elevation <= 0.0:
        return None, f"sun prior: none (sun {math.degrees(elevation):.1f} deg, below the horizon at capture)"
    return (elevation, sigma_rad), f"sun prior: elevation {math.degrees(elevation):.1f} deg from {source}"


def torch_threads(n: int) -> None:
    import torch

    if torch.get_num_threads() != n:
        torch.set_num_threads(max(1, n))


def _safe_name(face_id: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in face_id) or "face"
