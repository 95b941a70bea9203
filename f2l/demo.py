"""``f2l demo``: the README's end-to-end example on a small embedded synthetic set.

synth (n faces with glossy skin, as in users' photos, under known skies) -> estimate with every
built-in model -> evaluate (§5.1 table) -> pictures: a contact sheet per face (photo | ground-truth
probe | each estimate) and the evaluation scene relit by each probe.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def builtin_models() -> list[str]:
    from f2l.models.registry import discover

    return [name for name, info in discover().items() if info.ok and info.package == "f2l"]


def run_demo(out: Path, n: int = 12, seed: int = 0, models: list[str] | None = None, echo=print,
             grid=None, image_size: int = 128) -> dict:
    from f2l.estimate.runner import run_estimates
    from f2l.metrics.evaluate import evaluate_estimates
    from f2l.synth.dataset import write_synthetic_shards

    out = Path(out)
    models = models or builtin_models()
    shards = out / "shards"
    est_dir = out / "estimates"
    echo(f"[1/4] synthesising {n} faces (glossy skin) under known skies -> {shards}")
    from f2l.lighting.grid import LatLongGrid

    synth_summary = write_synthetic_shards(shards, n=n, seed=seed, grid=grid or LatLongGrid(), image_size=image_size,
                                          gloss=True)
    echo(json.dumps(synth_summary))
    echo(f"[2/4] estimating with {', '.join(models)} -> {est_dir}")
    est_summary = run_estimates([shards], models=models, out_dir=est_dir)
    echo(json.dumps(est_summary))
    echo("[3/4] evaluating (paper §5.1 metrics; protocol in docs/metrics.md)")
    result = evaluate_estimates(est_dir, [shards])
    echo(result["markdown"])
    echo("[4/4] pictures")
    pictures = write_pictures(out, shards, est_dir, models)
    for p in pictures:
        echo(f"  wrote {p}")
    echo(f"tables: {result['summary_md']}, {result['summary_csv']}, {result['per_face_csv']}")
    from f2l.report.build import write_report

    report = write_report(out, title=f"f2l demo: {n} synthetic faces (own renders, glossy skin)")
    echo(f"report: {report.pages[0]} (open it in a browser)")
    return {"synth": synth_summary, "estimate": est_summary, "markdown": result["markdown"], "pictures": pictures,
            "report": report.pages[0]}


def write_pictures(out: Path, shards: Path, est_dir: Path, models: list[str], max_faces: int = 12) -> list[str]:
    """Contact sheets: one row per face (photo | GT probe | estimates) and the relit scene."""
    import pyarrow.parquet as pq
    from PIL import Image

    from f2l.io.exr import read_exr
    from f2l.io.preview import contact_sheet, save_png, tonemap
    from f2l.lighting.grid import LatLongGrid
    from f2l.metrics.evaluate import ground_truth_index
    from f2l.metrics.scene import render_scene

    estimates = [r for r in pq.read_table(est_dir / "estimates.parquet").to_pylist() if r["status"] == "ok"]
    by_face: dict[str, dict] = {}
    for r in estimates:
        by_face.setdefault(r["face_id"], {})[r["model"]] = r
    gt = ground_truth_index([shards])
    probe_rows, scene_rows = [], []
    for face_id in sorted(by_face)[:max_faces]:
        truth = gt.get(face_id)
        if truth is None or truth["probe"] is None:
            continue
        gt_probe = read_exr(truth["probe"])
        grid = LatLongGrid(*gt_probe.shape[:2])
        photo = np.asarray(Image.open(shards / "photos" / f"{face_id}.png").convert("RGB"))
        sky = truth["meta"].get("sky", {})
        label = f"{face_id[-3:]} {sky.get('kind', '')}"
        # One exposure per row (the ground truth's), after normalising each probe's sky energy,
        # so brightness differences between columns are real differences in the estimates.
        ref_energy = _sky_energy(gt_probe, grid)
        probe_row = [(label, photo), ("ground truth", tonemap(gt_probe))]
        gt_scene, mask = render_scene(gt_probe, grid)
        scene_scale = 1.0 / max(float(gt_scene[mask].mean()), 1e-12)
        scene_row = [(label, photo), ("ground truth", _scene_png(gt_scene * scene_scale))]
        ev = _exposure_ev(gt_probe)
        for model in models:
            row = by_face[face_id].get(model)
            if row is None:
                continue
            est = read_exr(est_dir / row["probe_path"])
            est_n = est * (ref_energy / max(_sky_energy(est, grid), 1e-12))
            probe_row.append((model, tonemap(est_n, exposure_ev=ev)))
            img, _ = render_scene(est, grid)
            scene_row.append((model, _scene_png(img / max(float(img[mask].mean()), 1e-12))))
        probe_rows.append(probe_row)
        scene_rows.append(scene_row)
    outputs = []
    if probe_rows:
        p = out / "probes_contact_sheet.png"
        save_png(p, contact_sheet(probe_rows, cell_height=96))
        outputs.append(str(p))
        p = out / "relit_scene_contact_sheet.png"
        save_png(p, contact_sheet(scene_rows, cell_height=96))
        outputs.append(str(p))
    return outputs


def _sky_energy(probe: np.ndarray, grid) -> float:
    rows = grid.sky_rows
    return float((probe[:rows].sum(-1) * grid.solid_angles[:rows]).sum())


def _exposure_ev(probe: np.ndarray) -> float:
    from f2l.io.preview import auto_exposure_scale

    return float(np.log2(auto_exposure_scale(probe)))


def _scene_png(img: np.ndarray) -> np.ndarray:
    from f2l.io.preview import tonemap

    return tonemap(img, exposure_ev=np.log2(0.5))
