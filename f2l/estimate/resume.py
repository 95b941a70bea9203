"""Resumable estimate output: finished rows are published in small parts while a run goes on,
and a rerun skips what is already done.

Layout of an ``f2l estimate --out OUT`` directory:

* ``OUT/estimates.parquet`` — the table of a finished run (schema ``estimates``), rows sorted by
  (face_id, model);
* ``OUT/estimates.parts/part-NNNNNN.parquet`` — rows finished by a run still going (or killed),
  each part published atomically every ``rows_per_part`` rows.

A (face, model) pair is *done* when a row of either file has status ``ok`` or ``bad_face`` (a
deterministic refusal) and the same ``config_hash`` (model name and version, f2l version and
estimator configuration; :func:`f2l.estimate.runner.config_hash`). Done pairs are skipped;
everything else (errors, other configurations) is estimated again. At the end of a run the old
rows not redone, the parts and the new rows are merged into ``estimates.parquet`` (atomic) and
the parts are removed, so a killed run loses at most one part's worth of work.
"""

from __future__ import annotations

import os
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

PARTS_DIR = "estimates.parts"
DONE_STATUSES = ("ok", "bad_face")


def _read_rows(path: Path) -> list[dict]:
    from f2l.io.schema import validate_table

    try:
        table = pq.read_table(path)
        validate_table(table, "estimates", source=str(path))
    except Exception:  # a damaged part, or one of an older schema: its faces are estimated again
        return []
    return table.to_pylist()


def previous_rows(out_dir: Path) -> list[dict]:
    """Rows of the last finished table and of any parts left by an unfinished run."""
    rows = _read_rows(out_dir / "estimates.parquet") if (out_dir / "estimates.parquet").is_file() \
        else []
    parts = out_dir / PARTS_DIR
    if parts.is_dir():
        for p in sorted(parts.glob("part-*.parquet")):
            rows.extend(_read_rows(p))
    return rows


def done_keys(rows: list[dict], hashes: dict[str, str]) -> set[tuple[str, str]]:
    """(face_id, model) pairs finished with the current configuration hash of their model."""
    return {(r["face_id"], r["model"]) for r in rows
            if r["status"] in DONE_STATUSES and r["model"] in hashes
            and r["config_hash"] == hashes[r["model"]]}


class PartWriter:
    """Buffers result rows and publishes them as numbered parts (atomic each)."""

    def __init__(self, out_dir: Path, rows_per_part: int = 64) -> None:
        self.dir = Path(out_dir) / PARTS_DIR
        self.dir.mkdir(parents=True, exist_ok=True)
        existing = [int(p.stem.split("-")[1]) for p in self.dir.glob("part-*.parquet")]
        self.next_index = max(existing, default=-1) + 1
        self.rows_per_part = max(1, int(rows_per_part))
        self.buffer: list[dict] = []
        self.rows: list[dict] = []  # everything this run produced

    def append(self, row: dict) -> None:
        self.buffer.append(row)
        self.rows.append(row)
        if len(self.buffer) >= self.rows_per_part:
            self.flush()

    def flush(self) -> None:
        from f2l.io.tables import rows_to_table, write_table_atomic

        if not self.buffer:
            return
        path = self.dir / f"part-{self.next_index:06d}.parquet"
        write_table_atomic(rows_to_table(self.buffer, "estimates"), path, "estimates")
        self.next_index += 1
        self.buffer = []


def finalise(out_dir: Path, old_rows: list[dict], new_rows: list[dict],
             rows_per_group: int = 1024) -> int:
    """Publish ``estimates.parquet`` = old rows not redone + new rows, sorted; remove the parts.
    Returns the number of rows."""
    from f2l.io.tables import rows_to_table, write_table_atomic

    redone = {(r["face_id"], r["model"]) for r in new_rows}
    keep: dict[tuple[str, str], dict] = {}
    for r in old_rows:  # later rows (parts) win over earlier ones for the same pair
        key = (r["face_id"], r["model"])
        if key not in redone:
            keep[key] = r
    rows = sorted(list(keep.values()) + new_rows, key=lambda r: (r["face_id"], r["model"]))
    table = rows_to_table(rows, "estimates") if rows else None
    if table is None:
        from f2l.io.schema import arrow_schema

        table = pa.Table.from_pylist([], schema=arrow_schema("estimates"))
    write_table_atomic(table, out_dir / "estimates.parquet", "estimates",
                       row_group_size=rows_per_group)
    parts = out_dir / PARTS_DIR
    if parts.is_dir():
        for p in parts.glob("part-*"):  # published parts and torn temporaries of a killed write
            p.unlink()
        try:
            os.rmdir(parts)
        except OSError:
            pass
    return len(rows)
