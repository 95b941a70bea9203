"""Bulk estimation over face-record shards: ``f2l estimate``.

Streams records (bounded memory: at most ``2 * workers`` groups in flight), estimates each with
every requested model in a worker process (``executor="local"``, :func:`f2l.io.executor.run_local`)
or on a Ray cluster (``executor="ray"``, :mod:`f2l.estimate.ray_executor`), writes the probe (float32 EXR)
and a tone-mapped PNG preview per face and model, and one row per (face, model) to
``estimates.parquet``. A bad record or a failed estimate becomes a row with a status and a
message (:mod:`f2l.estimate.bad_rows`); the rest go on. Progress goes to a callback
(:mod:`f2l.io.progress`), never to the terminal. Runs resume: pairs already estimated with the same configuration are
skipped, and a killed run keeps what it finished (:mod:`f2l.estimate.resume`).
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import asdict
from pathlib import Path

from f2l import __version__
from f2l.estimate.bad_rows import DUPLICATE_STATUS, bad_row as _bad_row
from f2l.estimate.estimator import EstimatorConfig
from f2l.estimate.group_record import (JOINT_MODES, estimate_alone, estimate_group, estimate_session, group_key,
                                       joint_hash)
from f2l.estimate.record import (_base_row, _get_model, _safe_name, capture_sun_prior,  # noqa: F401
                                 config_hash, estimate_record, torch_threads)
from f2l.io.executor import check_executor, run_local
from f2l.io.progress import Progress, ProgressCallback
from f2l.io.tables import ESTIMATE_RUN_FILE as RUN_FILE, ESTIMATES_FILE  # noqa: F401 (named in f2l.io: evaluate reads them)


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
    progress: ProgressCallback | None = None,
    config: EstimatorConfig | None = None,
    sun_prior: bool = True,
    executor: str = "local",
    ray_address: str | None = None,
    rows_per_part: int = 64,
    skin_gloss: float | None = None,
    skin_reflection: float | None = None,
    joint: str = "photo",
    settings: dict | None = None,
) -> dict:
    """Estimate every record of ``shards`` with each of ``models``; returns a summary dict.
    ``workers`` None: :func:`default_workers`. ``config`` None: EstimatorConfig with ``threads``,
    ``max_pixels``, ``max_iter`` and ``sun_prior`` (which are not read with a ``config``). Explicit
    settings apply to either: ``skin_gloss`` and ``skin_reflection`` when not None, and ``settings``
    (``{field: value}`` of EstimatorConfig, e.g. from ``f2l estimate --set``; an unknown field is a
    ValueError). ``progress``: a callback told of each estimate (:mod:`f2l.io.progress`). ``joint`` "photo": the faces of one photo (records
    in a row with the same ``source_path``) share one light (f2l.estimate.group_record);
    "session": the faces of one session (records in a row with the same ``meta["session"]``),
    turned into one frame by their cameras' headings; "none": every face alone. The Ray executor estimates faces alone."""
    from f2l.estimate import resume
    from f2l.io.shards import BadRecord, count_records, iter_records, shard_files
    from f2l.io.record_limits import declared_size_problem
    from f2l.models.registry import model_class

    check_executor(executor)
    if joint not in JOINT_MODES:
        raise ValueError(f"joint must be one of {', '.join(JOINT_MODES)}, got {joint!r}")
    if executor == "ray":
        joint = "none"
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    workers = default_workers(threads) if workers is None else max(1, int(workers))
    cfg = config or EstimatorConfig(threads=threads, max_pixels=max_pixels, max_iter=max_iter,
                                    sun_prior_from_capture=sun_prior)
    explicit = {k: float(v) for k, v in (("skin_gloss", skin_gloss), ("skin_reflection", skin_reflection))
                if v is not None}
    explicit.update(settings or {})
    unknown = sorted(set(explicit) - {f.name for f in dataclasses.fields(EstimatorConfig)})
    if unknown:
        raise ValueError(f"unknown estimator setting(s) {', '.join(unknown)}")
    if explicit:
        cfg = dataclasses.replace(cfg, **explicit)
    hashes, joint_hashes = {}, {}
    for name in models:  # fail fast, with the registry's message, on an unknown model
        hashes[name] = config_hash(name, model_class(name).version, cfg)
        joint_hashes[name] = joint_hash(name, model_class(name).version, cfg, joint)
    shard_paths = [str(Path(s).resolve()) for s in shards]
    run_info = {"f2l_version": __version__, "shards": shard_paths, "models": models,
                "config": asdict(cfg), "config_hashes": hashes, "executor": executor, "joint": joint}
    _write_json_atomic(out_dir / RUN_FILE, run_info)
    old_rows = resume.previous_rows(out_dir)
    done = resume.done_keys(old_rows, hashes) | resume.done_keys(old_rows, joint_hashes)

    try:
        total_records = sum(count_records(s) for s in shards)
    except Exception:  # noqa: BLE001 - counting is only for the progress bar
        total_records = None
    n_tasks = None if total_records is None else total_records * len(models)

    counts = {"ok": 0, "failed": 0, "skipped": 0}
    t_start = time.perf_counter()
    parts = resume.PartWriter(out_dir, rows_per_part)
    bar = Progress(progress, "estimate", "estimate", n_tasks)

    def handle(row: dict) -> None:
        parts.append(row)
        counts["ok" if row["status"] == "ok" else "failed"] += 1
        if row["status"] != "ok":
            bar.note(f"[{row['status']}] {row['message']}")
        bar.advance(1)

    first_in: dict[str, str] = {}  # face_id -> the shard file it was first read from

    def grouped():
        """(records of one photo, or one BadRecord, model) still to do: with ``joint`` "photo" the
        good records in a row with the same source_path form a group; a group is done when all
        its faces are."""
        group: list = []

        def flush():
            for name in models:
                if all((r.face_id, name) in done for r in group):
                    counts["skipped"] += len(group)
                    bar.advance(len(group))
                    continue
                yield group, name

        for rec, _ in _records():
            if isinstance(rec, BadRecord):
                for name in models:
                    if not rec.reason.startswith("duplicate face_id") and (rec.face_id, name) in done:
                        counts["skipped"] += 1
                        bar.advance(1)
                        continue
                    yield rec, name
                continue
            if group and group_key(rec, joint) != group_key(group[0], joint):
                yield from flush()
                group = []
            group.append(rec)
        if group:
            yield from flush()

    def _records():
        """Every (record or BadRecord, model) once per record (the first model's pair stands
        for the record: :func:`grouped` asks about every model itself)."""
        for rec, name in tasks(skip_done=False):
            if name == models[0]:
                yield rec, name

    def tasks(skip_done: bool = True):
        """(record or BadRecord, model) pairs still to do; done ones are counted and skipped. A
        face_id read before (this or an earlier shard, good or bad) becomes a duplicate BadRecord:
        only the first is estimated, so no probe of it is overwritten, and a run writes one row
        per (face_id, model) besides its duplicates."""
        for shard in shards:
            for path in shard_files(shard):
                for rec in iter_records(path):
                    if not isinstance(rec, BadRecord):
                        empty = declared_size_problem(rec.num_pixels, rec.grid_height,
                                                      rec.grid_width, min_pixels=1)
                        if empty is not None:  # a shard may store it; there is nothing to fit
                            rec = BadRecord(str(path), rec.face_id, empty)
                    if rec.face_id is not None and rec.face_id in first_in:  # one row per key a run
                        also = f"; {rec.reason}" if isinstance(rec, BadRecord) else ""
                        rec = BadRecord(str(path), rec.face_id,
                                        f"duplicate face_id (first in {first_in[rec.face_id]}){also}")
                    elif rec.face_id is not None:
                        first_in[rec.face_id] = str(path)
                    for name in models:
                        if isinstance(rec, BadRecord) and rec.reason.startswith("duplicate face_id"):
                            yield rec, name  # never done: the first one's row holds the key
                            continue
                        if skip_done and (rec.face_id, name) in done:
                            counts["skipped"] += 1
                            bar.advance(1)
                            continue
                        yield rec, name

    work = {"photo": estimate_group, "session": estimate_session, "none": estimate_alone}[joint]

    def group_tasks():
        """(group, model, out, cfg) for each group to estimate; a BadRecord's rows are written
        as the stream reaches it (between results, as the executor asks for tasks)."""
        for rec, name in grouped():
            if isinstance(rec, BadRecord):
                handle(_bad_row(rec, name))
                continue
            yield rec, name, str(out_dir), cfg

    if executor == "ray":
        from f2l.estimate.ray_executor import ray_estimate_rows

        for row in ray_estimate_rows(shards, models, str(out_dir), cfg, done,
                                     address=ray_address, workers=workers):
            handle(row)
    else:
        if workers <= 1:
            torch_threads(threads)
        for rows in run_local(work, group_tasks(), workers, initializer=_init_worker, initargs=(threads,)):
            for row in rows:
                handle(row)
    parts.flush()
    resume.finalise(out_dir, [], _merged_rows(old_rows, parts.rows))
    elapsed = time.perf_counter() - t_start
    total = counts["ok"] + counts["failed"]
    return {
        "out": str(out_dir),
        "estimates": str(out_dir / ESTIMATES_FILE),
        "models": models,
        "executor": executor,
        "joint": joint,
        "workers": workers,
        "total": total,
        "ok": counts["ok"],
        "failed": counts["failed"],
        "skipped_done": counts["skipped"],
        "elapsed_s": round(elapsed, 3),
        "faces_per_minute": round(60.0 * total / elapsed, 2) if elapsed > 0 and total else None,
    }


def _merged_rows(old_rows: list[dict], new_rows: list[dict]) -> list[dict]:
    """The finished table's rows: the old rows not redone (later ones win) and the new rows.

    A duplicate face_id's row shares its (face_id, model) key with the first one's, so the key
    alone cannot merge them: old duplicate rows are dropped (every run finds its duplicates
    again), and only the new rows that are not duplicates redo an old row."""
    redone = {(r["face_id"], r["model"]) for r in new_rows if r["status"] != DUPLICATE_STATUS}
    keep: dict[tuple[str, str], dict] = {}
    for r in old_rows:
        key = (r["face_id"], r["model"])
        if key not in redone and r["status"] != DUPLICATE_STATUS:
            keep[key] = r
    # the first one before its duplicates: finalise's sort is stable
    firsts = [r for r in new_rows if r["status"] != DUPLICATE_STATUS]
    return list(keep.values()) + firsts + [r for r in new_rows if r["status"] == DUPLICATE_STATUS]


def _write_json_atomic(path: Path, obj) -> None:
    from f2l.io.atomic import write_text_atomic

    write_text_atomic(path, json.dumps(obj, indent=2, sort_keys=True))
