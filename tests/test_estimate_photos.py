"""Photo → probe in one command: `f2l estimate` on photos and folders of photos (f2l.pipeline.photos).

Real photographs (scikit-image's astronaut, a NASA portrait, public domain; coffee, face-free):
every face of a photo gets a probe, a rerun reuses the fitted faces and the estimates, and a
photo without a usable face or a broken file is reported without stopping the others.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pyarrow.parquet as pq
import pytest
from PIL import Image
from typer.testing import CliRunner

from f2l.cli import app

skdata = pytest.importorskip("skimage.data")


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    d = tmp_path_factory.mktemp("photos")
    a = skdata.astronaut()
    two = np.concatenate([a, a[:, ::-1]], axis=1)  # two people side by side
    Image.fromarray(np.ascontiguousarray(two)).save(d / "two.jpg", quality=92)
    Image.fromarray(skdata.coffee()).save(d / "coffee.jpg", quality=92)
    (d / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 40)
    return d


def test_a_photo_gives_a_probe_per_face_and_a_rerun_reuses_everything(photos, tmp_path):
    out = tmp_path / "est"
    res = invoke("estimate", photos / "two.jpg", "-m", "sh9", "--out", out, "--json")
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["ok"] == 2 and summary["photos"]["counts"] == {"computed": 1, "ok": 1}
    rows = pq.read_table(out / "estimates.parquet").to_pylist()
    assert sorted(r["face_id"].rsplit("-", 1)[1] for r in rows) == ["f0", "f1"]
    # the two faces of one photo share one light (--joint photo, the default): one probe, two rows
    assert len(list((out / "probes" / "sh9").glob("*.exr"))) == 1
    assert rows[0]["probe_path"] == rows[1]["probe_path"] and {r["group_size"] for r in rows} == {2}
    assert all(r["group_used"] for r in rows)
    from f2l.io.exr import read_exr

    for exr in (out / "probes" / "sh9").glob("*.exr"):
        probe = np.asarray(read_exr(exr))
        assert probe.shape == (64, 128, 3) and np.isfinite(probe).all() and probe.max() > 0
    # one whole-photo overlay with both faces framed
    overlays = [p for p in (out / "faces").rglob("overlays/*.png") if not re.search(r"-f\d+$", p.stem)]
    assert len(overlays) == 1 and overlays[0].stem.startswith("two-")
    again = invoke("estimate", photos / "two.jpg", "-m", "sh9", "--out", out, "--json")
    assert again.exit_code == 0, again.output
    summary = json.loads(again.stdout)
    assert summary["photos"]["counts"] == {"reused": 1, "ok": 1}
    assert summary["skipped_done"] == 2 and summary["total"] == 0
    alone = invoke("estimate", photos / "two.jpg", "-m", "sh9", "--out", tmp_path / "alone", "--joint", "none", "--json")
    assert alone.exit_code == 0, alone.output
    assert len(list((tmp_path / "alone" / "probes" / "sh9").glob("*.exr"))) == 2


def test_a_folder_with_bad_photos_estimates_the_good_ones_and_says_why_not_the_others(photos, tmp_path):
    out = tmp_path / "est"
    res = invoke("estimate", photos, "-m", "sh9", "--out", out, "--json")
    assert res.exit_code == 4, res.output  # 4: some photos failed, the rest written
    summary = json.loads(res.stdout)
    assert summary["ok"] == 2
    not_ok = {r["source_path"].rsplit("/", 1)[1]: r for r in summary["photos"]["not_ok"]}
    assert set(not_ok) == {"coffee.jpg", "broken.png"}
    assert not_ok["coffee.jpg"]["status"] == "no_face" and "coffee.jpg" in not_ok["coffee.jpg"]["message"]
    assert not_ok["broken.png"]["status"] == "error" and "broken.png" in not_ok["broken.png"]["message"]


def test_photos_without_a_usable_face_fail_with_the_reasons(photos, tmp_path):
    res = invoke("estimate", photos / "coffee.jpg", "-m", "sh9", "--out", tmp_path / "est")
    assert res.exit_code == 2
    assert "no usable face" in res.output and "coffee.jpg: no face detected" in res.output


def test_the_readmes_own_photo_example_runs_as_written(tmp_path):
    """README: `.venv/bin/f2l estimate photo.jpg --model sunsky --out est/`, run in a folder
    holding a photo of one's own (here scikit-image's astronaut), gives a probe and the table."""
    import shlex
    import subprocess
    import sys
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    line = next(ln.strip() for ln in readme.splitlines() if ln.strip().startswith(".venv/bin/f2l estimate photo.jpg"))
    args = shlex.split(line)[1:]
    Image.fromarray(skdata.astronaut()).save(tmp_path / "photo.jpg", quality=92)
    proc = subprocess.run([sys.executable, "-m", "f2l.cli", *args], cwd=tmp_path, capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr
    rows = pq.read_table(tmp_path / "est" / "estimates.parquet").to_pylist()
    assert [r["status"] for r in rows] == ["ok"] and rows[0]["model"] == "sunsky"
    assert (tmp_path / "est" / rows[0]["probe_path"]).is_file() and rows[0]["probe_path"].startswith("probes/sunsky/")
