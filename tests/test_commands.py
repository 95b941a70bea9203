"""The demo, bench, synth and evaluate paths, run small."""

import json
import subprocess

import numpy as np
import pyarrow.parquet as pq

from f2l.lighting.grid import LatLongGrid
from tests.plugin_helpers import f2l_cmd


def test_version_and_help():
    from f2l import __version__

    out = subprocess.run(f2l_cmd("--version"), capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and __version__ in out.stdout
    for cmd in ("models", "synth", "estimate", "evaluate", "bench", "demo"):
        out = subprocess.run(f2l_cmd(cmd, "--help"), capture_output=True, text=True, timeout=120)
        assert out.returncode == 0 and "Usage" in out.stdout, cmd


def test_synth_is_deterministic(tmp_path):
    from f2l.io.shards import iter_records
    from f2l.synth.dataset import write_synthetic_shards

    grid = LatLongGrid(16, 32)
    for name in ("a", "b"):
        write_synthetic_shards(tmp_path / name, n=2, seed=5, grid=grid, image_size=48, progress=False)
    ra, rb = list(iter_records(tmp_path / "a")), list(iter_records(tmp_path / "b"))
    assert [r.face_id for r in ra] == [r.face_id for r in rb]
    for x, y in zip(ra, rb):
        assert np.array_equal(x.observed_rgb, y.observed_rgb) and np.array_equal(x.visibility_bits, y.visibility_bits)
    assert (tmp_path / "a" / ra[0].gt_probe_path).read_bytes() == (tmp_path / "b" / rb[0].gt_probe_path).read_bytes()


def test_demo_end_to_end_small(tmp_path):
    from f2l.demo import run_demo

    lines = []
    result = run_demo(tmp_path, n=2, seed=3, models=["sh9"], echo=lines.append, grid=LatLongGrid(16, 32), image_size=48)
    assert "MAE (s)" in result["markdown"] and "Sun-ang" in result["markdown"] and "sh9" in result["markdown"]
    assert len(result["pictures"]) == 2
    for p in result["pictures"]:
        from PIL import Image

        assert Image.open(p).size[0] > 100
    rows = pq.read_table(tmp_path / "estimates" / "estimates.parquet").to_pylist()
    assert len(rows) == 2 and all(r["status"] == "ok" for r in rows)
    csv = (tmp_path / "estimates" / "metrics_per_face.csv").read_text().splitlines()
    assert len(csv) == 3


def test_bench_small(tmp_path):
    from f2l.dev.bench import run_bench

    result = run_bench(faces=1, models=["sh9"], out_dir=tmp_path, image_size=48, grid=LatLongGrid(16, 32), threads=1)
    assert "adaptive" in result["markdown"] and "sh9" in result["markdown"]
    data = json.loads((tmp_path / "bench.json").read_text())
    assert data["transport"][0]["bits_differ"] < 0.01
    assert (tmp_path / "error_vs_runtime.png").stat().st_size > 1000
