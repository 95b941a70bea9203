"""Issue 18: a wheel built from this tree carries everything f2l reads at run time and works from
any folder.

The wheel is built once per module from a copy of the sources (no build/ or *.egg-info left in
the checkout, no stale build/lib files in the wheel) and installed without dependencies into a
fresh venv. That venv sees the test environment's third-party packages through a folder of links
that leaves out the editable f2l (its ``__editable__`` finder, .pth and dist-info), so the wheel's
f2l is the only one importable, and its console script ``f2l`` is run from an unrelated folder.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import site
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SOURCES = ["f2l", "plugins", "schemas", "pipelines", "pyproject.toml", "README.md", "LICENSE"]


def _quiet_env(**extra: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSAFEPATH")}
    env.update(extra)
    return env


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    src = tmp_path_factory.mktemp("src")
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(REPO / name, src / name)
    out = tmp_path_factory.mktemp("dist")
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                           "-q", "-w", str(out), str(src)], capture_output=True, text=True,
                          env=_quiet_env(PYTHONWARNINGS="ignore"), timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    (path,) = out.glob("f2l-*.whl")
    return path


def test_wheel_holds_package_data_and_entry_points(wheel):
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
        entry_points = zf.read(next(n for n in names if n.endswith(".dist-info/entry_points.txt"))).decode()
    expected = [f"f2l/schemas/{p.name}" for p in (REPO / "schemas").glob("*.schema.json")]
    expected += [f"f2l/pipelines/{p.name}" for p in (REPO / "pipelines").glob("*.toml")]
    expected += [f"f2l/data/{p.name}" for p in (REPO / "f2l" / "data").iterdir()]
    expected += [f"f2l/render/data/hdri/{p.name}" for p in (REPO / "f2l" / "render" / "data" / "hdri").iterdir()]
    expected += [f"f2l_builtin_models/data/{p.name}" for p in (REPO / "plugins" / "f2l_builtin_models" / "data").iterdir()]
    expected += [str(p.relative_to(REPO)) for p in (REPO / "f2l").rglob("*.py")]
    expected += [str(p.relative_to(REPO / "plugins")) for p in (REPO / "plugins" / "f2l_builtin_models").rglob("*.py")]
    assert len(expected) > 20 and "f2l/schemas/face_record.schema.json" in expected
    missing = sorted(set(expected) - names)
    assert not missing, f"missing from {wheel.name}: {missing}"
    assert not [n for n in names if n.endswith("README.md") and "schemas" in n]  # not a schema
    assert not [n for n in names if "__pycache__" in n or n.startswith(("tests/", "build/"))]
    assert re.search(r"^\[console_scripts\]\nf2l = f2l\.cli:main$", entry_points, re.M), entry_points
    for name, target in (("sh9", "sh:SH9"), ("sh25", "sh:SH25"), ("sunsky", "sunsky:SunSky"), ("ae", "ae:AE")):
        assert re.search(rf"^{name} = f2l_builtin_models\.{target}$", entry_points, re.M), entry_points
    assert "[f2l.lighting_models]" in entry_points
    # the fixtures for plugin authors' tests (f2l.testing.pytest_plugin) reach pytest from a wheel too
    assert re.search(r"^\[pytest11\]\nf2l = f2l\.testing\.pytest_plugin$", entry_points, re.M), entry_points


@pytest.fixture(scope="module")
def venv(wheel, tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("venv")
    deps = root / "deps"  # the test environment's packages, less the editable f2l
    deps.mkdir()
    ours = re.compile(r"^(__editable__.*|f2l-.*\.dist-info|f2l|f2l_builtin_models|__pycache__|.*\.pth)$")
    for entry in Path(sysconfig.get_paths()["purelib"]).iterdir():
        if not ours.match(entry.name):
            (deps / entry.name).symlink_to(entry)
    env_dir = root / "env"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(env_dir)], check=True, timeout=120)
    python = env_dir / "bin" / "python"
    purelib = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                  capture_output=True, text=True, check=True).stdout.strip())
    (purelib / "f2l_test_deps.pth").write_text(f"{deps}\n")
    proc = subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "--no-index",
                           "-q", str(wheel)], capture_output=True, text=True, env=_quiet_env(), timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    work = root / "elsewhere"  # the working folder: not the checkout, nothing of it on sys.path
    work.mkdir()
    return {"python": python, "f2l": env_dir / "bin" / "f2l", "purelib": purelib, "work": work,
            "env": _quiet_env()}


def _run(venv, *args, timeout: float = 300.0, exit_code: int = 0) -> subprocess.CompletedProcess:
    proc = subprocess.run([str(a) for a in args], cwd=venv["work"], env=venv["env"], capture_output=True,
                          text=True, timeout=timeout)
    assert proc.returncode == exit_code, f"{args[1:]} exited {proc.returncode}:\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}"
    return proc


def test_the_wheel_is_what_runs(venv):
    code = ("import json, sys, f2l, f2l_builtin_models; from f2l.io.schema import schemas_dir; "
            "from f2l.pipeline.spec import default_pipeline_path; from f2l.models.registry import discover; "
            "models = {k: (v.error, v.cls and sys.modules[v.cls.__module__].__file__) for k, v in discover().items()}; "
            "print(json.dumps([models, f2l.__file__, f2l_builtin_models.__file__, str(schemas_dir()), "
            "str(default_pipeline_path())]))")
    models, *found = json.loads(_run(venv, venv["python"], "-c", code).stdout)
    assert set(models) >= {"sh9", "sh25", "sunsky", "ae"}, models
    assert all(error is None for error, _ in models.values()), models
    paths = [Path(p) for p in found] + [Path(file) for _, file in models.values()]
    for p in paths:
        assert venv["purelib"] in p.parents, f"{p} is not from the installed wheel"
        assert REPO not in p.resolve().parents
    assert (paths[2] / "face_record.schema.json").is_file() and paths[3].is_file()
    assert not (paths[2] / "README.md").exists()
    assert _run(venv, venv["f2l"], "--version").stdout.startswith("f2l ")


def test_synth_estimate_evaluate_build_dataset_from_elsewhere(venv, tmp_path):
    """The issue's acceptance path: the installed console script, run outside the checkout."""
    from tests.test_build_dataset import make_tree

    work, f2l = venv["work"], venv["f2l"]
    _run(venv, f2l, "eval", "synth", "--out", "faces", "--n", "2", "--grid", "16x32", "--image-size", "64", "--seed", "3",
         "--json")
    proc = _run(venv, f2l, "estimate", "faces", "-m", "sunsky", "--out", "est", "--workers", "1", "--json")
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert (summary["ok"], summary["failed"]) == (2, 0)
    assert (work / "est" / "estimates.parquet").is_file()
    proc = _run(venv, f2l, "evaluate", "est")
    assert "sunsky" in proc.stdout and (work / "est" / "metrics_summary.csv").is_file()
    # build-dataset with the packaged default pipeline (no --pipeline) on the build-dataset tests'
    # capture tree: DNG brackets, a chart, face photos, a given probe
    make_tree(tmp_path / "raw")
    proc = _run(venv, f2l, "build-dataset", tmp_path / "raw", "--work", "bwork", "--out", "bshards",
                exit_code=4)  # 4: the tree's broken.png failed, the rest is built
    assert "XNNPACK" not in proc.stderr and "INFO:" not in proc.stderr, proc.stderr
    assert list((work / "bshards").glob("*.parquet")), "build-dataset wrote no shard"
    card = json.loads((work / "bshards" / "dataset_card.json").read_text())
    assert "face2light" in json.dumps(card)
    assert card.get("counts", {}).get("records", 1) > 0
