"""Bulk estimation: reruns skip finished faces, a killed run resumes from its parts, and the Ray
executor gives the local executor's results."""

from __future__ import annotations

import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest

from f2l.estimate.resume import PARTS_DIR
from f2l.estimate.runner import run_estimates
from f2l.io.tables import rows_to_table, write_table_atomic


def _rows(out) -> dict:
    return {(r["face_id"], r["model"]): r for r in pq.read_table(out / "estimates.parquet").to_pylist()}


@pytest.fixture(scope="module")
def first_run(small_shards, tmp_path_factory):
    out = tmp_path_factory.mktemp("est")
    summary = run_estimates([small_shards], ["sh9"], out, workers=1, threads=1, progress=False)
    return out, summary


def test_rerun_skips_what_is_done(first_run, small_shards, tmp_path):
    out, summary = first_run
    assert summary["ok"] == 4 and summary["skipped_done"] == 0
    before = _rows(out)
    ids = [k[0] for k in sorted(before)]
    assert ids == sorted(ids)  # rows sorted by (face_id, model)
    again_dir = tmp_path / "again"
    shutil.copytree(out, again_dir)
    again = run_estimates([small_shards], ["sh9"], again_dir, workers=1, threads=1, progress=False)
    assert again["total"] == 0 and again["skipped_done"] == 4
    after = _rows(again_dir)
    assert after.keys() == before.keys()
    for k in before:
        assert after[k]["params"] == before[k]["params"] and after[k]["status"] == "ok"
    assert not (again_dir / PARTS_DIR).exists()
    # another configuration of the same model is not "done"
    other = run_estimates([small_shards], ["sh9"], again_dir, workers=1, threads=1, progress=False,
                          max_iter=5, max_pixels=500)
    assert other["skipped_done"] == 0 and other["ok"] == 4


def test_killed_run_resumes_from_its_parts(first_run, small_shards, tmp_path):
    out, _ = first_run
    full = _rows(out)
    keys = sorted(full)
    # what a run killed after two faces leaves: no table, one published part with two rows
    killed = tmp_path / "killed"
    (killed / PARTS_DIR).mkdir(parents=True)
    part = rows_to_table([full[k] for k in keys[:2]], "estimates")
    write_table_atomic(part, killed / PARTS_DIR / "part-000000.parquet", "estimates")
    (killed / PARTS_DIR / "part-000001.parquet.123.tmp").write_bytes(b"half a part")  # torn write
    resumed = run_estimates([small_shards], ["sh9"], killed, workers=1, threads=1, progress=False)
    assert resumed["skipped_done"] == 2 and resumed["ok"] == 2
    rows = _rows(killed)
    assert rows.keys() == full.keys()
    for k in keys[:2]:  # the part's rows, read back as written
        assert rows[k]["params"] == full[k]["params"]
    for k in keys[2:]:  # refitted: equal to rounding as amplified by the fit (test_ray_executor_matches_local)
        np.testing.assert_allclose(rows[k]["params"], full[k]["params"], rtol=1e-4,
                                   atol=1e-4 * np.abs(full[k]["params"]).max())
    assert not (killed / PARTS_DIR).exists()


def test_ray_executor_matches_local(first_run, small_shards, tmp_path):
    pytest.importorskip("ray", reason="the 'ray' extra is not installed")
    out, _ = first_run
    local = _rows(out)
    summary = run_estimates([small_shards], ["sh9"], tmp_path / "ray", workers=2, threads=1,
                            progress=False, executor="ray")
    assert summary["executor"] == "ray" and summary["ok"] == 4
    rows = _rows(tmp_path / "ray")
    assert rows.keys() == local.keys()
    for k in local:
        # The same sh9 fit in another process, whose BLAS may take other threads and kernels: both
        # run the same capped IRLS iterations (these faces stop at the caps, not at the 1e-6 rule), a
        # contraction, so rounding moves theta as input noise does: +-1 ulp on every float32 input
        # moves it by <= 6e-6 max|theta| (elementwise up to 1.2e-4 on small coefficients: hence atol).
        np.testing.assert_allclose(rows[k]["params"], local[k]["params"], rtol=1e-4,
                                   atol=1e-4 * np.abs(local[k]["params"]).max())
        assert (tmp_path / "ray" / rows[k]["probe_path"]).is_file()


def test_scale_report_measures_each_size_in_its_own_process():
    from f2l.estimate.scale import format_table, run_scale_report

    rows = run_scale_report((1, 2), model="sh9", image_size=64, grid=(16, 32))
    assert [r["faces"] for r in rows] == [1, 2] and [r["ok"] for r in rows] == [1, 2]
    for r in rows:
        assert r["build_s"] > 0 and r["estimate_s"] > 0 and r["faces_per_min"] > 0
        assert r["build_peak_mib"] > 0 and r["estimate_peak_mib"] > 0 and r["base_mib"] > 0
    assert "largest / smallest" in format_table(rows)
