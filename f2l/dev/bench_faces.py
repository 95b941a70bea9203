"""``f2l dev bench-faces``: run time of face fitting per stage, next to its geometric error.

Synthetic photos (painted features, EXIF focal length, :func:`f2l.synth.dataset.write_synthetic_shards`)
are rendered first (not timed), then each is fitted the way ``f2l fit-faces`` does it, timing
photo decode, landmarks (detector + landmark model), geometry (pose fit, mesh, rasterisation,
resampling, mask) and transport (visibility bits), after one warm-up face. The error columns
come from the true-geometry twin (:mod:`f2l.evaluation.compare_geometry`): median normal error on the mask and
the head-pose errors. ``--photo`` adds real photos (no error columns).
"""

from __future__ import annotations

import json
import math
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from f2l.lighting.grid import LatLongGrid


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _time_photo(path: Path, landmarker, options):
    from f2l.face.fit import FaceFit, fit_photo_faces
    from f2l.io.photo import load_photo

    t0 = time.perf_counter()
    photo = load_photo(path)
    load_s = time.perf_counter() - t0
    fits = [f for f in fit_photo_faces(photo, landmarker, options) if isinstance(f, FaceFit)]
    return photo, load_s, fits


def run_face_bench(faces: int = 4, image_size: int = 256, resolution: int = 104,
                   grid: LatLongGrid = LatLongGrid(), seed: int = 3, threads: int = 2,
                   photos: list[Path] | None = None) -> dict:
    from f2l.evaluation.compare_geometry import true_geometry_twin
    from f2l.face.fit import FitOptions, face_record
    from f2l.face.landmarker import FaceLandmarker
    from f2l.io.shards import iter_records
    from f2l.synth.dataset import write_synthetic_shards

    options = FitOptions(resolution=resolution, grid=grid, threads=threads)
    landmarker = FaceLandmarker(threads=1)
    rows = []
    with tempfile.TemporaryDirectory(prefix="f2l-bench-faces-") as tmp:
        truth_dir = Path(tmp) / "truth"
        write_synthetic_shards(truth_dir, n=faces + 1, seed=seed, grid=grid, progress=False,
                               image_size=image_size, features=True, overcast_fraction=0.0)
        truth = {r.face_id: r for r in iter_records(truth_dir)}
        paths = sorted((truth_dir / "photos").glob("*.png"))
        _time_photo(paths[0], landmarker, options)  # warm-up: imports, caches, Embree
        jobs = [(p, truth[p.stem]) for p in paths[1:]] + [(Path(p), None) for p in photos or []]
        for path, gt in jobs:
            photo, load_s, fits = _time_photo(path, landmarker, options)
            if not fits:
                rows.append({"photo": path.name, "status": "no usable face"})
                continue
            fit = fits[0]
            row = {"photo": path.name, "status": "ok", "pixels": fit.num_pixels,
                   "masked": int(fit.mask.sum()), "load_s": load_s, **fit.timings}
            row["fit_s"] = fit.timings["landmarks_s"] + fit.timings["geometry_s"] + \
                fit.timings["transport_s"]
            if gt is not None:
                rec = face_record(fit, photo, "bench", options, source_path=str(path))
                _, errors = true_geometry_twin(rec, gt, threads)
                pose = gt.meta["pose_deg"]
                row.update(normal_err_deg=float(np.median(errors)),
                           yaw_err_deg=abs(fit.head.yaw_deg - pose["yaw"]),
                           pitch_err_deg=abs(fit.head.pitch_deg - pose["pitch"]))
            rows.append(row)
    ok = [r for r in rows if r["status"] == "ok"]
    med = {k: float(np.median([r[k] for r in ok])) for k in
           ("load_s", "landmarks_s", "geometry_s", "transport_s", "fit_s", "pixels")} if ok else {}
    return {"rows": rows, "median": med, "peak_rss_mb": round(_rss_mb(), 1),
            "options": options.to_meta(), "image_size": image_size, "threads": threads}


def format_table(result: dict) -> str:
    lines = ["| photo | px (masked) | load s | landmarks s | geometry s | transport s | "
             "fit+transport s | normal err ° | yaw / pitch err ° |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        if r["status"] != "ok":
            lines.append(f"| {r['photo']} | {r['status']} | | | | | | | |")
            continue
        err = f"{r['normal_err_deg']:.2f}" if "normal_err_deg" in r else "—"
        pose = (f"{r['yaw_err_deg']:.2f} / {r['pitch_err_deg']:.2f}"
                if "yaw_err_deg" in r else "—")
        lines.append(f"| {r['photo']} | {r['pixels']} ({r['masked']}) | {r['load_s']:.3f} | "
                     f"{r['landmarks_s']:.3f} | {r['geometry_s']:.3f} | {r['transport_s']:.3f} | "
                     f"**{r['fit_s']:.3f}** | {err} | {pose} |")
    m = result["median"]
    if m:
        lines.append(f"\nmedian fit+transport {m['fit_s']:.3f} s/face "
                     f"({60.0 / max(m['fit_s'], 1e-9):.0f} faces/min), {m['pixels']:.0f} face px; "
                     f"peak memory (RSS) {result['peak_rss_mb']:.0f} MiB; "
                     f"resolution {result['options']['resolution']}, grid "
                     f"{result['options']['grid'][0]}x{result['options']['grid'][1]}, "
                     f"{result['threads']} threads")
    return "\n".join(lines)


def to_json(result: dict) -> str:
    def clean(v):
        return round(v, 4) if isinstance(v, float) and math.isfinite(v) else v

    return json.dumps({**result, "rows": [{k: clean(v) for k, v in r.items()}
                                          for r in result["rows"]]})
