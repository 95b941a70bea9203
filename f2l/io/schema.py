"""JSON Schemas of f2l's Parquet tables, and validation of Arrow tables against them.

A table schema (``schemas/<name>.schema.json``, draft 2020-12) describes one row. Besides the
standard keywords it carries annotations that this module understands:

- ``x-arrow-type`` per column: ``string``, ``bool``, ``int32``, ``int64``, ``float32``,
  ``float64``, ``binary``, ``large_binary`` or ``list<T>``.
- ``x-shape`` per list/binary column: the logical shape of the flattened array; entries are ints,
  column names, or integer expressions over columns (``+ - * / //``, ``ceil(..)``,
  ``len(<list column>)``). The stored length must equal the product.
- ``x-empty-if-failed``: the list may be empty when the row's ``x-status-column`` is not ``ok``.
- ``x-row-norm`` ``{"value", "tolerance"}``: each vector (last ``x-shape`` axis) has that norm.
- ``items.minimum`` / ``items.maximum``: element bounds of a list column.
- ``x-json-type``: a string column holding JSON of that type (e.g. ``object``).
- ``x-key``: the columns that name a row in error messages.

Nullable columns have ``"type": [T, "null"]``. Float values (scalars and list elements) must be
finite. Scalar columns are also checked per row with ``jsonschema``.
"""

from __future__ import annotations

import ast
import json
from importlib import resources
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

__all__ = [
    "SchemaError",
    "schemas_dir",
    "load_schema",
    "arrow_schema",
    "table_errors",
    "validate_table",
    "is_nullable",
    "schema_version",
    "json_dumps_strict",
]

SCHEMA_METADATA_NAME = b"f2l.schema"
SCHEMA_METADATA_VERSION = b"f2l.schema_version"
_MAX_REPORTED_ERRORS = 10


class SchemaError(ValueError):
    """A table, row or record does not conform to its schema; ``errors`` lists every problem."""

    def __init__(self, message: str, errors: list[str] | None = None):
        super().__init__(message)
        self.errors = list(errors) if errors else [message]


# -- locating and loading schemas ------------------------------------------------------------
def schemas_dir() -> Path:
    """Directory holding ``<name>.schema.json``: the package ``f2l.schemas``, whose single source is
    the repository's top-level ``schemas/`` (pyproject maps it in; an editable install reads the
    repository's folder, a wheel carries a copy)."""
    try:
        # a data folder without __init__.py is a namespace package: files() gives a
        # MultiplexedPath, whose joinpath of an existing file is a real path
        folder = Path(str(resources.files("f2l.schemas").joinpath("face_record.schema.json"))).parent
    except ModuleNotFoundError:
        folder = Path(__file__).resolve().parents[2] / "schemas"  # a source tree on sys.path
    if not (folder / "face_record.schema.json").is_file():
        raise FileNotFoundError(f"f2l schemas not found in {folder} (is f2l installed with its package data?)")
    return folder


@lru_cache(maxsize=None)
def _load_schema_text(name: str) -> str:
    path = schemas_dir() / f"{name}.schema.json"
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FileNotFoundError(f"no schema named {name!r} ({path} does not exist)") from None


def load_schema(name: str) -> dict:
    """The JSON Schema ``schemas/<name>.schema.json`` as a dict (a fresh copy each call)."""
    return json.loads(_load_schema_text(name))


def _resolve(schema: dict | str) -> dict:
    return load_schema(schema) if isinstance(schema, str) else schema


# -- Arrow types -----------------------------------------------------------------------------
_SCALAR_ARROW = {
    "string": pa.string(),
    "bool": pa.bool_(),
    "int32": pa.int32(),
    "int64": pa.int64(),
    "float32": pa.float32(),
    "float64": pa.float64(),
    "binary": pa.binary(),
    "large_binary": pa.large_binary(),
}


def _parse_arrow_type(text: str) -> pa.DataType:
    text = text.strip()
    if text.startswith("list<") and text.endswith(">"):
        return pa.list_(_parse_arrow_type(text[5:-1]))
    try:
        return _SCALAR_ARROW[text]
    except KeyError:
        raise ValueError(f"unknown x-arrow-type {text!r}") from None


def is_nullable(prop: dict) -> bool:
    """Whether a column's JSON ``type`` admits null."""
    t = prop.get("type")
    return isinstance(t, list) and "null" in t


def _columns(schema: dict) -> dict[str, dict]:
    return schema["properties"]


def _is_bulk(prop: dict) -> bool:
    """List and binary columns: checked vectorised, not by jsonschema."""
    t = prop["x-arrow-type"]
    return t.startswith("list<") or t in ("binary", "large_binary")


def arrow_schema(schema: dict | str) -> pa.Schema:
    """The Arrow schema of a table schema (column order as in ``properties``), with metadata."""
    schema = _resolve(schema)
    fields = [
        pa.field(name, _parse_arrow_type(prop["x-arrow-type"]), nullable=is_nullable(prop))
        for name, prop in _columns(schema).items()
    ]
    meta = {
        SCHEMA_METADATA_NAME: str(schema.get("title", "")).encode(),
        SCHEMA_METADATA_VERSION: str(schema.get("x-schema-version", "")).encode(),
    }
    return pa.schema(fields, metadata=meta)


# -- x-shape expressions ---------------------------------------------------------------------
@lru_cache(maxsize=256)
def _parse_dim(expr: str) -> ast.Expression:
    return ast.parse(expr, mode="eval")


def _eval_dim(node: ast.AST, env: dict[str, np.ndarray], lengths: dict[str, np.ndarray]):
    """Evaluate an x-shape expression vectorised over rows (int64 / float64 arrays)."""
    if isinstance(node, ast.Expression):
        return _eval_dim(node.body, env, lengths)
    if isinstance(node, ast.Constant) and isinstance(node.value, int):
        return np.int64(node.value)
    if isinstance(node, ast.Name):
        return env[node.id]
    if isinstance(node, ast.BinOp):
        a = _eval_dim(node.left, env, lengths)
        b = _eval_dim(node.right, env, lengths)
        ops = {ast.Add: np.add, ast.Sub: np.subtract, ast.Mult: np.multiply,
               ast.Div: np.true_divide, ast.FloorDiv: np.floor_divide}
        return ops[type(node.op)](a, b)
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and len(node.args) == 1:
        if node.func.id == "ceil":
            return np.ceil(_eval_dim(node.args[0], env, lengths)).astype(np.int64)
        if node.func.id == "len" and isinstance(node.args[0], ast.Name):
            return lengths[node.args[0].id]
    raise ValueError(f"unsupported x-shape expression: {ast.dump(node)}")


def _dim_names(dim: Any) -> set[str]:
    if isinstance(dim, int):
        return set()
    return {n.id for n in ast.walk(_parse_dim(str(dim))) if isinstance(n, ast.Name)} - {"ceil", "len"}


def _dim_label(dim: Any) -> str:
    return str(dim) if isinstance(dim, int) else str(dim).replace(" ", "")


# -- validation ------------------------------------------------------------------------------
class _Errors:
    """Collects (row, message) pairs and labels rows by the schema's key columns."""

    def __init__(self, table: pa.Table, schema: dict, source: str):
        self.items: list[tuple[int, str]] = []
        self.table = table
        self.source = source
        self.key = [k for k in schema.get("x-key", []) if k in table.column_names]

    def add(self, row: int | None, message: str) -> None:
        self.items.append((-1 if row is None else int(row), message))

    def keys(self, row: int) -> str:
        parts = []
        for k in self.key:
            try:
                parts.append(f"{k}={self.table.column(k)[row].as_py()!r}")
            except Exception:  # noqa: BLE001 - a label must never fail
                pass
        return ", ".join(parts)

    def label(self, row: int) -> str:
        keys = self.keys(row)
        return f"row {row}" + (f" ({keys})" if keys else "") + ": "

    def table_suffix(self) -> str:
        """Which records a table-wide problem affects (named when there are few)."""
        n = self.table.num_rows
        if n == 0 or not self.key:
            return ""
        if n <= 3:
            return " (" + "; ".join(self.keys(r) or f"row {r}" for r in range(n)) + ")"
        return f" (all {n} rows)"

    def messages(self) -> list[str]:
        return [f"{self.source}: {m}{self.table_suffix()}" if r < 0
                else f"{self.source}: {self.label(r)}{m}" for r, m in self.items]


def _column_array(table: pa.Table, name: str) -> pa.Array:
    col = table.column(name)
    if isinstance(col, pa.ChunkedArray):
        return col.chunk(0) if col.num_chunks == 1 else col.combine_chunks()
    return col


@lru_cache(maxsize=64)
def _validator(sub_json: str):
    from jsonschema import Draft202012Validator

    return Draft202012Validator(json.loads(sub_json))


def _check_columns(table: pa.Table, schema: dict, errs: _Errors) -> set[str]:
    """Missing/extra columns and Arrow types; returns the columns usable for row checks."""
    expected = arrow_schema(schema)
    have = set(table.column_names)
    for name in expected.names:
        if name not in have:
            errs.add(None, f"missing column {name!r}")
    for name in table.column_names:
        if name not in expected.names:
            errs.add(None, f"unexpected column {name!r}")
    good = set()
    for field in expected:
        if field.name not in have:
            continue
        actual = table.schema.field(field.name).type
        if actual != field.type:
            errs.add(None, f"column {field.name!r} has Arrow type {actual}, expected {field.type}")
            continue
        good.add(field.name)
    return good


def _check_nulls(table: pa.Table, schema: dict, good: set[str], errs: _Errors) -> None:
    for name, prop in _columns(schema).items():
        if name not in good:
            continue
        arr = _column_array(table, name)
        if arr.null_count and not is_nullable(prop):
            for row in np.flatnonzero(arr.is_null().to_numpy(zero_copy_only=False))[:3]:
                errs.add(row, f"column {name!r} is null but not nullable")
        if pa.types.is_list(arr.type):
            values = arr.flatten()
            if values.null_count:
                parents = pc.list_parent_indices(arr).to_numpy()
                rows = np.unique(parents[values.is_null().to_numpy(zero_copy_only=False)])
                for row in rows[:3]:
                    errs.add(row, f"column {name!r} contains null elements")


def _check_json_rows(table: pa.Table, schema: dict, good: set[str], errs: _Errors) -> None:
    """Per-row jsonschema check of the scalar columns, plus x-json-type contents."""
    props = _columns(schema)
    scalar = [n for n, p in props.items() if not _is_bulk(p) and n in good]
    if not scalar:
        return
    sub = {
        "$schema": schema.get("$schema", "https://json-schema.org/draft/2020-12/schema"),
        "type": "object",
        "properties": {n: props[n] for n in scalar},
        "required": [n for n in schema.get("required", []) if n in scalar],
    }
    validator = _validator(json.dumps(sub, sort_keys=True))
    json_cols = {n: props[n]["x-json-type"] for n in scalar if "x-json-type" in props[n]}
    py_types = {"object": dict, "array": list, "string": str}
    for row, values in enumerate(table.select(scalar).to_pylist()):
        for err in validator.iter_errors(values):
            where = ".".join(str(p) for p in err.absolute_path) or "row"
            errs.add(row, f"{where}: {err.message}")
        for name, json_type in json_cols.items():
            text = values.get(name)
            if text is None:
                continue
            try:
                parsed = json.loads(text)
            except json.JSONDecodeError as exc:
                errs.add(row, f"{name}: not valid JSON ({exc})")
                continue
            want = py_types.get(json_type)
            if want is not None and not isinstance(parsed, want):
                errs.add(row, f"{name}: JSON is {type(parsed).__name__}, expected {json_type}")


def _length_of(arr: pa.Array) -> np.ndarray:
    """Per-row lengths (int64, -1 for null) of a list or binary array."""
    if pa.types.is_list(arr.type) or pa.types.is_large_list(arr.type):
        lengths = pc.list_value_length(arr)
    else:
        lengths = pc.binary_length(arr)
    return pc.fill_null(pc.cast(lengths, pa.int64()), -1).to_numpy(zero_copy_only=False)


def _check_bulk(table: pa.Table, schema: dict, good: set[str], errs: _Errors) -> None:
    """Vectorised x-shape lengths, finiteness, element bounds and row norms of bulk columns."""
    props = _columns(schema)
    n_rows = table.num_rows
    bulk = [n for n, p in props.items() if _is_bulk(p) and n in good]
    lengths = {n: _length_of(_column_array(table, n)) for n in bulk}
    env: dict[str, np.ndarray] = {}
    for name, prop in props.items():
        if name in good and not _is_bulk(prop) and prop["x-arrow-type"].startswith("int"):
            arr = _column_array(table, name)
            env[name] = pc.fill_null(pc.cast(arr, pa.int64()), 0).to_numpy(zero_copy_only=False)
    status_col = schema.get("x-status-column")
    failed = np.zeros(n_rows, dtype=bool)
    if status_col in good:
        st = _column_array(table, status_col)
        failed = ~pc.fill_null(pc.equal(st, "ok"), False).to_numpy(zero_copy_only=False)

    for name in bulk:
        prop = props[name]
        arr = _column_array(table, name)
        length = lengths[name]
        shape_ok = np.ones(n_rows, dtype=bool)
        shape = prop.get("x-shape")
        if shape is not None:
            needed = set().union(*(_dim_names(d) for d in shape))
            missing = [d for d in needed if d not in env and d not in lengths]
            if missing:
                errs.add(None, f"cannot check length of {name!r}: column(s) {missing} unusable")
                shape_ok[:] = False
            else:
                expected = np.ones(n_rows, dtype=np.int64)
                for dim in shape:
                    val = np.int64(dim) if isinstance(dim, int) else _eval_dim(
                        _parse_dim(str(dim)), env, lengths
                    )
                    expected = expected * np.asarray(val, dtype=np.int64)
                valid = (length == expected) | (length < 0)
                if prop.get("x-empty-if-failed"):
                    valid |= failed & (length == 0)
                shape_ok = valid
                label = "*".join(_dim_label(d) for d in shape)
                unit = "values" if pa.types.is_list(arr.type) else "bytes"
                for row in np.flatnonzero(~valid)[:_MAX_REPORTED_ERRORS]:
                    errs.add(row, f"column {name!r} has {length[row]} {unit}, expected "
                                  f"{expected[row]} ({label})")
        if not pa.types.is_list(arr.type):
            continue
        values = arr.flatten()
        vtype = values.type
        if not (pa.types.is_floating(vtype) or pa.types.is_integer(vtype)):
            continue
        parents = pc.list_parent_indices(arr).to_numpy()
        vals = values.to_numpy(zero_copy_only=False)
        if pa.types.is_floating(vtype):
            with np.errstate(invalid="ignore"):
                bad = ~np.isfinite(vals)
            for row in np.unique(parents[bad])[:_MAX_REPORTED_ERRORS]:
                errs.add(row, f"column {name!r} has non-finite values (NaN/inf)")
        items = prop.get("items", {})
        for key, cmp, word in (("minimum", np.less, "below"), ("maximum", np.greater, "above")):
            if key in items:
                with np.errstate(invalid="ignore"):
                    bad = cmp(vals, items[key])
                for row in np.unique(parents[bad])[:_MAX_REPORTED_ERRORS]:
                    errs.add(row, f"column {name!r} has values {word} the {key} {items[key]}")
        norm = prop.get("x-row-norm")
        if norm and shape and isinstance(shape[-1], int) and shape_ok.all() and vals.size:
            k = shape[-1]
            with np.errstate(invalid="ignore"):
                dev = np.abs(np.linalg.norm(vals.reshape(-1, k).astype(np.float64), axis=1)
                             - norm["value"])
            vec_rows = parents[::k]
            with np.errstate(invalid="ignore"):
                far = dev > norm["tolerance"]  # NaN rows are reported as non-finite above
            bad_rows = np.unique(vec_rows[far])
            for row in bad_rows[:_MAX_REPORTED_ERRORS]:
                worst = np.nanmax(np.where(vec_rows == row, dev, 0.0))
                errs.add(row, f"column {name!r} has vectors whose norm differs from "
                              f"{norm['value']} by up to {worst:.3g} (tolerance "
                              f"{norm['tolerance']})")


def _check_scalar_finite(table: pa.Table, schema: dict, good: set[str], errs: _Errors) -> None:
    for name, prop in _columns(schema).items():
        if name in good and prop["x-arrow-type"] in ("float32", "float64"):
            vals = _column_array(table, name).to_numpy(zero_copy_only=False)
            vals = np.asarray(vals, dtype=np.float64)  # nulls become NaN
            nulls = _column_array(table, name).is_null().to_numpy(zero_copy_only=False)
            for row in np.flatnonzero(~np.isfinite(vals) & ~nulls)[:_MAX_REPORTED_ERRORS]:
                errs.add(row, f"column {name!r} is not finite ({vals[row]})")


def table_errors(table: pa.Table, schema: dict | str, source: str) -> list[str]:
    """Every problem of ``table`` against ``schema`` as messages ``"<source>: row i (key): ..."``."""
    schema = _resolve(schema)
    errs = _Errors(table, schema, source)
    good = _check_columns(table, schema, errs)
    _check_nulls(table, schema, good, errs)
    _check_json_rows(table, schema, good, errs)
    _check_scalar_finite(table, schema, good, errs)
    _check_bulk(table, schema, good, errs)
    return errs.messages()


def validate_table(table: pa.Table, schema: dict | str, source: str) -> None:
    """Raise :class:`SchemaError` naming ``source`` (and the row's key) if ``table`` does not conform."""
    errors = table_errors(table, schema, source)
    if errors:
        shown = errors[:_MAX_REPORTED_ERRORS]
        more = len(errors) - len(shown)
        text = "; ".join(shown) + (f"; ... and {more} more" if more else "")
        raise SchemaError(text, errors)


def schema_version(schema: dict | str) -> int:
    """The ``x-schema-version`` of a schema."""
    return int(_resolve(schema)["x-schema-version"])


def json_dumps_strict(obj: Any) -> str:
    """Deterministic strict JSON (sorted keys, no NaN/inf; numpy scalars/arrays converted)."""

    def default(o: Any):
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, Path):
            return str(o)
        raise TypeError(f"{type(o).__name__} is not JSON-serialisable")

    return json.dumps(obj, sort_keys=True, allow_nan=False, default=default, separators=(",", ":"))

