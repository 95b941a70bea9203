"""Bulk estimation over face-record shards: ``f2l estimate``.

Streams records (bounded memory: at most ``2 * workers`` records in flight), estimates each with
every requested model in a worker process (``executor="local"``, a process pool) or on a Ray
cluster (``executor="ray"``, :mod:`f2l.estimate.ray_executor`), writes the probe (float32 EXR)
and a tone-mapped PNG preview per face and model, and one row per (face, model) to
``estimates.parquet``. A bad record or a failed estimate becomes a row with a status and a
message; the rest go on. Runs resume: pairs already estimated with the same configuration are
skipped, and a killed run keeps what it finished (:mod:`f2l.estimate.resume`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import asdict
from pathlib import Path


from f2l import __version__
from f2l.estimate.estimator import EstimationError, EstimatorConfig, FaceObservation, estimate

ESTIMATES_FILE = "estimates.parquet"
RUN_FILE = "run.json"

_MODEL_CACHE: dict = {}


def config_hash(model_name: str, model_version: str, cfg: EstimatorConfig) -> str:
    payload = json.dumps({"model": model_name, "version": model_version, "f2l": __version__, "cfg": asdict(cfg)}, sort_keys=True)
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
        "config_hash": "",
        "timings_json": "{}",
    }


def estimate_record(record, model_name: str, out_dir: str, cfg: EstimatorConfig) -> dict:
    """Estimate one face with one model; never raises for a bad face (status in the row)."""
    from f2l.io.exr import write_exr
    from f2l.io.preview import save_png, tonemap
    from f2l.lighting.grid import LatLongGrid

    torch_threads(cfg.threads)
    row = _base_row({"face_id": record.face_id, "source_path": record.source_path,
                     "grid_height": record.grid_height, "grid_width": record.grid_width}, model_name)
    t0 = time.perf_counter()
    try:
        grid = LatLongGrid(record.grid_height, record.grid_width)
        model = _get_model(model_name, grid)
        row["model_version"] = str(model.version)
        row["config_hash"] = config_hash(model_name, model.version, cfg)
        obs = FaceObservation(
            normals=record.normals, observed_rgb=record.observed_rgb, mask=record.mask,
            visibility_bits=record.visibility_bits, grid=grid, face_id=record.face_id,
        )
        run_cfg, prior_note = cfg, ""
        if cfg.sun_prior_from_capture and hasattr(model, "sun_layout"):
            prior, prior_note = capture_sun_prior(record, cfg.sun_prior_sigma_rad)
            if prior is not None:
                run_cfg = dataclasses.replace(cfg, sun_elevation_prior=prior)
        result = estimate(obs, model, run_cfg)
        safe_id = _safe_name(record.face_id)
        probe_rel = f"probes/{model_name}/{safe_id}.exr"
        preview_rel = f"previews/{model_name}/{safe_id}.png"
        (Path(out_dir) / probe_rel).parent.mkdir(parents=True, exist_ok=True)
        (Path(out_dir) / preview_rel).parent.mkdir(parents=True, exist_ok=True)
        write_exr(Path(out_dir) / probe_rel, result.probe,
                  metadata={"f2l_model": model_name, "f2l_face_id": record.face_id, "f2l_convention": "latlong,+Y up,centre=-Z"})
        save_png(Path(out_dir) / preview_rel, tonemap(result.probe))
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
            message=prior_note,
            probe_path=probe_rel,
            preview_path=preview_rel,
            timings_json=json.dumps({k: round(float(v), 6) for k, v in result.timings.items()}),
        )
    except EstimationError as exc:
        row.update(status="bad_face", message=f"{record.face_id}: {exc}")
    except Exception as exc:  # noqa: BLE001 - one failure never stops the batch
        row.update(status="error", message=f"{record.face_id}: {type(exc).__name__}: {exc}")
    row["runtime_s"] = time.perf_counter() - t0
    return row


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


def _init_worker(threads: int) -> None:
    os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    torch_threads(threads)


def default_workers(threads: int) -> int:
    """Worker processes that fill the machine: cores // threads (at least 1)."""
    return max(1, (os.cpu_count() or 1) // max(1, int(threads)))


def run_estimates(
    shards: list[Path],
    models: list[str],
    out_dir: Path,
    workers: int | None = None,
    threads: int = 2,
    max_pixels: int | None = None,
    max_iter: int = 18,
    progress: bool = True,
    config: EstimatorConfig | None = None,
    sun_prior: bool = True,
    executor: str = "local",
    ray_address: str | None = None,
    rows_per_part: int = 64,
) -> dict:
    """Estimate every record of ``shards`` with each of ``models``; returns a summary dict.
    ``workers`` None: :func:`default_workers`."""
    from f2l.estimate import resume
    from f2l.io.shards import BadRecord, count_records, iter_records
    from f2l.models.registry import load_model
    from f2l.lighting.grid import LatLongGrid

    if executor not in ("local", "ray"):
        raise ValueError(f"executor must be 'local' or 'ray', got {executor!r}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    workers = default_workers(threads) if workers is None else max(1, int(workers))
    cfg = config or EstimatorConfig(threads=threads, max_pixels=max_pixels, max_iter=max_iter,
                                    sun_prior_from_capture=sun_prior)
    hashes = {}
    for name in models:  # fail fast, with the registry's message, on an unknown model
        hashes[name] = config_hash(name, load_model(name, LatLongGrid(8, 16)).version, cfg)
    shard_paths = [str(Path(s).resolve()) for s in shards]
    run_info = {"f2l_version": __version__, "shards": shard_paths, "models": models,
                "config": asdict(cfg), "config_hashes": hashes, "executor": executor}
    _write_json_atomic(out_dir / RUN_FILE, run_info)
    old_rows = resume.previous_rows(out_dir)
    done = resume.done_keys(old_rows, hashes)

    try:
        total_records = sum(count_records(s) for s in shards)
    except Exception:  # noqa: BLE001 - counting is only for the progress bar
        total_records = None
    n_tasks = None if total_records is None else total_records * len(models)

    counts = {"ok": 0, "failed": 0, "skipped": 0}
    t_start = time.perf_counter()
    parts = resume.PartWriter(out_dir, rows_per_part)
    bar = _progress(n_tasks, progress)

    def handle(row: dict) -> None:
        parts.append(row)
        counts["ok" if row["status"] == "ok" else "failed"] += 1
        if row["status"] != "ok" and progress:
            bar.write(f"[{row['status']}] {row['message']}")
        bar.update(1)

    def tasks():
        """(record or BadRecord, model) pairs still to do; done ones are counted and skipped."""
        for shard in shards:
            for rec in iter_records(shard):
                for name in models:
                    if (rec.face_id, name) in done:
                        counts["skipped"] += 1
                        bar.update(1)
                        continue
                    yield rec, name

    try:
        if executor == "ray":
            from f2l.estimate.ray_executor import ray_estimate_rows

            for row in ray_estimate_rows(shards, models, str(out_dir), cfg, done,
                                         address=ray_address, workers=workers):
                handle(row)
        elif workers <= 1:
            torch_threads(threads)
            for rec, name in tasks():
                handle(_bad_row(rec, name) if isinstance(rec, BadRecord)
                       else estimate_record(rec, name, str(out_dir), cfg))
        else:
            import multiprocessing

            # spawn, not fork: forking a process whose torch/OpenMP threads are running can deadlock
            context = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(max_workers=workers, initializer=_init_worker, initargs=(threads,),
                                     mp_context=context) as pool:
                pending: set[Future] = set()
                for rec, name in tasks():
                    if isinstance(rec, BadRecord):
                        handle(_bad_row(rec, name))
                        continue
                    pending.add(pool.submit(estimate_record, rec, name, str(out_dir), cfg))
                    if len(pending) >= 2 * workers:
                        finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                        for fut in finished:
                            handle(fut.result())
                for fut in pending:
                    handle(fut.result())
        parts.flush()
        resume.finalise(out_dir, old_rows, parts.rows)
    finally:
        bar.close()
    elapsed = time.perf_counter() - t_start
    total = counts["ok"] + counts["failed"]
    return {
        "out": str(out_dir),
        "estimates": str(out_dir / ESTIMATES_FILE),
        "models": models,
        "executor": executor,
        "workers": workers,
        "total": total,
        "ok": counts["ok"],
        "failed": counts["failed"],
        "skipped_done": counts["skipped"],
        "elapsed_s": round(elapsed, 3),
        "faces_per_minute": round(60.0 * total / elapsed, 2) if elapsed > 0 and total else None,
    }


def _bad_row(bad, model: str) -> dict:
    row = _base_row({"face_id": bad.face_id or "", "source_path": bad.source}, model)
    row.update(status="bad_record", message=f"{bad.source}: {bad.reason}")
    return row


def _write_json_atomic(path: Path, obj) -> None:
    from f2l.io.atomic import write_text_atomic

    write_text_atomic(path, json.dumps(obj, indent=2, sort_keys=True))


class _NoBar:
    def update(self, n=1):
        pass

    def write(self, msg):
        pass

    def close(self):
        pass


def _progress(total, enabled: bool):
    if not enabled:
        return _NoBar()
    from tqdm import tqdm

    bar = tqdm(total=total, unit="estimate", dynamic_ncols=True)
    return bar
