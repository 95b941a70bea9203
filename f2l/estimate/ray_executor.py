"""``f2l estimate --executor ray``: the same estimates on a Ray cluster (optional extra ``ray``).

Ray Data reads the face-record shards (``ray.data.read_parquet``: one row per record), and
``map_batches`` runs a stateful estimator per worker (:class:`RecordEstimator`: torch threads
set once, models loaded once per grid and reused) that turns each record into one
``estimates`` row per model, exactly as the local executor does
(:func:`f2l.estimate.runner.estimate_record`). The driver streams the result batches into the
same resumable output (:mod:`f2l.estimate.resume`), so memory stays bounded by Ray's streaming
executor and a rerun skips what is done. Probes and previews are written by the workers into
the output directory, which must therefore be shared with them (a local cluster, or a shared
file system).

``address``: an existing cluster (``ray://...`` or ``host:port``); None starts a local one with
``workers`` CPUs for this run and shuts it down afterwards (:func:`f2l.io.executor.ray_session`).
A record that cannot be read is the same row as the local executor's (:func:`f2l.estimate.bad_rows.bad_row`).
"""

from __future__ import annotations

from collections.abc import Iterator

import pyarrow as pa

from f2l.estimate.bad_rows import bad_row
from f2l.io.executor import ExecutorUnavailable, ray_session  # noqa: F401 (ExecutorUnavailable: named here before)
from f2l.io.shards import BadRecord


class RecordEstimator:
    """Per-worker state for ``map_batches``: estimates every (record, model) of a batch."""

    def __init__(self, models: list[str], out_dir: str, cfg, done: set, threads: int) -> None:
        from f2l.estimate.record import torch_threads

        torch_threads(threads)
        self.models, self.out_dir, self.cfg, self.done = models, out_dir, cfg, done

    def __call__(self, batch: pa.Table) -> pa.Table:
        from f2l.estimate.record import estimate_record
        from f2l.io.shards import FaceRecord
        from f2l.io.tables import rows_to_table, table_row

        rows = []
        for i in range(batch.num_rows):
            raw = table_row(batch, i)
            shard = raw.pop("path", None)  # read_parquet(include_paths=True): the shard file
            try:
                rec = FaceRecord.from_row(raw)
                rec.validate()
            except Exception as exc:  # noqa: BLE001 - a bad record becomes rows, not a crash
                bad = BadRecord(str(shard or raw.get("source_path") or ""), raw.get("face_id"), str(exc))
                rows.extend(bad_row(bad, name) for name in self.models)
                continue
            for name in self.models:
                if (rec.face_id, name) not in self.done:
                    rows.append(estimate_record(rec, name, self.out_dir, self.cfg))
        return rows_to_table(rows, "estimates")


def ray_estimate_rows(shards, models: list[str], out_dir: str, cfg, done: set, *,
                      address: str | None = None, workers: int = 2) -> Iterator[dict]:
    """Estimate rows (dicts of the ``estimates`` schema) computed on Ray, as they arrive."""
    from f2l.io.shards import shard_files

    files = [str(p) for p in shard_files(shards)]
    with ray_session(address, workers) as ray:
        ctx = ray.data.DataContext.get_current()
        ctx.enable_progress_bars = False
        ds = ray.data.read_parquet(files, override_num_blocks=max(len(files), int(workers)), include_paths=True)
        threads = max(1, int(cfg.threads))
        # each estimator actor reserves half a CPU slot: ``workers`` actors then leave room for
        # Ray Data's listing and read tasks (1 CPU each), which would otherwise wait forever for
        # a slot the actors hold (the pipeline deadlocks on a cluster of ``workers`` CPUs)
        out = ds.map_batches(RecordEstimator, batch_format="pyarrow", batch_size=1,
                             fn_constructor_args=(models, out_dir, cfg, done, threads),
                             compute=ray.data.ActorPoolStrategy(size=max(1, int(workers))),
                             num_cpus=0.5)
        for batch in out.iter_batches(batch_format="pyarrow", batch_size=None):
            yield from batch.to_pylist()
