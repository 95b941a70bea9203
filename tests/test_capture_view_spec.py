"""The view spec (issue 41, item 4 "Typed specs, validated once"): the ``view_json`` column of
captures.parquet is encoded and decoded in one place (:class:`f2l.capture.view_spec.ViewSpec`),
round-trips exactly, refuses an invalid description naming the key, and reads the text that
ingest wrote before the spec existed unchanged (so old tables load and cache keys hold)."""

from __future__ import annotations

import doctest
import json
from datetime import datetime
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from f2l.capture import view_spec
from f2l.capture.view_spec import FalloffSpec, LensSpec, ViewSpec, ViewSpecError

SESSION_TOML = """probe_azimuth_deg = 30
[lens]
projection = "equisolid"
fov_deg = 180
principal_point_px = [16, 12.5]
falloff = {model = "flat_field", file = "cal/flat.exr"}
[[shots]]
files = "sky/frame_*"
yaw_deg = 90.0
pitch_deg = 80
roll_deg = -5.5
role = "sky_bracket"
[[shots]]
files = "sky/poly_*"
pitch_deg = 45.0
colmap_model = "OPENCV_FISHEYE"
colmap_params = [10, 10.5, 16, 12, 0.01, 0, 0, 0]
max_angle_deg = 95.5
falloff = {model = "polynomial", coefficients = [-0.2, 0, 0.05], radius = "half_diagonal"}
[[shots]]
files = "faces/*"
role = "face"
vignetting = [-0.1]
"""

FLAT = '"falloff": {"file": "s1/cal/flat.exr", "model": "flat_field", "sha256": "SHA"}'
OLD_VIEW_JSON = {
    # what f2l ingest wrote for SESSION_TOML before the view spec (commit 6027a5b), SHA standing
    # for the flat field's SHA-256
    "s1/cal/flat.exr": "{" + FLAT + ', "fov_deg": 180, "principal_point_px": [16, 12.5], "probe_azimuth_deg": 30, '
                       '"projection": "equisolid"}',
    "s1/faces/a.png": "{" + FLAT + ', "fov_deg": 180, "principal_point_px": [16, 12.5], "probe_azimuth_deg": 30, '
                      '"projection": "equisolid", "role": "face", "vignetting": [-0.1]}',
    "s1/sky/frame_00.dng": "{" + FLAT + ', "fov_deg": 180, "pitch_deg": 80, "principal_point_px": [16, 12.5], '
                           '"probe_azimuth_deg": 30, "projection": "equisolid", "role": "sky_bracket", '
                           '"roll_deg": -5.5, "yaw_deg": 90.0}',
    "s1/sky/poly_00.dng": '{"colmap_model": "OPENCV_FISHEYE", "colmap_params": [10, 10.5, 16, 12, 0.01, 0, 0, 0], '
                          '"falloff": {"coefficients": [-0.2, 0, 0.05], "model": "polynomial", "radius": '
                          '"half_diagonal"}, "fov_deg": 180, "max_angle_deg": 95.5, "pitch_deg": 45.0, '
                          '"principal_point_px": [16, 12.5], "probe_azimuth_deg": 30, "projection": "equisolid"}',
    "outside": '{"falloff": {"allow_outside": true, "file": "/data/cal/flat.exr", "model": "flat_field", '
               '"sha256": "SHA"}, "fov_deg": 180.0, "pitch_deg": 90.0, "probe_azimuth_deg": 90.0, '
               '"projection": "equidistant"}',
    "empty": "{}",
}


def _tree(root: Path) -> None:
    from f2l.capture.dng import write_bracket
    from f2l.io.exr import write_exr

    scene = (0.05 + 0.2 * np.random.default_rng(0).random((24, 32, 3))).astype(np.float32)
    (root / "s1" / "sky").mkdir(parents=True)
    write_bracket(root / "s1" / "sky", scene, [1 / 1000, 1 / 250, 1 / 60], seed=1, timestamp=datetime(2024, 6, 21, 12))
    write_bracket(root / "s1" / "sky", scene, [1 / 1000, 1 / 250, 1 / 60], seed=2, prefix="poly",
                  timestamp=datetime(2024, 6, 21, 12, 1))
    (root / "s1" / "cal").mkdir()
    write_exr(root / "s1" / "cal" / "flat.exr", np.ones((24, 32, 3), np.float32))
    (root / "s1" / "faces").mkdir()
    (root / "s1" / "faces" / "a.png").write_bytes(b"not a png")
    (root / "s1" / "session.toml").write_text(SESSION_TOML)


@pytest.fixture(scope="module")
def ingested(tmp_path_factory):
    from f2l.capture.manifest import run_ingest
    from f2l.io.hashing import file_sha256

    base = tmp_path_factory.mktemp("view_spec")
    _tree(base / "raw")
    run_ingest(base / "raw", base / "work", detect_roles=False)
    rows = {r["path"]: r for r in pq.read_table(base / "work" / "captures.parquet").to_pylist()}
    return base, rows, file_sha256(base / "raw" / "s1" / "cal" / "flat.exr")


def test_doctests():
    result = doctest.testmod(view_spec, optionflags=doctest.ELLIPSIS)
    assert result.attempted > 0 and result.failed == 0


def test_spec_to_json_to_spec_is_identical():
    spec = ViewSpec(LensSpec(projection="equisolid", fov_deg=180, principal_point_px=(16, 12.5),
                             colmap_model="OPENCV_FISHEYE", colmap_params=(10, 10.5, 16, 12, 0.01, 0, 0, 0),
                             focal_length_mm=8.0, sensor_width_mm=36, image_circle_radius_px=150,
                             max_angle_deg=95.5, vignetting=(-0.1,),
                             falloff=FalloffSpec("flat_field", file="/x/flat.exr", sha256="ab" * 32,
                                                 allow_outside=True)),
                    yaw_deg=-90, pitch_deg=80.0, roll_deg=-5.5, role="sky_bracket", probe_azimuth_deg=30)
    text = spec.to_json()
    again = ViewSpec.from_json(text)
    assert again == spec and again.to_json() == text
    assert type(again.lens.fov_deg) is int and type(again.pitch_deg) is float  # values as written
    assert ViewSpec.from_json("") == ViewSpec.from_json(None) == ViewSpec.from_json("{}") == ViewSpec()
    assert ViewSpec().to_json() == "{}"


@pytest.mark.parametrize("name", sorted(OLD_VIEW_JSON))
def test_text_written_before_the_spec_reads_back_unchanged(name):
    text = OLD_VIEW_JSON[name].replace("SHA", "0f" * 32)
    spec = ViewSpec.from_json(text)
    assert spec.to_json() == text  # the column's text, hence the merge/sphere cache keys, unchanged
    assert spec.as_dict() == json.loads(text)


def test_ingest_writes_the_text_it_wrote_before(ingested):
    _, rows, sha = ingested
    for path, text in OLD_VIEW_JSON.items():
        if path in rows:
            assert rows[path]["view_json"] == text.replace("SHA", sha), path
    frames = [rows[f"s1/sky/frame_0{i}.dng"] for i in range(3)]
    assert {r["bracket_id"] for r in frames} == {"s1/frame_00"} and rows["s1/sky/poly_00.dng"]["bracket_id"]
    assert ViewSpec.from_json(rows["s1/faces/a.png"]["view_json"]).role == "face"
    spec = ViewSpec.from_json(frames[0]["view_json"])
    assert spec.lens.falloff.file == "s1/cal/flat.exr" and spec.lens.falloff.sha256 == sha
    assert spec.pose == {"yaw_deg": 90.0, "pitch_deg": 80, "roll_deg": -5.5} and spec.role == "sky_bracket"


def test_a_table_written_before_the_spec_still_loads(ingested, tmp_path):
    """captures.parquet with the old code's view_json (literal) goes through make-probes' and
    build-dataset's readers: both brackets placed, the session's probe azimuth read."""
    import shutil

    from f2l.capture.probes import make_probes
    from f2l.io.tables import rows_to_table, write_table_atomic
    from f2l.pipeline.plan import SessionPlan

    base, rows, sha = ingested
    old = [dict(r, view_json=OLD_VIEW_JSON.get(p.replace("_01", "_00").replace("_02", "_00"), "{}").replace("SHA", sha))
           for p, r in sorted(rows.items())]
    work = tmp_path / "work"
    work.mkdir()
    write_table_atomic(rows_to_table(old, "captures"), work / "captures.parquet", "captures")
    summary = make_probes(base / "raw", work, grid_height=16)
    table = pq.read_table(work / "probes.parquet").to_pylist()
    assert summary.views == 2 and summary.probes == 1, table
    assert all(r["status"] == "ok" for r in table), table
    loaded = pq.read_table(work / "captures.parquet").to_pylist()
    plan = SessionPlan("s1", brackets={"s1/frame_00": [r for r in loaded if r["bracket_id"] == "s1/frame_00"]})
    assert plan.probe_azimuth_deg == 30.0 and plan.probe_azimuth_problem is None
    shutil.rmtree(work)


@pytest.mark.parametrize("text, key", [
    ('{"projection": "fisheye"}', "projection"),
    ('{"projection": "equidistant", "focal_length_px": "wide"}', "focal_length_px"),
    ('{"fov_deg": -180}', "fov_deg"),
    ('{"fov_deg": true}', "fov_deg"),
    ('{"sensor_width_mm": Infinity}', "sensor_width_mm"),
    ('{"principal_point_px": [1, 2, 3]}', "principal_point_px"),
    ('{"colmap_model": 7}', "colmap_model"),
    ('{"colmap_params": []}', "colmap_params"),
    ('{"colmap_params": [1, NaN]}', "colmap_params"),
    ('{"vignetting": [0.1, 0.1, 0.1, 0.1]}', "vignetting"),
    ('{"falloff": {"model": "gaussian"}}', "falloff"),
    ('{"falloff": {"coefficients": [0.1]}}', "falloff"),
    ('{"falloff": {"model": "polynomial", "radius": "huge"}}', "falloff"),
    ('{"falloff": {"model": "flat_field", "file": "f.exr", "mtime": 3}}', "falloff"),
    ('{"falloff": "cos4"}', "falloff"),
    ('{"pitch_deg": NaN}', "pitch_deg"),
    ('{"yaw_deg": "north"}', "yaw_deg"),
    ('{"roll_deg": 200}', "roll_deg"),
    ('{"probe_azimuth_deg": 1e999}', "probe_azimuth_deg"),
    ('{"role": "sky"}', "role"),
    ('{"zoom": 2}', "zoom"),
    ('[1, 2]', ""),
    ('{"projection": ', ""),
])
def test_an_invalid_view_names_the_key(text, key):
    with pytest.raises(ViewSpecError) as err:
        ViewSpec.from_json(text)
    assert err.value.key == key
    assert (key or "view") in str(err.value)


def test_a_lens_that_cannot_place_the_frame_is_a_lens_error_naming_the_key():
    from f2l.capture.lens import LensError, lens_of

    spec = ViewSpec.from_json('{"projection": "equidistant", "focal_length_px": 1e308}')  # valid, implausible
    with pytest.raises(LensError) as err:
        lens_of(spec.lens, 96, 96)
    assert err.value.key == "focal_length_px" and isinstance(err.value, ViewSpecError)


def test_placement_key_ignores_role_and_probe_azimuth():
    a = ViewSpec.from_json('{"fov_deg": 180, "pitch_deg": 90, "projection": "equidistant", "role": "sky_bracket"}')
    b = ViewSpec.from_json('{"fov_deg": 180, "pitch_deg": 90, "probe_azimuth_deg": 5, "projection": "equidistant"}')
    c = ViewSpec.from_json('{"fov_deg": 180, "pitch_deg": 45, "projection": "equidistant"}')
    assert a.placement_key() == b.placement_key() != c.placement_key()
    assert c.pose_deg() == {"yaw_deg": 0.0, "pitch_deg": 45.0, "roll_deg": 0.0}


def test_a_non_finite_probe_azimuth_is_a_plan_problem():
    from f2l.pipeline.plan import SessionPlan

    plan = SessionPlan("s", faces=[{"path": "s/a.png", "view_json": '{"probe_azimuth_deg": NaN}'}])
    assert plan.probe_azimuth_deg is None
    assert "probe_azimuth_deg" in plan.probe_azimuth_problem and "finite" in plan.probe_azimuth_problem
