"""The Sun+Sky evaluation harness: sun-elevation range of `f2l synth`, sun energy shares per face,
medians and the overcast sun-share excess in the summary."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from f2l.lighting.grid import LatLongGrid, direction_from_angles
from f2l.metrics import summarise, summary_records, to_csv, to_markdown
from f2l.metrics.sun_share import OvercastExcess, overcast_excess, sun_shares
from f2l.synth.render import make_synthetic_set
from f2l.synth.skies import (
    SUN_ELEVATION_RANGE_DEG,
    overcast_sky,
    parse_elevation_range,
    random_sky,
    sun_lobe_energy,
)

TINY = LatLongGrid(16, 32)
SMALL = LatLongGrid(32, 64)


def _sky_meta(shard_dir):
    from f2l.io.shards import iter_records

    return [r.meta["sky"] for r in iter_records(shard_dir)]


# -- sun elevation range ------------------------------------------------------------------------
def test_parse_elevation_range():
    assert parse_elevation_range("10:70") == (10.0, 70.0)
    assert parse_elevation_range("5:80") == SUN_ELEVATION_RANGE_DEG
    for bad in ("70:10", "10", "a:b", "-5:30", "10:95", "1:2:3"):
        with pytest.raises(ValueError, match="sun elevation range"):
            parse_elevation_range(bad)


def test_random_sky_honours_elevation_range():
    elevations = []
    for seed in range(40):
        _, info = random_sky(TINY, np.random.default_rng(seed), 0.0, sun_elevation_range_deg=(10.0, 70.0))
        assert info["kind"] == "clear"
        elevations.append(info["sun_elevation_deg"])
        np.testing.assert_allclose(info["sun_direction"][1], math.sin(math.radians(info["sun_elevation_deg"])))
    assert min(elevations) >= 10.0 and max(elevations) <= 70.0
    assert max(elevations) - min(elevations) > 30.0  # the range is used, not a point


def test_default_elevation_range_keeps_the_stream():
    for seed in range(8):
        default_rng, explicit_rng, narrow_rng = (np.random.default_rng(seed) for _ in range(3))
        p0, i0 = random_sky(TINY, default_rng, 0.5)
        p1, i1 = random_sky(TINY, explicit_rng, 0.5, sun_elevation_range_deg=(5.0, 80.0))
        _, i2 = random_sky(TINY, narrow_rng, 0.5, sun_elevation_range_deg=(40.0, 41.0))
        assert np.array_equal(p0, p1) and i0 == i1
        # every range draws the same numbers: the generators end in the same state
        assert default_rng.bit_generator.state == narrow_rng.bit_generator.state
        assert i2["kind"] == i0["kind"]
        # the documented draw order: kind, elevation U[5, 80], azimuth U[-180, 180)
        ref = np.random.default_rng(seed)
        ref.uniform()
        elev, az = ref.uniform(5.0, 80.0), ref.uniform(-180.0, 180.0)
        if i0["kind"] == "clear":
            assert i0["sun_elevation_deg"] == elev and i0["sun_azimuth_deg"] == az
            assert i2["sun_azimuth_deg"] == az and 40.0 <= i2["sun_elevation_deg"] <= 41.0


def test_synthetic_set_range_changes_only_the_elevation():
    kw = dict(image_size=32, overcast_fraction=0.0, noise_sigma=0.002)
    default = list(make_synthetic_set(2, TINY, 11, **kw))
    explicit = list(make_synthetic_set(2, TINY, 11, sun_elevation_range_deg=(5.0, 80.0), **kw))
    narrow = list(make_synthetic_set(2, TINY, 11, sun_elevation_range_deg=(60.0, 62.0), **kw))
    for a, b, c in zip(default, explicit, narrow):
        assert np.array_equal(a.photo_srgb, b.photo_srgb) and np.array_equal(a.gt_probe, b.gt_probe)
        assert a.meta == b.meta
        assert a.meta["pose_deg"] == c.meta["pose_deg"] and np.array_equal(a.albedo, c.albedo)
        assert a.meta["sky"]["sun_azimuth_deg"] == c.meta["sky"]["sun_azimuth_deg"]
        assert 60.0 <= c.meta["sky"]["sun_elevation_deg"] <= 62.0


def test_synth_cli_elevation_option(tmp_path):
    from typer.testing import CliRunner

    from f2l.cli import app

    runner = CliRunner()
    args = ["eval", "synth", "--n", "3", "--seed", "4", "--grid", "16x32", "--image-size", "32",
            "--overcast-fraction", "0", "--json"]
    res = runner.invoke(app, [*args, "--out", str(tmp_path / "s"), "--sun-elevation-deg", "60:62"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output)["faces"] == 3
    skies = _sky_meta(tmp_path / "s")
    assert len(skies) == 3
    for sky in skies:
        assert sky["kind"] == "clear" and 60.0 <= sky["sun_elevation_deg"] <= 62.0
    bad = runner.invoke(app, [*args, "--out", str(tmp_path / "bad"), "--sun-elevation-deg", "70:10"])
    assert bad.exit_code == 2 and "--sun-elevation-deg" in bad.output
    assert not (tmp_path / "bad").exists()


# -- sun energy shares ---------------------------------------------------------------------------
def _overcast_with_sun(grid, sun_to_sky=1.0, elevation_deg=45.0, azimuth_deg=30.0):
    """Overcast sky plus a white sun whose upper-hemisphere energy is ``sun_to_sky`` times the
    sky's; returns (probe, the sun's own share sun_to_sky / (1 + sun_to_sky)). The probe's sun
    share is a little larger: its 13° cap also holds some sky."""
    sky = overcast_sky(grid).astype(np.float64)
    upper = grid.upper_mask[..., None]
    sky_energy = float(np.sum(sky * upper * grid.solid_angles[..., None]))
    d = direction_from_angles(math.radians(elevation_deg), math.radians(azimuth_deg))
    lobe = sun_lobe_energy(grid, d, 8192.0)
    probe = sky + (sun_to_sky * sky_energy / 3.0) * lobe[..., None] * upper
    return probe, sun_to_sky / (1.0 + sun_to_sky)


def test_sun_shares_analytic():
    gt = overcast_sky(SMALL).astype(np.float64)
    same = sun_shares(2.0 * gt, gt, SMALL)  # scale-invariant: an exact (rescaled) estimate
    assert same["sun_share_est"] == pytest.approx(same["sun_share_gt"], abs=1e-12)
    assert 0.0 < same["sun_share_gt"] < 0.06  # a 13° cap of a smooth overcast sky
    one = np.zeros(SMALL.shape + (3,))
    one[5, 7] = 1.0
    assert sun_shares(one, gt, SMALL)["sun_share_est"] == pytest.approx(1.0)
    sunny, lower = _overcast_with_sun(SMALL, sun_to_sky=1.0)
    s = sun_shares(sunny, gt, SMALL)
    assert lower - 0.01 < s["sun_share_est"] < lower + 0.06
    assert s["sun_share_est"] - s["sun_share_gt"] > 0.4


# -- summary: medians and the overcast excess -------------------------------------------------------
def _rows():
    nan = float("nan")

    def row(model, ang, overcast, est, gt):
        return {"model": model, "Sun-ang (°)": ang, "runtime_s": 1.0, "gt_overcast": overcast,
                "sun_share_est": est, "sun_share_gt": gt}

    return [
        row("sunsky", 10.0, False, 0.9, 0.3),  # clear: its large excess is not counted
        row("sunsky", 40.0, False, 0.8, 0.7),
        row("sunsky", 20.0, False, 0.6, 0.6),
        row("sunsky", nan, True, 0.08, 0.03),  # excess 0.05
        row("sunsky", nan, True, 0.18, 0.03),  # 0.15 > 0.1
        row("sunsky", nan, True, 0.33, 0.03),  # 0.30 > 0.1
        row("sunsky", nan, True, nan, 0.03),  # no estimate share: left out
        row("sh25", 30.0, False, 0.2, 0.5),
        row("sh25", nan, True, 0.03, 0.03),
        row("clear-only", 5.0, False, 0.5, 0.4),
    ]


def test_overcast_excess_counts():
    o = overcast_excess([r for r in _rows() if r["model"] == "sunsky"])
    assert (o.n, o.exceed) == (3, 2)
    assert o.fraction == pytest.approx(2 / 3) and o.max_excess == pytest.approx(0.30)
    empty = overcast_excess([r for r in _rows() if r["model"] == "clear-only"])
    assert (empty.n, empty.exceed) == (0, 0) and math.isnan(empty.fraction) and math.isnan(empty.max_excess)
    # only a real bool flags a face as overcast (a CSV string "False" must not count)
    assert overcast_excess([{"gt_overcast": "False", "sun_share_est": 0.9, "sun_share_gt": 0.0}]).n == 0
    assert overcast_excess([{"gt_overcast": np.bool_(True), "sun_share_est": 0.9, "sun_share_gt": 0.0}]).exceed == 1


def test_summary_median_and_overcast_excess(tmp_path):
    t = summarise(_rows())
    assert t.metrics == ["Sun-ang (°)", "runtime_s"] and t.medians == ["Sun-ang (°)"]
    ang = t.groups["sunsky"]["Sun-ang (°)"]
    assert (ang.count, ang.median) == (3, 20.0) and ang.mean == pytest.approx(70.0 / 3)
    assert t.overcast["sunsky"] == OvercastExcess(3, 2, pytest.approx(0.30))
    assert t.overcast["sh25"] == OvercastExcess(1, 0, pytest.approx(0.0))
    assert t.overcast["clear-only"].n == 0

    md = to_markdown(t)
    assert "| model | n | Sun-ang (°) | runtime_s | median Sun-ang (°) | overcast: est sun share > gt + 0.1 |" in md
    assert "| 20 | 2/3 (67%) | 0.3 |" in md
    assert "| 30 | 0/1 (0%) | 0 |" in md
    assert "| clear-only | 1 | 5 | 1 | 5 | — | — |" in md

    with open(to_csv(t, tmp_path / "s.csv"), encoding="utf-8") as f:
        got = {r["model"]: r for r in csv.DictReader(f)}
    assert float(got["sunsky"]["Sun-ang (°) median"]) == 20.0
    assert got["sunsky"]["overcast n"] == "3" and got["sunsky"]["overcast sun share excess count"] == "2"
    assert float(got["sunsky"]["overcast sun share excess fraction"]) == pytest.approx(2 / 3)
    assert float(got["sunsky"]["overcast sun share excess max"]) == pytest.approx(0.30)
    assert got["clear-only"]["overcast sun share excess max"] == "nan"
    assert [r["model"] for r in summary_records(t)] == ["sunsky", "sh25", "clear-only"]


def test_summary_without_sun_shares_has_no_overcast_columns():
    t = summarise([{"model": "m", "MAE (s)": 1.0}, {"model": "m", "MAE (s)": 3.0}])
    assert t.overcast == {} and t.medians == []
    assert to_markdown(t).splitlines()[0] == "| model | n | MAE (s) |"
    assert t.groups["m"]["MAE (s)"].median == 2.0


# -- f2l evaluate end to end on analytic estimates ------------------------------------------------------
def _write_estimates(out, probes_by_model):
    """An estimates directory as `f2l estimate` writes it, with the given probes (face_id -> probe)."""
    from f2l.estimate.runner import ESTIMATES_FILE
    from f2l.io.exr import write_exr

    rows = []
    for model, probes in probes_by_model.items():
        for face_id, probe in probes.items():
            rel = f"probes/{model}-{face_id}.exr"
            (out / "probes").mkdir(parents=True, exist_ok=True)
            write_exr(out / rel, np.asarray(probe, np.float32))
            rows.append({"face_id": face_id, "model": model, "status": "ok", "probe_path": rel,
                         "grid_height": TINY.height, "grid_width": TINY.width, "runtime_s": 0.5,
                         "sun_direction": None})
    pq.write_table(pa.Table.from_pylist(rows), out / ESTIMATES_FILE)


def test_evaluate_sun_share_columns_and_overcast_excess(tmp_path):
    from f2l.io.exr import read_exr
    from f2l.io.shards import iter_records
    from f2l.metrics.evaluate import evaluate_estimates
    from f2l.synth.dataset import write_synthetic_shards

    shards = tmp_path / "shards"
    write_synthetic_shards(shards, n=2, seed=5, grid=TINY, image_size=32, overcast_fraction=1.0, progress=False)
    gts = {r.face_id: read_exr(shards / r.gt_probe_path) for r in iter_records(shards)}
    sunny = {fid: _overcast_with_sun(TINY, 1.0)[0] for fid in gts}
    est_dir = tmp_path / "est"
    _write_estimates(est_dir, {"exact": gts, "sunny": sunny})

    result = evaluate_estimates(est_dir, [shards])
    with open(result["per_face_csv"], encoding="utf-8") as f:
        reader = csv.DictReader(f)
        at = reader.fieldnames.index("gt_overcast")
        assert reader.fieldnames[at:at + 3] == ["gt_overcast", "sun_share_est", "sun_share_gt"]
        assert reader.fieldnames[-3:] == ["sun_cone68_deg", "sun_cone90_deg", "predicted_mae_s"]
        per_face = list(reader)
    assert len(per_face) == 4 and all(r["gt_overcast"] == "True" for r in per_face)
    for r in per_face:
        est, gt = float(r["sun_share_est"]), float(r["sun_share_gt"])
        assert 0.0 < gt < 0.06
        if r["model"] == "exact":
            assert est == gt
        else:
            assert est - gt > 0.3

    summary = result["summary"]
    assert summary.overcast["exact"] == OvercastExcess(2, 0, 0.0)
    assert (summary.overcast["sunny"].n, summary.overcast["sunny"].exceed) == (2, 2)
    assert "| 0/2 (0%) | 0 |" in result["markdown"] and "2/2 (100%)" in result["markdown"]
    # JSON-ready records: overcast faces have no sun angle, reported as null rather than NaN
    rec = {r["model"]: r for r in result["summary_rows"]}
    assert rec["sunny"]["overcast sun share excess count"] == 2
    assert rec["exact"]["Sun-ang (°) median"] is None
    json.dumps(result["summary_rows"], allow_nan=False)
