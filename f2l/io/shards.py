"""Face-record shards: Parquet record files plus EXR/PNG side files (schema ``face_record``).

Layout of a shard directory::

    shards/part-00000.parquet   one row group per record (readers stream one record at a time)
    shards/part-00001.parquet   ...
    shards/probes/<face_id>.exr ground-truth probes (float32 lat-long), referenced by gt_probe_path
    shards/photos/<face_id>.png photo previews, referenced by photo_path

Every file is written atomically (``<name>.<pid>.tmp`` then ``os.replace``), every record is
validated against ``schemas/face_record.schema.json`` on write and (by default) on read, and a
reader turns an unreadable file or an invalid record into a :class:`BadRecord` instead of
raising, so one bad file never stops a batch. The generic table machinery (rows <-> Arrow,
atomic Parquet writers, :class:`ParquetAppender` for result tables) lives in ``f2l.io.tables``
and is re-exported here; the side files in :mod:`f2l.io.side_files`, the size limits in
:mod:`f2l.io.record_limits`.

A record from outside is read with bounds, before anything is allocated from what it declares
(:func:`declared_size_problem`): a lighting grid of at most :data:`MAX_GRID_TEXELS` texels
(``$F2L_MAX_GRID_TEXELS``), at most :data:`MAX_RECORD_PIXELS` face pixels
(``$F2L_MAX_RECORD_PIXELS``), array columns of no more values and a row group of no more bytes
(uncompressed; both from the file's footer) than its declared sizes need, and a ``meta_json`` read by
:func:`f2l.io.bounded.load_json` (depth, string length, size, finite numbers). A record beyond
them becomes a :class:`BadRecord` naming the file, the record and the reason.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from f2l.io.bounded import MAX_TEXT_BYTES, InputError, load_json
from f2l.io.schema import SchemaError, arrow_schema, json_dumps_strict, table_errors, validate_table
from f2l.io.tables import (
    CommitOnSuccess,
    ParquetAppender,
    _AtomicParquet,
    _schema,
    _write_options,
    rows_to_table,
    table_row,
    write_table_atomic,
)

__all__ = [
    "FACE_SCHEMA_NAME",
    "FaceRecord",
    "BadRecord",
    "ShardWriter",
    "ParquetAppender",
    "iter_records",
    "count_records",
    "shard_files",
    "write_table_atomic",
    "rows_to_table",
    "table_row",
    "pack_visibility",
    "unpack_visibility",
    "SchemaError",
]

from f2l.io.record_limits import _declared_bytes, declared_size_problem

FACE_SCHEMA_NAME = "face_record"
_NORMAL_TOLERANCE = 1e-3

_ROW_GROUP_SLACK_BYTES = 4 * MAX_TEXT_BYTES  # strings (meta_json up to 16 MiB, paths) and framing


def _face_id_pattern() -> re.Pattern:
    return re.compile(_schema(FACE_SCHEMA_NAME)["properties"]["face_id"]["pattern"])


# -- visibility packing ----------------------------------------------------------------------
def pack_visibility(visible: np.ndarray) -> np.ndarray:
    """Pack (N, L) bool visibility (row-major texels) to (N, ceil(L/8)) uint8, little bit order."""
    visible = np.asarray(visible, dtype=bool)
    if visible.ndim != 2:
        raise ValueError(f"visibility must be (N, L), got shape {visible.shape}")
    return np.packbits(visible, axis=1, bitorder="little")


def unpack_visibility(bits: np.ndarray, num_texels: int) -> np.ndarray:
    """Unpack (N, ceil(L/8)) uint8 to (N, L) bool."""
    return np.unpackbits(bits, axis=1, count=num_texels, bitorder="little").astype(bool)


# -- records ---------------------------------------------------------------------------------
def _as_float32(a: Any) -> np.ndarray:
    a = np.asarray(a)
    return a.astype(np.float32) if a.dtype.kind == "f" and a.dtype != np.float32 else a


def _as_int32(a: Any) -> np.ndarray:
    a = np.asarray(a)
    if a.dtype.kind in "iu" and a.dtype != np.int32 and a.size:
        if a.min() >= np.iinfo(np.int32).min and a.max() <= np.iinfo(np.int32).max:
            return a.astype(np.int32)
    elif a.dtype.kind in "iu" and a.dtype != np.int32:
        return a.astype(np.int32)
    return a


@dataclass(eq=False)
class FaceRecord:
    """One face: pixels with 3D points (cm), unit normals, observed linear RGB and visibility.

    Arrays are coerced on construction where lossless-enough (float -> float32, int -> int32,
    0/1 ints -> bool); :meth:`validate` then checks shapes, dtypes and values strictly.
    """

    face_id: str
    source_path: str
    face_index: int
    image_height: int
    image_width: int
    pixel_rc: np.ndarray        # (N, 2) int32, row/col in px
    points: np.ndarray          # (N, 3) float32, cm, world = camera frame
    normals: np.ndarray         # (N, 3) float32, unit
    observed_rgb: np.ndarray    # (N, 3) float32, linear RGB >= 0
    mask: np.ndarray            # (N,) bool
    grid_height: int
    grid_width: int
    visibility_bits: np.ndarray  # (N, ceil(L/8)) uint8, packbits(axis=1, bitorder='little')
    visibility_method: str = "exact"
    gt_probe_path: str | None = None
    photo_path: str | None = None
    meta: dict = field(default_factory=dict)
    status: str = "ok"
    message: str = ""

    def __post_init__(self) -> None:
        self.pixel_rc = _as_int32(self.pixel_rc)
        self.points = _as_float32(self.points)
        self.normals = _as_float32(self.normals)
        self.observed_rgb = _as_float32(self.observed_rgb)
        mask = np.asarray(self.mask)
        if mask.dtype.kind in "iu" and mask.size and np.isin(mask, (0, 1)).all():
            mask = mask.astype(bool)
        elif mask.dtype.kind in "iu" and not mask.size:
            mask = mask.astype(bool)
        self.mask = mask
        vis = np.asarray(self.visibility_bits)
        if vis.dtype.kind in "iu" and vis.dtype != np.uint8 and (
            not vis.size or (vis.min() >= 0 and vis.max() <= 255)
        ):
            vis = vis.astype(np.uint8)
        self.visibility_bits = vis

    def __repr__(self) -> str:
        return (f"FaceRecord(face_id={self.face_id!r}, source_path={self.source_path!r}, "
                f"face_index={self.face_index}, num_pixels={self.num_pixels}, "
                f"grid={self.grid_height}x{self.grid_width}, status={self.status!r})")

    # -- derived -------------------------------------------------------------------------
    @property
    def num_pixels(self) -> int:
        """Number N of face pixels."""
        return int(self.points.shape[0]) if self.points.ndim else 0

    @property
    def num_texels(self) -> int:
        """L = grid_height * grid_width."""
        return int(self.grid_height) * int(self.grid_width)

    @property
    def grid(self):
        """The lighting grid as a :class:`f2l.lighting.grid.LatLongGrid`."""
        from f2l.lighting.grid import LatLongGrid

        return LatLongGrid(int(self.grid_height), int(self.grid_width))

    def visibility(self) -> np.ndarray:
        """Unpacked visibility, (N, L) bool, row-major texels."""
        return unpack_visibility(self.visibility_bits, self.num_texels)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    # -- validation ----------------------------------------------------------------------
    def check_arrays(self) -> None:
        """Shapes, dtypes, finiteness, unit normals, observed >= 0, pixels inside the photo."""
        n = self.num_pixels
        problem = declared_size_problem(n, self.grid_height, self.grid_width)
        if problem is not None:
            raise SchemaError(f"face {self.face_id!r}: {problem}", [problem])
        errors: list[str] = []
        nbytes = -(-self.num_texels // 8)
        specs = (
            ("pixel_rc", np.int32, (n, 2)),
            ("points", np.float32, (n, 3)),
            ("normals", np.float32, (n, 3)),
            ("observed_rgb", np.float32, (n, 3)),
            ("mask", np.bool_, (n,)),
            ("visibility_bits", np.uint8, (n, nbytes)),
        )
        ok_arrays = set()
        for name, dtype, shape in specs:
            a = getattr(self, name)
            if not isinstance(a, np.ndarray):
                errors.append(f"{name} is {type(a).__name__}, expected numpy array")
            elif a.dtype != dtype:
                errors.append(f"{name} has dtype {a.dtype}, expected {np.dtype(dtype)}")
            elif a.shape != shape:
                errors.append(f"{name} has shape {a.shape}, expected {shape}")
            else:
                ok_arrays.add(name)
        for name in ("points", "normals", "observed_rgb"):
            if name in ok_arrays and not np.isfinite(getattr(self, name)).all():
                errors.append(f"{name} has non-finite values (NaN/inf)")
                ok_arrays.discard(name)
        if "normals" in ok_arrays and n:
            dev = np.abs(np.linalg.norm(self.normals.astype(np.float64), axis=1) - 1.0)
            if dev.max() > _NORMAL_TOLERANCE:
                errors.append(f"normals are not unit length (max |norm - 1| = {dev.max():.3g}, "
                              f"tolerance {_NORMAL_TOLERANCE})")
        if "observed_rgb" in ok_arrays and n and self.observed_rgb.min() < 0:
            errors.append(f"observed_rgb has negative values (min {self.observed_rgb.min():.3g})")
        if "pixel_rc" in ok_arrays and n:
            rc = self.pixel_rc
            if rc.min() < 0 or rc[:, 0].max() >= self.image_height or \
                    rc[:, 1].max() >= self.image_width:
                errors.append(f"pixel_rc outside the {self.image_height}x{self.image_width} photo")
        if "visibility_bits" in ok_arrays and n and self.num_texels % 8:
            pad_mask = np.uint8((0xFF << (self.num_texels % 8)) & 0xFF)
            if (self.visibility_bits[:, -1] & pad_mask).any():
                errors.append("visibility_bits has non-zero padding bits beyond L texels")
        if not isinstance(self.meta, dict):
            errors.append(f"meta is {type(self.meta).__name__}, expected dict")
        if errors:
            raise SchemaError(f"face {self.face_id!r}: " + "; ".join(errors), errors)

    def validate(self) -> None:
        """Check the record fully (arrays and schema); raise :class:`SchemaError` naming face_id."""
        self.check_arrays()
        validate_table(self.to_table(), _schema(FACE_SCHEMA_NAME), source=f"face {self.face_id!r}")

    # -- conversion ----------------------------------------------------------------------
    def to_row(self) -> dict[str, Any]:
        """Row dict in the stored layout (flattened arrays, visibility bytes, meta_json)."""
        try:
            meta_json = json_dumps_strict(self.meta)
        except (TypeError, ValueError) as exc:
            raise SchemaError(f"face {self.face_id!r}: meta is not strict JSON: {exc}") from None
        return {
            "face_id": self.face_id,
            "source_path": str(self.source_path),
            "face_index": int(self.face_index),
            "image_height": int(self.image_height),
            "image_width": int(self.image_width),
            "num_pixels": self.num_pixels,
            "pixel_rc": np.ascontiguousarray(self.pixel_rc).reshape(-1),
            "points": np.ascontiguousarray(self.points).reshape(-1),
            "normals": np.ascontiguousarray(self.normals).reshape(-1),
            "observed_rgb": np.ascontiguousarray(self.observed_rgb).reshape(-1),
            "mask": np.ascontiguousarray(self.mask).reshape(-1),
            "grid_height": int(self.grid_height),
            "grid_width": int(self.grid_width),
            "visibility_bits": np.ascontiguousarray(self.visibility_bits).tobytes(),
            "visibility_method": self.visibility_method,
            "gt_probe_path": self.gt_probe_path,
            "photo_path": self.photo_path,
            "meta_json": meta_json,
            "status": self.status,
            "message": self.message,
        }

    def to_table(self) -> pa.Table:
        """One-row Arrow table of this record."""
        return rows_to_table([self.to_row()], _schema(FACE_SCHEMA_NAME))

    @classmethod
    def from_row(cls, row: Mapping[str, Any]) -> FaceRecord:
        """Inverse of :meth:`to_row` (accepts lists, numpy arrays or bytes for the arrays).

        The declared sizes are checked first (:func:`declared_size_problem`) and ``meta_json`` is
        read with bounds (:func:`f2l.io.bounded.load_json`): :class:`SchemaError` naming the face."""
        who = f"face {row.get('face_id')!r}"
        problem = declared_size_problem(row["num_pixels"], row["grid_height"], row["grid_width"])
        if problem is not None:
            raise SchemaError(f"{who}: {problem}", [problem])
        try:
            meta = load_json(row["meta_json"], f"{who}: meta_json")
        except (InputError, TypeError) as exc:
            raise SchemaError(str(exc), [str(exc)]) from None
        n = int(row["num_pixels"])
        num_texels = int(row["grid_height"]) * int(row["grid_width"])
        vis = row["visibility_bits"]
        vis = np.frombuffer(vis, dtype=np.uint8).copy() if isinstance(vis, (bytes, bytearray)) \
            else np.asarray(vis, dtype=np.uint8)

        def arr(name: str, dtype, shape):
            return np.asarray(row[name], dtype=dtype).reshape(shape)

        return cls(
            face_id=row["face_id"],
            source_path=row["source_path"],
            face_index=int(row["face_index"]),
            image_height=int(row["image_height"]),
            image_width=int(row["image_width"]),
            pixel_rc=arr("pixel_rc", np.int32, (n, 2)),
            points=arr("points", np.float32, (n, 3)),
            normals=arr("normals", np.float32, (n, 3)),
            observed_rgb=arr("observed_rgb", np.float32, (n, 3)),
            mask=arr("mask", bool, (n,)),
            grid_height=int(row["grid_height"]),
            grid_width=int(row["grid_width"]),
            visibility_bits=vis.reshape(n, -(-num_texels // 8)),
            visibility_method=row["visibility_method"],
            gt_probe_path=row["gt_probe_path"],
            photo_path=row["photo_path"],
            meta=meta,
            status=row["status"],
            message=row["message"],
        )


@dataclass(frozen=True)
class BadRecord:
    """A file or row that could not be read or failed validation (``face_id`` None if unknown)."""

    source: str
    face_id: str | None
    reason: str

    ok = False

    def __str__(self) -> str:
        who = f" (face {self.face_id!r})" if self.face_id is not None else ""
        return f"{self.source}{who}: {self.reason}"


# -- shard writer ----------------------------------------------------------------------------
_PART_RE = re.compile(r"^part-(\d{5,})\.parquet$")


class ShardWriter(CommitOnSuccess):
    """Write validated :class:`FaceRecord` s to ``out_dir/part-00000.parquet``, ... atomically.

    Each record is one row group; a shard is published (renamed from its ``.tmp``) when it holds
    ``records_per_shard`` records or on close. On an exception inside ``with``, the unfinished
    shard is discarded and finished shards are kept. Existing ``part-*.parquet`` files raise
    ``FileExistsError`` unless ``overwrite=True`` (then stale parts are removed on close).
    """

    def __init__(self, out_dir: str | os.PathLike, records_per_shard: int = 64, *,
                 compression: str = "zstd", overwrite: bool = False):
        if records_per_shard < 1:
            raise ValueError(f"records_per_shard must be >= 1, got {records_per_shard}")
        self.out_dir = Path(out_dir)
        self.records_per_shard = int(records_per_shard)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        existing = [p for p in self.out_dir.iterdir() if _PART_RE.match(p.name)]
        if existing and not overwrite:
            raise FileExistsError(f"{self.out_dir} already holds {len(existing)} shard file(s); "
                                  f"pass overwrite=True or use an empty directory")
        self._stale = set(existing)
        self._schema = _schema(FACE_SCHEMA_NAME)
        self._aschema = arrow_schema(self._schema)
        self._options = _write_options(self._schema, compression)
        self._current: _AtomicParquet | None = None
        self._in_current = 0
        self._seen: set[str] = set()
        self.paths: list[Path] = []
        self.num_records = 0
        self._closed = False

    def write(self, record: FaceRecord) -> None:
        """Validate ``record`` (raises :class:`SchemaError`) and append it to the current shard."""
        if self._closed:
            raise RuntimeError(f"{self.out_dir}: shard writer is closed")
        record.check_arrays()
        table = record.to_table()
        validate_table(table, self._schema, source=f"face {record.face_id!r}")
        if record.face_id in self._seen:
            raise SchemaError(f"face {record.face_id!r}: duplicate face_id in {self.out_dir}")
        if self._current is None:
            path = self.out_dir / f"part-{len(self.paths):05d}.parquet"
            self._current = _AtomicParquet(path, self._aschema, self._options)
        self._current.write(table)
        self._seen.add(record.face_id)
        self._in_current += 1
        self.num_records += 1
        if self._in_current >= self.records_per_shard:
            self._publish()

    def _publish(self) -> None:
        if self._current is not None:
            path = self._current.commit()
            self.paths.append(path)
            self._stale.discard(path)
            self._current, self._in_current = None, 0

    def close(self) -> list[Path]:
        """Publish the last shard; returns the shard paths written."""
        if not self._closed:
            self._publish()
            self._closed = True
            for stale in sorted(self._stale):
                stale.unlink(missing_ok=True)
        return list(self.paths)

    def abort(self) -> None:
        """Discard the unfinished shard (finished shards stay)."""
        if self._current is not None:
            self._current.abort()
            self._current, self._in_current = None, 0
        self._closed = True

# -- reading ---------------------------------------------------------------------------------
def shard_files(shards: str | os.PathLike | Iterable[str | os.PathLike]) -> list[Path]:
    """Parquet files of a shard directory (``*.parquet``, sorted), a file, or a list of either.

    A list keeps its order; each directory in it expands to its sorted files.
    """
    if isinstance(shards, (str, os.PathLike)):
        p = Path(shards)
        if p.is_dir():
            return sorted(q for q in p.glob("*.parquet") if not q.name.startswith("."))
        return [p]
    return [f for s in shards for f in shard_files(s)]


def _row_face_id(table: pa.Table, index: int) -> str | None:
    if "face_id" not in table.column_names:
        return None
    try:
        value = table.column("face_id")[index].as_py()
    except Exception:  # noqa: BLE001
        return None
    return value if isinstance(value, str) else None


def iter_records(shards: str | os.PathLike | Iterable[str | os.PathLike],
                 validate: bool = True) -> Iterator[FaceRecord | BadRecord]:
    """Stream records one row group at a time, files in sorted order.

    An unreadable file, an unreadable row group, a record whose declared sizes are refused
    (:func:`declared_size_problem`, checked before its arrays are read), a row group larger than
    its records' declared sizes need, an unbounded ``meta_json`` or a row failing validation
    yields a :class:`BadRecord` and reading continues with the next row group or file.
    """
    schema = _schema(FACE_SCHEMA_NAME)
    for path in shard_files(shards):
        source = str(path)
        try:
            pf = pq.ParquetFile(path)
        except Exception as exc:  # noqa: BLE001 - any unreadable file becomes a BadRecord
            yield BadRecord(source, None, f"unreadable Parquet file: {type(exc).__name__}: {exc}")
            continue
        with pf:
            for rg in range(pf.num_row_groups):
                refused, group_problem = _precheck_row_group(pf, rg)
                if group_problem is not None:  # nothing of it is read; each row's own reason first
                    if not refused:
                        yield BadRecord(source, None, f"row group {rg}: {group_problem}")
                    for i, (face_id, problem) in enumerate(refused):
                        yield BadRecord(source, face_id,
                                        f"row group {rg} row {i}: {problem or group_problem}")
                    continue
                try:
                    table = pf.read_row_group(rg)
                except Exception as exc:  # noqa: BLE001
                    yield BadRecord(source, None, f"row group {rg} unreadable: "
                                                  f"{type(exc).__name__}: {exc}")
                    continue
                for i in range(table.num_rows):
                    where = f"row group {rg} row {i}"
                    if refused[i][1] is not None:
                        yield BadRecord(source, refused[i][0], f"{where}: {refused[i][1]}")
                        continue
                    one = table.slice(i, 1) if table.num_rows > 1 else table
                    yield _record_from_table(one, source, where, schema, validate)


_SIZE_COLUMNS = ("face_id", "num_pixels", "grid_height", "grid_width")
_LIST_WIDTH = {"pixel_rc": 2, "points": 3, "normals": 3, "observed_rgb": 3, "mask": 1}  # per pixel


def _precheck_row_group(pf: pq.ParquetFile, rg: int) -> tuple[list[tuple[str | None, str | None]], str | None]:
    """Before a row group's arrays are read: per row ``(face_id, problem or None)`` from its
    declared sizes, and a problem of the whole group, from the file's footer: its size columns
    unreadable, every row refused, an array column holding more values than its accepted rows
    declare, or more bytes uncompressed than their declared sizes need."""
    names = set(pf.schema_arrow.names)
    missing = [c for c in _SIZE_COLUMNS if c not in names]
    if missing:
        return [], f"missing column(s) {', '.join(missing)}"
    try:
        rows = pf.read_row_group(rg, columns=list(_SIZE_COLUMNS)).to_pylist()
        meta = pf.metadata.row_group(rg)
        group_bytes = int(meta.total_byte_size)
        values = {meta.column(j).path_in_schema.split(".")[0]: int(meta.column(j).num_values)
                  for j in range(meta.num_columns)}
    except Exception as exc:  # noqa: BLE001
        return [], f"unreadable: {type(exc).__name__}: {exc}"
    refused: list[tuple[str | None, str | None]] = []
    need, pixels = _ROW_GROUP_SLACK_BYTES, []
    for r in rows:
        face_id = r["face_id"] if isinstance(r["face_id"], str) else None
        problem = declared_size_problem(r["num_pixels"], r["grid_height"], r["grid_width"])
        refused.append((face_id, problem))
        if problem is None:
            need += 2 * _declared_bytes(r["num_pixels"], r["grid_height"], r["grid_width"])
        pixels.append(int(r["num_pixels"]) if problem is None else 0)
    if all(problem is not None for _, problem in refused):
        return refused, "refused"  # each row's own reason; nothing more is read
    for name, width in _LIST_WIDTH.items():
        declared = sum(max(n * width, 1) for n in pixels)  # an empty list still takes a slot
        if values.get(name, 0) > declared:
            return refused, (f"column {name!r} holds {values[name]} values, more than the "
                             f"{declared} its records declare (num_pixels x {width}); not read")
    if group_bytes > need:
        return refused, (f"{group_bytes} bytes uncompressed, more than its records' declared sizes "
                         f"(num_pixels, grid_height x grid_width) need ({need}); not read")
    return refused, None


def _record_from_table(table: pa.Table, source: str, where: str, schema: dict,
                       validate: bool) -> FaceRecord | BadRecord:
    face_id = _row_face_id(table, 0)
    if "meta_json" in table.column_names:  # bounded before anything parses it (schema, from_row)
        try:
            text = table.column("meta_json")[0].as_py()
            if isinstance(text, str):
                load_json(text, f"{where}: meta_json")
        except InputError as exc:
            return BadRecord(source, face_id, str(exc))
        except Exception:  # noqa: BLE001 - a malformed column is reported by the checks below
            pass
    if validate:
        try:
            errors = table_errors(table, schema, source=where)
        except (UnicodeDecodeError, ValueError, TypeError, OverflowError) as exc:  # bytes no reader can decode
            return BadRecord(source, face_id, f"{where}: unreadable values ({type(exc).__name__}: {exc})")
        if errors:
            return BadRecord(source, face_id, "; ".join(errors[:10])
                             + (f"; ... and {len(errors) - 10} more" if len(errors) > 10 else ""))
    try:
        record = FaceRecord.from_row(table_row(table, 0))
        if validate:
            record.check_arrays()
    except SchemaError as exc:
        return BadRecord(source, face_id, f"{where}: {exc}")
    except Exception as exc:  # noqa: BLE001 - malformed rows read without validation
        return BadRecord(source, face_id, f"{where}: cannot decode record: "
                                          f"{type(exc).__name__}: {exc}")
    return record


def count_records(shards: str | os.PathLike | Iterable[str | os.PathLike]) -> int:
    """Number of rows in the readable shard files (from Parquet footers only)."""
    total = 0
    for path in shard_files(shards):
        try:
            total += pq.ParquetFile(path).metadata.num_rows
        except Exception:  # noqa: BLE001 - unreadable files are counted by iter_records as bad
            continue
    return total


# -- side files ------------------------------------------------------------------------------


