"""The cold start of ``f2l`` (docs/experiments/cold_start.md): what a fresh process imports, the
forked face fit of ``f2l estimate photo.jpg`` (f2l.io.forked), pyarrow without pandas in it
(f2l.io.hidden_modules), and the skin mask's point-in-polygon without matplotlib."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from f2l.face.regions import _inside
from f2l.io import forked

HEAVY = ("torch", "pandas", "scipy", "matplotlib", "trimesh", "pyarrow", "cv2")


def _fresh_python(code: str) -> str:
    """Run ``code`` in a new interpreter (this one's, this environment); its stdout."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONSTARTUP"}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


@pytest.mark.parametrize("argv", [["--help"], ["estimate", "--help"], ["--version"]])
def test_the_cli_starts_without_the_heavy_libraries(argv):
    out = _fresh_python(
        "import sys, json\n"
        "from f2l.cli import app\n"
        f"try:\n    app({argv!r})\nexcept SystemExit:\n    pass\n"
        f"print(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))")
    assert json.loads(out.strip().splitlines()[-1]) == []


def test_a_forked_call_returns_its_value_from_another_process():
    out = _fresh_python(
        "import os, json\n"
        "from f2l.io import forked\n"
        "assert forked.can_fork()\n"
        "call = forked.start(lambda: {'pid': os.getpid(), 'x': [1.5, 'a']})\n"
        "print(json.dumps([call.forked, call.result(), os.getpid()]))")
    was_forked, value, parent_pid = json.loads(out)
    assert was_forked and value["x"] == [1.5, "a"] and value["pid"] != parent_pid


def test_a_forked_calls_exception_is_raised_here_with_the_childs_traceback():
    out = _fresh_python(
        "import json\n"
        "from f2l.io import forked\n"
        "def boom():\n    raise KeyError('no such face')\n"
        "call = forked.start(boom)\n"
        "try:\n    call.result()\nexcept KeyError as exc:\n"
        "    print(json.dumps([call.forked, str(exc), exc.__notes__[0]]))")
    was_forked, message, note = json.loads(out)
    assert was_forked and message == "'no such face'"
    assert note.startswith("in the forked child:") and "boom" in note


def test_a_forked_call_that_cannot_pickle_its_result_says_so():
    out = _fresh_python(
        "from f2l.io import forked\n"
        "call = forked.start(lambda: (lambda: 1))\n"
        "try:\n    call.result()\nexcept Exception as exc:\n    print(type(exc).__name__, call.forked)")
    assert out.split()[1] == "True" and out.split()[0] in ("PicklingError", "AttributeError")


def test_without_fork_the_call_runs_here_with_the_same_result(monkeypatch):
    monkeypatch.setenv(forked.NO_FORK_ENV, "1")
    assert not forked.can_fork()
    call = forked.start(lambda: os.getpid())
    assert not call.forked and call.result() == os.getpid()
    failing = forked.start(lambda: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        failing.result()
    failing.cancel()  # nothing to stop


def test_pyarrow_with_pandas_hidden_converts_to_the_same_parquet_bytes():
    code = (
        "import sys, json, io\n"
        "import numpy as np, pyarrow as pa, pyarrow.parquet as pq\n"
        "from f2l.io.hidden_modules import hide\n"
        "hidden = hide() == ('pandas', 'networkx')\n"
        "arrays = [pa.array([1.5, None, float('nan')]), pa.array([[1.0, 2.0], [], None]),"
        " pa.array(['a', None, 'c']), pa.array(np.arange(3.0))]\n"
        "t = pa.Table.from_arrays(arrays, names=['x', 'l', 's', 'n'])\n"
        "sink = io.BytesIO(); pq.write_table(t, sink)\n"
        "back = pq.read_table(io.BytesIO(sink.getvalue()))\n"
        "lengths = pa.compute.list_value_length(back['l'].combine_chunks()).to_numpy(zero_copy_only=False)\n"
        "try:\n    import pandas\n    refused = False\nexcept ImportError:\n    refused = True\n"
        "print(json.dumps([hidden, 'pandas' in sys.modules, refused, sink.getvalue().hex(),"
        " back.to_pylist()[2]['s'], str(lengths.tolist())]))\n"
        # it ends as the forked fit's child does (f2l.io.forked: os._exit): the interpreter's own
        # teardown aborted once in a CI run ("terminate called without an active exception", after
        # this output; 0 of 86 reruns) and is not what this test is about
        "sys.stdout.flush(); import os; os._exit(0)\n")
    hidden, loaded, refused, with_hidden, last, lengths = json.loads(_fresh_python(code))
    assert hidden and not loaded and refused and last == "c" and lengths == "[2.0, 0.0, nan]"
    plain = json.loads(_fresh_python(code.replace("hidden = hide() == ('pandas', 'networkx')", "hidden = True")))
    assert plain[1] and not plain[2]  # without the hiding, pyarrow imports pandas on the way
    assert with_hidden == plain[3]  # the same Parquet bytes either way


def test_the_fits_mesh_and_normals_are_the_same_with_networkx_hidden():
    import hashlib

    from f2l.face.geometry import subdivided_mesh
    from f2l.face.mesh import canonical_face_mesh

    code = (
        "import sys, hashlib, json\n"
        "from f2l.io.hidden_modules import hide\n"
        "hide()\n"
        "from f2l.face.geometry import subdivided_mesh\n"
        "from f2l.face.mesh import canonical_face_mesh\n"
        "v, f, _ = canonical_face_mesh()\n"
        "out = subdivided_mesh(v * [1.0, 1.0, -1.0] + [0.0, 0.0, -40.0], f, 2)\n"
        "print(json.dumps([[hashlib.sha256(a.tobytes()).hexdigest() for a in out], 'networkx' in sys.modules,"
        " 'trimesh' in sys.modules]))")
    digests, networkx_loaded, trimesh_loaded = json.loads(_fresh_python(code))
    assert trimesh_loaded and not networkx_loaded
    v, f, _ = canonical_face_mesh()
    here = subdivided_mesh(v * [1.0, 1.0, -1.0] + [0.0, 0.0, -40.0], f, 2)
    assert len(here[0]) > 7000 and digests == [hashlib.sha256(a.tobytes()).hexdigest() for a in here]


def test_point_in_polygon_equals_matplotlibs_on_edges_vertices_and_centres():
    from matplotlib.path import Path

    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:60, 0:60]
    centres = np.c_[xx.ravel() + 0.5, yy.ravel() + 0.5]
    for trial in range(300):
        k = int(rng.integers(3, 30))
        if trial % 3 == 0:  # star-shaped, like the face oval and the features
            ang = np.sort(rng.uniform(0, 2 * np.pi, k))
            poly = np.c_[30 + rng.uniform(3, 25, k) * np.cos(ang), 30 + rng.uniform(3, 25, k) * np.sin(ang)]
        elif trial % 3 == 1:  # half-integer vertices: pixel centres on edges and vertices
            poly = rng.integers(0, 120, (k, 2)) * 0.5
        else:  # self-intersecting
            poly = rng.uniform(0, 60, (k, 2))
        pts = np.r_[centres, poly, (poly + np.roll(poly, -1, 0)) / 2, [[np.nan, 30.0], [30.0, np.inf]]]
        assert np.array_equal(_inside(poly, pts), Path(poly).contains_points(pts)), trial
    assert not _inside(np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([[0.5, 0.5]])).any()
    square = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])
    assert _inside(square, np.array([[1.0, 1.0], [3.0, 1.0], [1.0, -1.0]])).tolist() == [True, False, False]


@pytest.mark.slow
def test_estimate_on_a_photo_writes_the_same_bits_forked_or_not(tmp_path):
    """The CLI's forked fit (a real process: stdout and stderr are files) against F2L_NO_FORK."""
    skdata = pytest.importorskip("skimage.data")
    import pyarrow.parquet as pq
    from PIL import Image

    from f2l.io.exr import read_exr

    photo = tmp_path / "astronaut.png"
    Image.fromarray(skdata.astronaut()).save(photo)
    outs = {}
    for name, extra in (("forked", {}), ("here", {forked.NO_FORK_ENV: "1"})):
        out = tmp_path / name
        env = {k: v for k, v in os.environ.items() if k != forked.NO_FORK_ENV} | extra
        proc = subprocess.run([sys.executable, "-m", "f2l.cli", "estimate", str(photo), "-m", "sh9", "--out", str(out),
                               "--json"], capture_output=True, text=True, env=env, timeout=600)
        assert proc.returncode == 0, proc.stderr
        assert json.loads(proc.stdout)["ok"] == 1
        outs[name] = out
    shard = [p.relative_to(outs["forked"]) for p in outs["forked"].rglob("part-*.parquet")]
    assert len(shard) == 1 and (outs["forked"] / shard[0]).read_bytes() == (outs["here"] / shard[0]).read_bytes()
    rows = [pq.read_table(o / "estimates.parquet").drop_columns(["timings_json", "runtime_s"]).to_pylist()
            for o in outs.values()]
    assert rows[0][0]["status"] == "ok" and json.dumps(rows[0], default=str) == json.dumps(rows[1], default=str)
    probes = [sorted(o.glob("probes/sh9/*.exr")) for o in outs.values()]
    assert len(probes[0]) == 1 and np.array_equal(np.asarray(read_exr(probes[0][0])), np.asarray(read_exr(probes[1][0])))
