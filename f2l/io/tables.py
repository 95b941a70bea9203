"""Schema-validated Parquet tables: rows <-> Arrow, and atomic writers.

Tables follow a JSON Schema from ``schemas/`` (see ``f2l.io.schema``). Writers write to
``<name>.<pid>.tmp``, fsync, then ``os.replace``: a killed run never leaves a half table under
the final name. :class:`ParquetAppender` streams result rows (e.g. ``estimates.parquet``) in row
groups and publishes the file on close.
"""

from __future__ import annotations

import os
from abc import ABC, abstractmethod
from collections.abc import Iterable, Mapping, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from f2l.io.schema import SchemaError, arrow_schema, load_schema, validate_table

__all__ = ["CommitOnSuccess", "ParquetAppender", "rows_to_table", "table_row", "write_table_atomic"]

ESTIMATES_FILE = "estimates.parquet"
"""What ``f2l estimate`` writes in its output folder: one row per face and model."""
ESTIMATE_RUN_FILE = "run.json"
"""Beside it: the run's shards, models and settings (what ``f2l evaluate`` reads back)."""


@lru_cache(maxsize=None)
def _schema(name: str) -> dict:
    """Parsed schema, cached (treat as read-only)."""
    return load_schema(name)


def _schema_of(schema: dict | str) -> dict:
    return _schema(schema) if isinstance(schema, str) else schema



class CommitOnSuccess(ABC):
    """Context-manager protocol for writers: ``close()`` on success, ``abort()`` on an exception."""

    @abstractmethod
    def close(self):
        """Publish what was written."""

    @abstractmethod
    def abort(self) -> None:
        """Discard what was written; published files stay as they were."""

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


# -- rows <-> Arrow --------------------------------------------------------------------------
def _list_column(values: list, typ: pa.ListType) -> pa.Array:
    """A list column from per-row array-likes (numeric lists built from one concatenation)."""
    vtype = typ.value_type
    if any(v is None for v in values) or not (
        pa.types.is_floating(vtype) or pa.types.is_integer(vtype) or pa.types.is_boolean(vtype)
    ):
        return pa.array([v.reshape(-1).tolist() if isinstance(v, np.ndarray) else v
                         for v in values], type=typ)
    flat = [np.asarray(v).reshape(-1) for v in values]
    offsets = np.zeros(len(flat) + 1, dtype=np.int32)
    np.cumsum([f.size for f in flat], out=offsets[1:])
    dtype = vtype.to_pandas_dtype()
    concat = np.concatenate(flat) if flat else np.zeros(0, dtype=dtype)
    if concat.size == 0:
        concat = concat.astype(dtype)
    return pa.ListArray.from_arrays(pa.array(offsets, pa.int32()), pa.array(concat, type=vtype))


def rows_to_table(rows: Sequence[Mapping[str, Any]], schema: dict | str) -> pa.Table:
    """Arrow table (schema column order and metadata) from row dicts; numpy arrays are flattened."""
    schema = _schema_of(schema)
    aschema = arrow_schema(schema)
    names = set(aschema.names)
    for i, row in enumerate(rows):
        extra = set(row) - names
        missing = names - set(row)
        if extra or missing:
            raise SchemaError(f"{schema.get('title', 'table')} row {i}: "
                              + (f"missing columns {sorted(missing)} " if missing else "")
                              + (f"unexpected columns {sorted(extra)}" if extra else ""))
    arrays = []
    for fld in aschema:
        values = [row[fld.name] for row in rows]
        try:
            if pa.types.is_list(fld.type):
                arrays.append(_list_column(values, fld.type))
            elif pa.types.is_binary(fld.type) or pa.types.is_large_binary(fld.type):
                arrays.append(pa.array(
                    [None if v is None else (v.tobytes() if isinstance(v, np.ndarray) else bytes(v))
                     for v in values], type=fld.type))
            else:
                arrays.append(pa.array(values, type=fld.type))
        except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, ValueError) as exc:
            raise SchemaError(f"{schema.get('title', 'table')}: column {fld.name!r} cannot be "
                              f"stored as {fld.type}: {exc}") from None
    return pa.Table.from_arrays(arrays, schema=aschema)


def table_row(table: pa.Table, index: int) -> dict[str, Any]:
    """Row ``index`` as a dict: list columns as numpy arrays (copies), binary as uint8 arrays."""
    row: dict[str, Any] = {}
    for name in table.column_names:
        scalar = table.column(name)[index]
        if not scalar.is_valid:
            row[name] = None
        elif isinstance(scalar, pa.ListScalar):
            vals = scalar.values
            if pa.types.is_string(vals.type) or pa.types.is_large_string(vals.type):
                row[name] = vals.to_pylist()
            else:
                row[name] = np.array(vals.to_numpy(zero_copy_only=False), copy=True)
        elif pa.types.is_binary(scalar.type) or pa.types.is_large_binary(scalar.type):
            row[name] = np.frombuffer(scalar.as_buffer(), dtype=np.uint8).copy()
        else:
            row[name] = scalar.as_py()
    return row


# -- atomic Parquet writing ------------------------------------------------------------------
def _tmp_path(path: Path) -> Path:
    return path.with_name(f"{path.name}.{os.getpid()}.tmp")


def _write_options(schema: dict, compression: str) -> dict:
    props = schema["properties"]
    scalar = [n for n, p in props.items()
              if not (p["x-arrow-type"].startswith("list<") or "binary" in p["x-arrow-type"])]
    return {"compression": compression, "use_dictionary": False, "write_statistics": scalar}


class _AtomicParquet:
    """A ParquetWriter on ``<path>.<pid>.tmp`` that is fsynced and renamed on commit."""

    def __init__(self, path: Path, aschema: pa.Schema, options: dict):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = _tmp_path(self.path)
        self._file = open(self.tmp, "wb")  # noqa: SIM115 - closed in commit/abort
        try:
            self._writer = pq.ParquetWriter(self._file, aschema, **options)
        except BaseException:
            self._file.close()
            self.tmp.unlink(missing_ok=True)
            raise

    def write(self, table: pa.Table) -> None:
        self._writer.write_table(table, row_group_size=max(table.num_rows, 1))

    def commit(self) -> Path:
        self._writer.close()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        try:
            self._writer.close()
        except Exception:  # noqa: BLE001 - best effort on an already failing path
            pass
        self._file.close()
        self.tmp.unlink(missing_ok=True)


def write_table_atomic(table: pa.Table, path: str | os.PathLike, schema: dict | str | None = None,
                       *, row_group_size: int | None = None, compression: str = "zstd") -> Path:
    """Write ``table`` to ``path`` atomically; validate against ``schema`` (name or dict) first."""
    path = Path(path)
    if schema is not None:
        schema = _schema_of(schema)
        validate_table(table, schema, source=str(path))
        aschema = arrow_schema(schema)
        table = table.select(aschema.names).replace_schema_metadata(aschema.metadata)
        options = _write_options(schema, compression)
    else:
        options = {"compression": compression}
    writer = _AtomicParquet(path, table.schema, options)
    try:
        writer._writer.write_table(table, row_group_size=row_group_size)
    except BaseException:
        writer.abort()
        raise
    return writer.commit()


class ParquetAppender(CommitOnSuccess):
    """Append validated rows to a results table in row groups; atomic on :meth:`close`.

    Use as a context manager: on an exception the temporary file is removed and ``path`` is
    left as it was. Rows are validated when appended, so a bad row raises at its source.
    """

    def __init__(self, path: str | os.PathLike, schema: dict | str, *,
                 rows_per_group: int = 1024, compression: str = "zstd"):
        self.path = Path(path)
        self.schema = _schema_of(schema)
        self.rows_per_group = int(rows_per_group)
        self._aschema = arrow_schema(self.schema)
        self._writer = _AtomicParquet(self.path, self._aschema,
                                      _write_options(self.schema, compression))
        self._pending: list[pa.Table] = []
        self._pending_rows = 0
        self.num_rows = 0
        self._closed = False

    def append(self, row: Mapping[str, Any] | Sequence[Mapping[str, Any]]) -> None:
        """Validate one row dict (or a list of them) and buffer it."""
        rows = [row] if isinstance(row, Mapping) else list(row)
        self.append_table(rows_to_table(rows, self.schema))

    def extend(self, rows: Iterable[Mapping[str, Any]]) -> None:
        for row in rows:
            self.append(row)

    def append_table(self, table: pa.Table) -> None:
        """Validate a table of rows and buffer it."""
        if self._closed:
            raise RuntimeError(f"{self.path}: appender is closed")
        validate_table(table, self.schema, source=f"{self.path} (rows from {self.num_rows})")
        table = table.select(self._aschema.names).replace_schema_metadata(self._aschema.metadata)
        self._pending.append(table)
        self._pending_rows += table.num_rows
        self.num_rows += table.num_rows
        if self._pending_rows >= self.rows_per_group:
            self._flush()

    def _flush(self) -> None:
        if not self._pending:
            return
        table = pa.concat_tables(self._pending).combine_chunks()
        self._pending, self._pending_rows = [], 0
        for start in range(0, table.num_rows, self.rows_per_group):
            self._writer.write(table.slice(start, self.rows_per_group))

    def close(self) -> Path:
        """Flush and atomically publish ``path`` (an empty table if nothing was appended)."""
        if self._closed:
            return self.path
        self._flush()
        self._closed = True
        return self._writer.commit()

    def abort(self) -> None:
        """Discard everything appended; ``path`` is untouched."""
        if not self._closed:
            self._closed = True
            self._writer.abort()
