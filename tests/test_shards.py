"""Face-record shards and results tables: round trip, validation, corruption, atomicity."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

from f2l.io.schema import SchemaError, arrow_schema, load_schema, table_errors, validate_table
from f2l.io.shards import (BadRecord, FaceRecord, ParquetAppender, ShardWriter, count_records, iter_records,
                           pack_visibility, write_table_atomic)
from f2l.io.side_files import write_side_photo

GRID_H, GRID_W = 8, 16


def make_record(face_id: str, n: int, seed: int) -> FaceRecord:
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return FaceRecord(
        face_id=face_id,
        source_path=f"photos/img_{seed}.jpg",
        face_index=seed % 3,
        image_height=480,
        image_width=640,
        pixel_rc=np.stack([rng.integers(0, 480, n), rng.integers(0, 640, n)], axis=1).astype(np.int32),
        points=(rng.normal(size=(n, 3)) * 10.0).astype(np.float32),
        normals=normals.astype(np.float32),
        observed_rgb=rng.random((n, 3)).astype(np.float32) * 5.0,
        mask=rng.random(n) > 0.3,
        grid_height=GRID_H,
        grid_width=GRID_W,
        visibility_bits=pack_visibility(rng.random((n, GRID_H * GRID_W)) > 0.5),
        visibility_method="exact" if seed % 2 else "adaptive",
        gt_probe_path=f"probes/{face_id}.exr" if seed % 2 else None,
        photo_path=None,
        meta={"albedo": [0.5, 0.4, 0.3], "sky": "clear", "sun_dir": np.array([0.0, 1.0, 0.0]),
              "exposure_ev100": 12.5},
    )


ARRAYS = ("pixel_rc", "points", "normals", "observed_rgb", "mask", "visibility_bits")
SCALARS = ("face_id", "source_path", "face_index", "image_height", "image_width", "grid_height",
           "grid_width", "visibility_method", "gt_probe_path", "photo_path", "status", "message")


def assert_same(a: FaceRecord, b: FaceRecord) -> None:
    for name in ARRAYS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype, name
        assert x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    for name in SCALARS:
        assert getattr(a, name) == getattr(b, name), name
    assert json.loads(json.dumps(a.meta, default=lambda o: o.tolist())) == b.meta


def write_raw(table: pa.Table, path: Path) -> None:
    """Write a (possibly malformed) table, one row group per row, bypassing validation."""
    pq.write_table(table, path, row_group_size=1)


# -- schemas ---------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["face_record", "estimates"])
def test_schema_files_are_complete(name):
    schema = load_schema(name)
    # estimates v2: the absolute scale; v3: the joint estimate's group columns; v4: the sun's uncertainty
    assert schema["x-schema-version"] == {"face_record": 1, "estimates": 4}[name]
    assert set(schema["required"]) == set(schema["properties"])
    for col, prop in schema["properties"].items():
        assert "type" in prop and "description" in prop and "x-arrow-type" in prop, col
    aschema = arrow_schema(schema)
    assert aschema.names == list(schema["properties"])


def test_face_schema_arrow_types():
    a = arrow_schema("face_record")
    assert a.field("points").type == pa.list_(pa.float32())
    assert a.field("pixel_rc").type == pa.list_(pa.int32())
    assert a.field("mask").type == pa.list_(pa.bool_())
    assert a.field("visibility_bits").type == pa.binary()
    assert a.field("gt_probe_path").nullable and not a.field("face_id").nullable


# -- round trip ------------------------------------------------------------------------------
def test_round_trip_identical(tmp_path):
    sizes = [0, 1, 7, 50, 333]
    records = [make_record(f"face-{i:03d}", n, seed=i) for i, n in enumerate(sizes)]
    with ShardWriter(tmp_path, records_per_shard=2) as writer:
        for r in records:
            writer.write(r)
    assert [p.name for p in writer.paths] == ["part-00000.parquet", "part-00001.parquet",
                                              "part-00002.parquet"]
    assert not list(tmp_path.rglob("*.tmp*"))
    # one row group per record, so readers stream one record at a time
    for path in writer.paths:
        meta = pq.ParquetFile(path).metadata
        assert meta.num_row_groups == meta.num_rows
    assert count_records(tmp_path) == len(records)

    out = list(iter_records(tmp_path))
    assert all(isinstance(r, FaceRecord) for r in out), out
    assert [r.face_id for r in out] == [r.face_id for r in records]
    for a, b in zip(records, out):
        assert_same(a, b)
        assert b.num_pixels == a.num_pixels
        np.testing.assert_array_equal(b.visibility(), a.visibility())
        assert b.visibility().shape == (a.num_pixels, GRID_H * GRID_W)


def test_written_table_validates(tmp_path):
    with ShardWriter(tmp_path) as writer:
        writer.write(make_record("a", 10, 1))
    table = pq.read_table(tmp_path / "part-00000.parquet")
    validate_table(table, "face_record", source="x")
    assert table.schema.metadata[b"f2l.schema"] == b"face_record"


# -- validation ------------------------------------------------------------------------------
def _bad_tables() -> dict[str, tuple[pa.Table, str]]:
    good = make_record("bad-face", 6, 3).to_table()
    n = good.column("num_pixels")[0].as_py()
    out = {}
    idx = good.column_names.index("face_index")
    out["wrong_type"] = (good.set_column(idx, "face_index", pc.cast(good["face_index"], pa.int64())),
                         "face_index")
    out["missing_column"] = (good.drop_columns(["normals"]), "missing column 'normals'")
    idx = good.column_names.index("num_pixels")
    out["inconsistent_lengths"] = (
        good.set_column(idx, pa.field("num_pixels", pa.int32(), nullable=False),
                        pa.array([n + 1], pa.int32())), "expected")
    rec = make_record("bad-face", 6, 3)
    rec.normals[2] = np.nan
    out["nan_normals"] = (rec.to_table(), "non-finite")
    rec = make_record("bad-face", 6, 3)
    rec.normals[4] *= 1.5
    out["non_unit_normals"] = (rec.to_table(), "norm")
    return out


@pytest.mark.parametrize("case", ["wrong_type", "missing_column", "inconsistent_lengths",
                                  "nan_normals", "non_unit_normals"])
def test_validation_rejects_malformed_shard(tmp_path, case):
    table, needle = _bad_tables()[case]
    with pytest.raises(SchemaError) as exc:
        validate_table(table, "face_record", source="shard.parquet")
    msg = str(exc.value)
    assert "shard.parquet" in msg and "face_id='bad-face'" in msg and needle in msg, msg

    path = tmp_path / "part-00000.parquet"
    write_raw(table, path)
    out = list(iter_records(tmp_path))
    assert len(out) == 1 and isinstance(out[0], BadRecord), out
    bad = out[0]
    assert bad.face_id == "bad-face" and bad.source == str(path)
    assert needle in bad.reason and str(path) in str(bad)


@pytest.mark.parametrize("case", ["nan_normals", "non_unit_normals"])
def test_record_validate_and_writer_reject(tmp_path, case):
    rec = make_record("bad-face", 6, 3)
    if case == "nan_normals":
        rec.normals[0, 1] = np.nan
    else:
        rec.normals[0] = [1.0, 1.0, 0.0]
    with pytest.raises(SchemaError, match="bad-face.*normals"):
        rec.validate()
    with pytest.raises(SchemaError, match="bad-face"), ShardWriter(tmp_path) as writer:
        writer.write(rec)
    assert not list(tmp_path.glob("*.parquet")) and not list(tmp_path.glob("*.tmp"))


def test_record_validate_other_checks():
    rec = make_record("f", 5, 1)
    rec.observed_rgb[0, 0] = -0.1
    with pytest.raises(SchemaError, match="observed_rgb"):
        rec.validate()
    rec = make_record("f", 5, 1)
    rec.points = rec.points[:4]
    with pytest.raises(SchemaError, match="'f'.*shape"):
        rec.validate()
    rec = make_record("f", 5, 1)
    rec.pixel_rc = rec.pixel_rc.astype(np.float32)
    with pytest.raises(SchemaError, match="pixel_rc has dtype float32"):
        rec.validate()
    rec = make_record("f", 5, 1)
    rec.visibility_method = "magic"
    with pytest.raises(SchemaError, match="visibility_method"):
        rec.validate()
    rec = make_record("f", 5, 1)
    rec.meta = {"x": float("nan")}
    with pytest.raises(SchemaError, match="meta"):
        rec.validate()


def test_duplicate_face_id_rejected(tmp_path):
    with ShardWriter(tmp_path) as writer:
        writer.write(make_record("same", 3, 1))
        with pytest.raises(SchemaError, match="duplicate"):
            writer.write(make_record("same", 4, 2))
    assert count_records(tmp_path) == 1


def test_existing_shards_need_overwrite(tmp_path):
    with ShardWriter(tmp_path, records_per_shard=1) as writer:
        for i in range(3):
            writer.write(make_record(f"f{i}", 3, i))
    with pytest.raises(FileExistsError):
        ShardWriter(tmp_path)
    with ShardWriter(tmp_path, records_per_shard=1, overwrite=True) as writer:
        writer.write(make_record("g", 3, 9))
    assert [p.name for p in sorted(tmp_path.glob("*.parquet"))] == ["part-00000.parquet"]
    assert [r.face_id for r in iter_records(tmp_path)] == ["g"]


# -- corruption and atomicity ----------------------------------------------------------------
def test_corrupt_file_yields_one_bad_record(tmp_path):
    with ShardWriter(tmp_path, records_per_shard=2) as writer:
        for i in range(4):
            writer.write(make_record(f"good-{i}", 5 + i, i))
    # a corrupt file sorted between the good ones
    corrupt = tmp_path / "part-00000b.parquet"
    corrupt.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    out = list(iter_records(tmp_path))
    bad = [r for r in out if isinstance(r, BadRecord)]
    good = [r for r in out if isinstance(r, FaceRecord)]
    assert len(bad) == 1 and bad[0].source == str(corrupt) and bad[0].face_id is None
    assert corrupt.name in str(bad[0])
    assert [r.face_id for r in good] == [f"good-{i}" for i in range(4)]
    assert count_records(tmp_path) == 4


def test_truncated_file_yields_bad_record(tmp_path):
    with ShardWriter(tmp_path, records_per_shard=2) as writer:
        for i in range(4):
            writer.write(make_record(f"g{i}", 5, i))
    first = tmp_path / "part-00000.parquet"
    first.write_bytes(first.read_bytes()[: first.stat().st_size // 2])
    out = list(iter_records(tmp_path))
    assert isinstance(out[0], BadRecord) and out[0].source == str(first)
    assert [r.face_id for r in out if isinstance(r, FaceRecord)] == ["g2", "g3"]


def test_writer_exception_keeps_finished_shards_and_no_tmp(tmp_path):
    with pytest.raises(RuntimeError), ShardWriter(tmp_path, records_per_shard=2) as writer:
        for i in range(3):
            writer.write(make_record(f"f{i}", 4, i))
        raise RuntimeError("killed")
    assert [p.name for p in tmp_path.iterdir()] == ["part-00000.parquet"]
    assert [r.face_id for r in iter_records(tmp_path)] == ["f0", "f1"]


def test_side_photo_atomic(tmp_path):
    img = np.random.default_rng(0).integers(0, 256, (12, 9, 3), dtype=np.uint8)
    rel = write_side_photo(tmp_path, "face-1", img)
    assert rel == "photos/face-1.png"
    from PIL import Image

    np.testing.assert_array_equal(np.asarray(Image.open(tmp_path / rel)), img)
    assert not [p for p in tmp_path.rglob("*") if ".tmp" in p.name]
    with pytest.raises(SchemaError):
        write_side_photo(tmp_path, "../evil", img)


def test_side_probe_round_trip(tmp_path):
    pytest.importorskip("f2l.io.exr")
    from f2l.io.side_files import load_gt_probe, write_side_probe

    probe = np.random.default_rng(1).random((8, 16, 3)).astype(np.float32) * 1e6
    rel = write_side_probe(tmp_path, "face-2", probe)
    assert rel == "probes/face-2.exr"
    rec = make_record("face-2", 3, 1)
    rec.gt_probe_path = rel
    np.testing.assert_array_equal(load_gt_probe(tmp_path, rec), probe)
    rec.gt_probe_path = None
    assert load_gt_probe(tmp_path, rec) is None
    assert not [p for p in tmp_path.rglob("*") if ".tmp" in p.name]


# -- results tables --------------------------------------------------------------------------
def estimate_row(face_id: str, status: str = "ok", **over) -> dict:
    row = {
        "face_id": face_id, "source_path": "x.jpg", "model": "sunsky", "model_version": "1.0",
        "params": np.arange(10, dtype=np.float64), "param_names": [f"p{i}" for i in range(10)],
        "albedo": [0.5, 0.4, 0.3], "ground_albedo": 0.2, "sun_direction": [0.0, 0.6, -0.8],
        "loss": 1.5e-3, "iterations": 42,
        "converged": True, "status": status, "message": "", "runtime_s": 3.2,
        "probe_path": f"probes/{face_id}.exr", "preview_path": None,
        "grid_height": 64, "grid_width": 128, "config_hash": "abc123",
        "timings_json": json.dumps({"fit": 3.0}),
        "absolute_scale_cd_m2": None, "absolute_scale_source": "relative (no absolute scale: the record holds no EXIF)",
        "group_id": "", "group_size": 1, "group_used": None, "agreement": None, "face_weight": None,
        "exposure_gain": None, "sun_cone68_deg": 4.0, "sun_cone90_deg": 7.5, "predicted_mae_s": 0.12,
    }
    row.update(over)
    return row


def test_parquet_appender_estimates(tmp_path):
    path = tmp_path / "estimates.parquet"
    with ParquetAppender(path, "estimates", rows_per_group=3) as app:
        for i in range(7):
            app.append(estimate_row(f"f{i}"))
        app.append(estimate_row("failed", status="no_face", message="no face found", params=[],
                                albedo=[], ground_albedo=None, loss=None, converged=False))
        # an unreadable record: no face id, no grid, no config (batch of one row)
        app.append([estimate_row("", status="bad_record", message="corrupt", params=[],
                                 param_names=[], albedo=[], sun_direction=None,
                                 grid_height=0, grid_width=0, config_hash="")])
        with pytest.raises(SchemaError, match="sun_direction"):
            app.append(estimate_row("nonunit", sun_direction=[1.0, 1.0, 0.0]))
        with pytest.raises(SchemaError, match="face_id='short'.*params"):
            app.append(estimate_row("short", params=[1.0, 2.0]))
        with pytest.raises(SchemaError, match="timings_json"):
            app.append(estimate_row("badjson", timings_json="[1, 2]"))
        assert not path.exists()
    assert not list(tmp_path.glob("*.tmp"))
    pf = pq.ParquetFile(path)
    assert pf.metadata.num_rows == 9 and pf.metadata.num_row_groups == 3
    table = pf.read()
    validate_table(table, "estimates", source=str(path))
    assert table.column("face_id").to_pylist()[-2:] == ["failed", ""]
    assert table.column("sun_direction").to_pylist()[-1] is None
    assert table.column("params")[0].values.to_numpy().tolist() == list(range(10))


def test_parquet_appender_abort_leaves_nothing(tmp_path):
    path = tmp_path / "estimates.parquet"
    with pytest.raises(KeyError), ParquetAppender(path, "estimates") as app:
        app.append(estimate_row("a"))
        raise KeyError("boom")
    assert list(tmp_path.iterdir()) == []


def test_ok_rows_need_full_arrays():
    from f2l.io.shards import rows_to_table

    table = rows_to_table([estimate_row("a", params=[], albedo=[])], "estimates")
    errors = table_errors(table, "estimates", source="t")
    assert any("params" in e for e in errors) and any("albedo" in e for e in errors)


def test_write_table_atomic(tmp_path):
    from f2l.io.shards import rows_to_table

    table = rows_to_table([estimate_row("a"), estimate_row("b")], "estimates")
    path = write_table_atomic(table, tmp_path / "out" / "estimates.parquet", "estimates")
    assert path.exists() and pq.read_table(path).num_rows == 2
    assert [p.name for p in path.parent.iterdir()] == ["estimates.parquet"]
    bad = table.drop_columns(["loss"])
    with pytest.raises(SchemaError, match="missing column 'loss'"):
        write_table_atomic(bad, tmp_path / "bad.parquet", "estimates")
    assert not (tmp_path / "bad.parquet").exists()


def test_iter_records_without_validation_and_file_list(tmp_path):
    good = make_record("ok-1", 4, 1)
    with ShardWriter(tmp_path / "a") as writer:
        writer.write(good)
    table, _ = _bad_tables()["inconsistent_lengths"]
    write_raw(table, tmp_path / "b.parquet")
    files = [tmp_path / "a", tmp_path / "b.parquet"]  # a directory and a file, in list order
    out = list(iter_records(files, validate=False))
    assert isinstance(out[0], FaceRecord) and out[0].face_id == "ok-1"
    assert isinstance(out[1], BadRecord) and out[1].face_id == "bad-face"
    assert "cannot decode" in out[1].reason
    assert count_records(files) == 2
