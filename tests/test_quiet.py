"""Issue 18: a quiet install and quiet runs.

- setuptools has nothing to warn about when it builds f2l (the walls of "Package 'f2l.data' is
  absent from the `packages` configuration" that `make setup` used to print);
- LiteRT's native "INFO: Created TensorFlow Lite XNNPACK delegate for CPU." (written by C++ to
  file descriptor 2, so no Python logging filter sees it) goes to ``f2l --debug-log``, not to the
  terminal in the middle of ``fit-faces`` / ``build-dataset`` progress.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SOURCES = ["f2l", "plugins", "schemas", "pipelines", "pyproject.toml", "README.md", "LICENSE"]
PYTHON_WARNING = re.compile(r"\w+Warning: .*")  # warnings.showwarning's "file:line: Category: message"

BUILD = """
import sys
from setuptools import build_meta
out = sys.argv[1]
build_meta.build_wheel(out)
build_meta.prepare_metadata_for_build_editable(out)
build_meta.build_editable(out)
"""


def test_setuptools_builds_without_warnings(tmp_path):
    src = tmp_path / "src"
    for name in SOURCES:  # a copy: the checkout gets no build/ or *.egg-info
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(REPO / name, src / name)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONWARNINGS", "PYTHONPATH")}
    proc = subprocess.run([sys.executable, "-W", "always", "-c", BUILD, str(tmp_path / "out")], cwd=src, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    output = proc.stdout + proc.stderr
    assert "absent from the `packages` configuration" not in output
    assert not PYTHON_WARNING.findall(output), PYTHON_WARNING.findall(output)


def test_landmarker_creation_writes_nothing_to_stderr():
    code = ("from f2l.face.landmarker import FaceLandmarker; import numpy as np; "
            "lm = FaceLandmarker(); print(len(lm(np.zeros((64, 64, 3), np.uint8))))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "0"
    assert proc.stderr == "", proc.stderr


def test_fit_faces_sends_litert_log_lines_to_the_debug_log(tmp_path):
    import skimage.data
    from PIL import Image

    photos = tmp_path / "photos"
    photos.mkdir()
    Image.fromarray(skimage.data.astronaut()).resize((256, 256)).save(photos / "astronaut.png")
    log = tmp_path / "debug.log"
    proc = subprocess.run([sys.executable, "-m", "f2l.cli", "--debug-log", str(log), "fit-faces", str(photos),
                           "--out", str(tmp_path / "out")], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert "XNNPACK" not in proc.stderr and "INFO:" not in proc.stderr, proc.stderr
    assert "XNNPACK" in log.read_text()
    assert list((tmp_path / "out").glob("*.parquet"))
