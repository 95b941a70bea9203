"""``f2l dev bench-capture``: ingest + merge run time against a bare LibRaw decode of the same files,
and peak memory as the number of brackets grows.

A synthetic capture tree (``brackets`` × ``frames`` real DNGs of ``megapixels`` each, written by
:func:`f2l.capture.dng.write_bracket` from a sky scene with a clipped sun, with a real camera's
colour matrix, two brackets per session in one folder that ingest must split; lossless-JPEG
compressed like camera RAWs by default, or uncompressed, where the decode is little more than a
file read) is timed three ways, each in a fresh child process so that one's memory never counts
against another's:

* bare decode: ``rawpy.imread(path).raw_image_visible`` for every file (the floor);
* ingest: ``f2l ingest`` (metadata incl. one LibRaw decode per RAW for the black/white levels,
  SHA-256, sessions and brackets; no content detection);
* merge: ``f2l make-probes`` with no lens model for the views (one bracket in memory at a time,
  views written as EXR, nothing to assemble);
* probes: the same after :func:`place_views` gives each session a session.toml placing its views
  (equidistant fisheyes looking up) and a fresh ingest: merge, conversion to Rec.709, sphere
  assembly (on make-probes' default 128 x 256 grid) and the sun from the views.

Peak memory is the child's peak resident set size (``VmHWM``, reset after the imports through
``/proc/self/clear_refs``), and that peak minus the resident size right after the imports: what
the work itself needed.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

_CHILD = r"""
import json, sys, time
from pathlib import Path
import rawpy
from f2l.capture.manifest import run_ingest
from f2l.capture.probes import make_probes
import f2l.capture.merge, f2l.capture.sphere, f2l.io.raw_meta, f2l.io.exr, f2l.io.tables
import f2l.metrics.lighting, exifread, PIL.Image, pyarrow.dataset, jsonschema, scipy.fft
try:  # pyarrow imports pandas lazily where it is installed (not an f2l dependency): import it here,
    import pandas  # noqa: F401  so that its import time is not counted as work
except ImportError:
    pass
mode, root, work = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3])
def status_mib(key):
    with open("/proc/self/status") as fh:
        return next(int(l.split()[1]) for l in fh if l.startswith(key + ":")) / 1024
with open("/proc/self/clear_refs", "w") as fh:  # reset the peak (VmHWM) after the imports
    fh.write("5")
base_mib = status_mib("VmRSS")
t0 = time.perf_counter()  # imports done: time the work only
found = None
if mode == "decode":
    for p in sorted(root.rglob("*.dng")):
        with rawpy.imread(str(p)) as raw:
            raw.raw_image_visible
elif mode == "ingest":
    found = run_ingest(root, work, detect_roles=False).brackets
else:  # "merge" (views unplaced: no assembly) or "probes" (placed: merge + assembly)
    summary = make_probes(root, work)
assembly_s = sum(r["seconds"] for r in summary.rows if r["kind"] == "probe") if mode == "probes" else 0.0
peak_mib = status_mib("VmHWM")
print(json.dumps({"seconds": time.perf_counter() - t0, "assembly_s": assembly_s, "peak_rss_mib": peak_mib,
                  "work_mib": peak_mib - base_mib, "brackets_found": found}))
"""


VIEWS_PER_SESSION = 2


def write_tree(root: Path, brackets: int, frames: int, megapixels: float, seed: int = 0,
               compression: str = "ljpeg") -> int:
    """``brackets`` brackets of ``frames`` frames, :data:`VIEWS_PER_SESSION` per session, all of a
    session's frames in one ``sky/`` folder (ingest splits them by time and by the restarting
    exposure sequence, shot in auto-bracketing order 0, -, +, ...), recorded with the Canon EOS 30D's
    colour matrix (make-probes converts to Rec.709); returns the number of files."""
    from datetime import datetime, timedelta

    from f2l.capture.dng import synthetic_sky_scene, write_bracket
    from f2l.testing.sessions import CANON_EOS_30D_XYZ_TO_CAMERA, aeb_order

    h = int(round(np.sqrt(megapixels * 1e6 * 3 / 4) / 2)) * 2
    w = int(round(h * 4 / 3 / 2)) * 2
    scene = synthetic_sky_scene(h, w, seed=seed)
    exposures = [2.0 ** (ev - frames) for ev in aeb_order(frames, 2.0)]
    for b in range(brackets):
        site, view = divmod(b, VIEWS_PER_SESSION)
        write_bracket(root / f"site{site:04d}" / "sky", scene, exposures, seed=seed + b,
                      full_scale_radiance=float(np.percentile(scene, 50)) * 4.0 * max(exposures) / 64,
                      compression=compression, camera_matrix=np.reshape(CANON_EOS_30D_XYZ_TO_CAMERA, (3, 3)),
                      prefix=f"v{view}", timestamp=datetime(2024, 6, 21, 12, 0, 0) + timedelta(seconds=30 * view))
    return brackets * frames


def place_views(root: Path) -> None:
    """Give every session of a :func:`write_tree` a session.toml placing its views (equidistant
    fisheyes looking up, turned by 180° about the vertical from one to the next): make-probes then
    assembles a probe per session."""
    shots = "".join(f'[[shots]]\nfiles = "sky/v{v}_*"\nyaw_deg = {180 * v}\npitch_deg = 90.0\n'
                    for v in range(VIEWS_PER_SESSION))
    for site in sorted(p for p in root.iterdir() if p.is_dir()):
        (site / "session.toml").write_text(f'[lens]\nprojection = "equidistant"\nfov_deg = 180.0\n\n{shots}')


def _child(mode: str, root: Path, work: Path) -> dict:
    out = subprocess.run([sys.executable, "-c", _CHILD, mode, str(root), str(work)],
                         check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_capture_bench(sizes=(2, 8), frames: int = 5, megapixels: float = 2.0,
                      repeat: int = 2, compression: str = "ljpeg") -> list[dict]:
    """One row per tree size: files, decode / ingest / merge seconds (best of ``repeat``; views
    unplaced, so make-probes only merges), the (ingest + merge) / decode ratio; then with every
    view placed, make-probes' seconds (merge + sphere assembly, of which assembly_s in
    ``assemble_session``) and (ingest + make-probes) / decode; each stage's peak memory."""
    rows = []
    for n in sizes:
        with tempfile.TemporaryDirectory(prefix="f2l-bench-capture-") as tmp:
            root = Path(tmp) / "raw"
            files = write_tree(root, n, frames, megapixels, compression=compression)
            best: dict[str, dict] = {}

            def keep(mode: str, r: dict) -> None:
                if mode not in best or r["seconds"] < best[mode]["seconds"]:
                    best[mode] = r

            for _ in range(max(1, repeat)):  # the views are unplaced: make-probes merges only
                work = Path(tmp) / f"work-{time.monotonic_ns()}"
                for mode in ("decode", "ingest", "merge"):
                    keep(mode, _child(mode, root, work))
            place_views(root)
            for _ in range(max(1, repeat)):  # the same brackets placed: merge + sphere assembly
                work = Path(tmp) / f"work-{time.monotonic_ns()}"
                _child("ingest", root, work)
                keep("probes", _child("probes", root, work))
            d, i, m = (best[k]["seconds"] for k in ("decode", "ingest", "merge"))
            p, a = best["probes"]["seconds"], best["probes"]["assembly_s"]
            rows.append({"brackets": n, "brackets_found": best["ingest"]["brackets_found"], "files": files, "megapixels": megapixels, "compression": compression,
                         "decode_s": d, "ingest_s": i, "merge_s": m, "make_probes_s": p, "assembly_s": a,
                         "ratio": (i + m) / d if d > 0 else float("inf"),
                         "ratio_with_assembly": (i + p) / d if d > 0 else float("inf"),
                         "files_per_s": files / (i + m),
                         "peak_mib": {k: round(v["peak_rss_mib"], 1) for k, v in best.items()},
                         "work_mib": {k: round(v["work_mib"], 1) for k, v in best.items()}})
    return rows


def format_table(rows: list[dict]) -> str:
    lines = ["| brackets (ingest found) | files | MP/file | DNG | bare decode s | ingest s | merge s | (ingest+merge)/decode "
             "| make-probes with assembly s (assembly) | (ingest+make-probes)/decode | files/s "
             "| peak MiB decode / ingest / merge / with assembly "
             "| above imports MiB decode / ingest / merge / with assembly |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        p, q = r["peak_mib"], r["work_mib"]
        lines.append(f"| {r['brackets']} ({r['brackets_found']}) | {r['files']} | {r['megapixels']:.1f} | {r['compression']} | {r['decode_s']:.2f} "
                     f"| {r['ingest_s']:.2f} | {r['merge_s']:.2f} | {r['ratio']:.2f}x "
                     f"| {r['make_probes_s']:.2f} ({r['assembly_s']:.2f}) | {r['ratio_with_assembly']:.2f}x "
                     f"| {r['files_per_s']:.1f} | {p['decode']} / {p['ingest']} / {p['merge']} / {p['probes']} "
                     f"| {q['decode']} / {q['ingest']} / {q['merge']} / {q['probes']} |")
    return "\n".join(lines)
