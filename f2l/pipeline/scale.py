"""``f2l dev scale-report --build``: ``build-dataset`` run time and peak memory, local against Ray, as
the number of face photos grows.

The capture tree: ``faces`` distinct face photos (scikit-image's astronaut, public domain, each
cropped, scaled, flipped and exposed differently, so each is its own cache key), ten per session,
each session with a given probe (a clear sky): fit-faces with its transport is the per-face work,
as in a real build. Each (executor, size) runs in a fresh child process with a clean work folder;
peak memory is the largest resident size of the child's whole process tree (the driver, and for
Ray its raylet, object store and workers), sampled every 0.1 s.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

__all__ = ["write_face_tree", "run_build_scale", "format_build_table"]

_CHILD = r"""
import json, sys, time
from pathlib import Path
from f2l.pipeline import build_dataset
root, work, out, executor, workers = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]), sys.argv[4], int(sys.argv[5])
t0 = time.perf_counter()
summary = build_dataset(root, work, out, executor=executor, workers=workers)
print(json.dumps({"seconds": time.perf_counter() - t0, "records": summary.counts.get("records", 0)}))
"""


def write_face_tree(root: Path, faces: int, per_session: int = 10, seed: int = 0) -> None:
    try:
        import skimage.data
    except ImportError as exc:  # the photos come from scikit-image's astronaut (the test extra)
        raise RuntimeError("scale-report --build needs scikit-image for its face photos: "
                           "pip install 'f2l[test]'") from exc
    from PIL import Image, ImageEnhance

    from f2l.io.exr import write_exr
    from f2l.lighting.grid import LatLongGrid
    from f2l.synth.skies import clear_sky

    rng = np.random.default_rng(seed)
    base = Image.fromarray(skimage.data.astronaut())
    for i in range(faces):
        session = Path(root) / f"s{i // per_session:04d}"
        if i % per_session == 0:
            (session / "probes").mkdir(parents=True, exist_ok=True)
            sky = clear_sky(LatLongGrid(64, 128), math.radians(rng.uniform(10, 70)), rng.uniform(-math.pi, math.pi))
            write_exr(session / "probes" / "sky.exr", sky)
            (session / "faces").mkdir(parents=True, exist_ok=True)
        x0, y0 = int(rng.integers(40, 90)), int(rng.integers(0, 30))
        side = int(rng.integers(280, 330))
        photo = base.crop((x0, y0, x0 + side, y0 + side)).resize((256, 256), Image.Resampling.LANCZOS)
        photo = ImageEnhance.Brightness(photo).enhance(float(rng.uniform(0.8, 1.2)))
        if rng.random() < 0.5:
            photo = photo.transpose(Image.Transpose.FLIP_LEFT_RIGHT)
        photo.save(session / "faces" / f"face{i:05d}.png")


def _tree_rss_mib(pid: int) -> float:
    """Resident size of ``pid`` and all its descendants (MiB), from /proc."""
    total, todo, seen = 0, [pid], set()
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        try:
            with open(f"/proc/{p}/status") as fh:
                total += next((int(line.split()[1]) for line in fh if line.startswith("VmRSS:")), 0)
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, ValueError):
            continue
    return total / 1024


def _run_child(root: Path, tmp: Path, executor: str, workers: int) -> dict:
    import threading
    import time

    work, out = tmp / f"work-{executor}", tmp / f"out-{executor}"
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(root), str(work), str(out), executor, str(workers)],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    peak = [0.0]

    def sample() -> None:
        while proc.poll() is None:
            peak[0] = max(peak[0], _tree_rss_mib(proc.pid))
            time.sleep(0.1)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    stdout, _ = proc.communicate()
    thread.join()
    if proc.returncode != 0:
        raise RuntimeError(f"build-dataset --executor {executor} failed (exit {proc.returncode})")
    result = json.loads(stdout.strip().splitlines()[-1])
    result["peak_mib"] = peak[0]
    return result


def run_build_scale(sizes=(10, 200), executors=("local", "ray"), workers: int = 2) -> list[dict]:
    """One row per (size, executor): seconds, faces/min, records, peak MiB of the process tree."""
    rows = []
    for n in sizes:
        with tempfile.TemporaryDirectory(prefix="f2l-build-scale-") as tmp:
            root = Path(tmp) / "raw"
            write_face_tree(root, int(n))
            for executor in executors:
                r = _run_child(root, Path(tmp), executor, workers)
                rows.append({"faces": int(n), "executor": executor, "workers": workers, **r,
                             "faces_per_min": 60.0 * n / r["seconds"] if r["seconds"] > 0 else float("inf")})
    return rows


def format_build_table(rows: list[dict]) -> str:
    lines = ["| faces | executor | build s | faces/min | records | peak MiB (process tree) |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['faces']} | {r['executor']} | {r['seconds']:.1f} | {r['faces_per_min']:.1f} "
                     f"| {r['records']} | {r['peak_mib']:.0f} |")
    return "\n".join(lines)
