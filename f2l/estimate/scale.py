"""``f2l dev scale-report``: build and estimate synthetic datasets of several sizes and report
faces/minute, per-stage time and peak memory, to show that memory stays flat as data grows.

Each size runs in a fresh child process (so one size's memory never counts against another):

* build: :func:`f2l.synth.dataset.write_synthetic_shards` (render faces under known probes,
  transport, shards), streamed one face at a time;
* estimate: :func:`f2l.estimate.runner.run_estimates` in-process (``workers=1``: the driver's
  streaming is what bounds memory; a process pool multiplies it by its worker count).

Peak memory is ``VmHWM`` of the child, reset after the imports (``/proc/self/clear_refs``), per
stage, plus the resident size after the imports for reference.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile

_CHILD = r"""
import json, sys, time
from pathlib import Path
from f2l.synth.dataset import write_synthetic_shards
from f2l.estimate.runner import run_estimates
from f2l.lighting.grid import LatLongGrid
import f2l.estimate.estimator, f2l.io.exr, f2l.io.preview, f2l.models.registry

def status_mib(key):
    with open("/proc/self/status") as fh:
        return next(int(l.split()[1]) for l in fh if l.startswith(key + ":")) / 1024

def reset_peak():
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")

n, out, model, image_size, gh, gw = int(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], int(sys.argv[4]), int(sys.argv[5]), int(sys.argv[6])
grid = LatLongGrid(gh, gw)
base = status_mib("VmRSS")
reset_peak()
t0 = time.perf_counter()
write_synthetic_shards(out / "shards", n=n, seed=0, grid=grid, image_size=image_size, progress=False)
build_s, build_peak = time.perf_counter() - t0, status_mib("VmHWM")
reset_peak()
t0 = time.perf_counter()
summary = run_estimates([out / "shards"], [model], out / "est", workers=1, threads=2, progress=False)
estimate_s, estimate_peak = time.perf_counter() - t0, status_mib("VmHWM")
print(json.dumps({"faces": n, "build_s": build_s, "estimate_s": estimate_s, "ok": summary["ok"],
                  "base_mib": base, "build_peak_mib": build_peak, "estimate_peak_mib": estimate_peak}))
"""


def run_scale_report(sizes=(10, 200), *, model: str, image_size: int = 96,
                     grid: tuple[int, int] = (32, 64)) -> list[dict]:
    """One row per dataset size (see the module docstring)."""
    rows = []
    for n in sizes:
        with tempfile.TemporaryDirectory(prefix="f2l-scale-") as tmp:
            out = subprocess.run([sys.executable, "-c", _CHILD, str(int(n)), tmp, model,
                                  str(image_size), str(grid[0]), str(grid[1])],
                                 check=True, capture_output=True, text=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        total = r["build_s"] + r["estimate_s"]
        r["faces_per_min"] = 60.0 * n / total if total > 0 else float("inf")
        r["model"] = model
        rows.append(r)
    return rows


def format_table(rows: list[dict]) -> str:
    lines = ["| faces | model | build s | estimate s | faces/min | peak MiB build / estimate "
             "| after imports MiB |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['faces']} | {r['model']} | {r['build_s']:.1f} | {r['estimate_s']:.1f} "
                     f"| {r['faces_per_min']:.1f} | {r['build_peak_mib']:.0f} / "
                     f"{r['estimate_peak_mib']:.0f} | {r['base_mib']:.0f} |")
    if len(rows) > 1:
        peaks = [max(r["build_peak_mib"], r["estimate_peak_mib"]) for r in rows]
        lines.append("")
        lines.append(f"peak memory, largest / smallest dataset: {peaks[-1] / peaks[0]:.2f}x")
    return "\n".join(lines)
