"""The search's share of the sun error, or the objective's (``f2l eval search``).

A compact-sun fit can miss the true sun for two reasons: its starts never reach the true sun's
basin (the search's fault), or its objective (data term and priors) is lower somewhere else (the
forward model's or the priors' fault, which no search fixes). For each clear case of a
``make eval-real`` folder, on the fitted mesh, on the true one (``f2l eval twin-geometry``) and on an
ideal photo on the true mesh (f2l's own Lambertian render of the true probe,
:func:`f2l.evaluation.photo_residual.ideal_photo`, read without the skin's gloss: what is left there
is the lighting model's family and its priors), each model is fitted three ways, all without the
elevation profile so that the objective compared is one fit's
(``EstimatorConfig.sun_elevation_profile_deg = ()``):

=========================================  =============================================================
variant                                    starts
=========================================  =============================================================
own starts                                 the global sun search's (the estimator's defaults)
started at the true sun                    one start, the sun at the renderer's sun direction
                                           (``estimate(..., sun_starts=...)``), the rest as the search's best
started at the true sun, no light prior    the same with ``light_prior_weight = 0``
=========================================  =============================================================

Per variant and part: mean / median Sun-ang, MAE (s), Full-dω MAE (l). For the row started at the
truth with the priors also: on how many cases that fit ends with a lower objective than the own-start fit, and of the
own-start suns more than ``FAR_DEG`` off, how many the truth's start beats and how far its own sun
then ends from the truth. Where a fit started at the truth ends far from it, the objective's
minimum is elsewhere; where it beats the own starts and stays near the truth, the search missed.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from f2l.estimate import EstimationError, EstimatorConfig, FaceObservation, estimate
from f2l.evaluation.eval_report import write_table
from f2l.evaluation.evaluate import _truth_on, case_of_source, load_cases, split_of
from f2l.evaluation.photo_residual import ideal_photo
from f2l.io.shards import iter_records
from f2l.metrics import evaluate_pair
from f2l.models.capabilities import CompactSun
from f2l.models.registry import load_model

VARIANTS = ("own starts", "started at the true sun", "started at the true sun, no light prior")
GEOMETRIES = ("fitted", "true", "true, ideal photo")
FAR_DEG = 15.0
LOWER_REL = 1e-3  # an objective counts as lower when below the other's by this fraction


def _configs(threads: int, geometry: str) -> dict:
    """{variant: EstimatorConfig}; the ideal photo is Lambertian and is read so (``skin_gloss = 0``)."""
    base = EstimatorConfig(threads=threads, sun_prior_from_capture=False, sun_elevation_profile_deg=())
    if geometry == "true, ideal photo":
        base = dataclasses.replace(base, skin_gloss=0.0)
    return {"own starts": base, "started at the true sun": base,
            "started at the true sun, no light prior": dataclasses.replace(base, light_prior_weight=0.0)}


def search_share(eval_dir: Path, models: list[str], threads: int = 2, limit: int | None = None,
                 progress=None) -> list[dict]:
    """One row per (model, geometry, variant, clear case) for the ``make eval-real`` folder
    ``eval_dir`` (``pbr/``, ``fitted/``, ``true_geometry/``); ``limit`` keeps the first cases."""
    eval_dir = Path(eval_dir)
    render_dir = eval_dir / "pbr"
    cases = load_cases(render_dir)
    configs = {g: _configs(threads, g) for g in GEOMETRIES}
    twins = {r.face_id: r for r in iter_records(eval_dir / "true_geometry") if getattr(r, "ok", False)}
    cache: dict = {}
    rows: list[dict] = []
    done = 0
    for fitted in iter_records(eval_dir / "fitted"):
        if not getattr(fitted, "ok", False) or (limit is not None and done >= limit):
            continue
        case = case_of_source(fitted.source_path)
        meta = cases.get(case)
        if meta is None or meta["sky"]["kind"] == "overcast" or fitted.face_id not in twins:
            continue
        done += 1
        sky = meta["sky"]
        grid = fitted.grid
        truth = _truth_on(render_dir, case, grid, cache)
        gt_sun = np.asarray(sky["sun_direction"], np.float64)
        twin = twins[fitted.face_id]
        ideal = ideal_photo(twin, truth, threads=threads)
        inputs = {"fitted": (fitted, fitted.observed_rgb), "true": (twin, twin.observed_rgb),
                  "true, ideal photo": (twin, ideal)}
        for name in models:
            model = load_model(name, grid)
            if not isinstance(model, CompactSun):
                raise ValueError(f"{name!r} is not a compact-sun model: it has no sun to start from")
            for geometry, (rec, photo) in inputs.items():
                obs = FaceObservation(rec.normals, photo, rec.mask, rec.visibility_bits, grid, face_id=rec.face_id)
                for variant in VARIANTS:
                    starts = None if variant == "own starts" else gt_sun[None]
                    try:
                        res = estimate(obs, model, configs[geometry][variant], sun_starts=starts)
                    except EstimationError:
                        continue
                    m = evaluate_pair(res.probe.astype(np.float64), truth, grid, overcast=False,
                                      est_sun_dir=res.sun_direction, gt_sun_dir=gt_sun)
                    rows.append({"model": name, "geometry": geometry, "variant": variant, "case": case,
                                 "split": split_of(meta), "sun_behind_head": bool(sky.get("sun_behind_head")),
                                 "objective": float(res.loss), **m})
        if progress:
            progress(1)
    return rows


def _summary(rs: list[dict], own: dict) -> str:
    """One table cell: mean (median) Sun-ang, MAE (s), Full-dω; and, against ``own`` ({case: row}
    of the own-start fit), the lower-objective counts."""
    if not rs:
        return "—"
    ang = np.array([r["Sun-ang (°)"] for r in rs], float)
    cell = (f"{np.mean(ang):.1f}° ({np.median(ang):.1f}°), {np.mean([r['MAE (s)'] for r in rs]):.3f}, "
            f"{np.mean([r['Full-dω MAE (l)'] for r in rs]):.4f}")
    if rs[0]["variant"] != "started at the true sun":  # the objectives compared must share their priors
        return cell
    paired = [(r, own[r["case"]]) for r in rs if r["case"] in own]
    lower = [(r, o) for r, o in paired if r["objective"] < o["objective"] * (1 - LOWER_REL)]
    far = [(r, o) for r, o in paired if o["Sun-ang (°)"] > FAR_DEG]
    far_lower = [r for r, o in far if r["objective"] < o["objective"] * (1 - LOWER_REL)]
    ends = f", its sun {np.mean([r['Sun-ang (°)'] for r in far_lower]):.1f}° off" if far_lower else ""
    return cell + f"; lower objective {len(lower)}/{len(paired)}; far suns beaten {len(far_lower)}/{len(far)}{ends}"


def search_table(rows: list[dict], held_out: bool = False) -> str:
    """Markdown: per model, geometry and variant, each part's cell (:func:`_summary`); with
    ``held_out`` one column over every case (a set no default was tuned on)."""
    parts = {"all cases": None} if held_out else {"tuning part": "tune", "reporting part": "report"}
    lines = ["| model | geometry | starts (no elevation profile) | " + " | ".join(parts) + " |",
             "|---" * (3 + len(parts)) + "|",
             f"| | | *(each cell: mean (median) Sun-ang, MAE (s), Full-dω MAE (l); for a start at the truth with the priors, on "
             f"how many faces it ends with a lower objective than the own starts, and of the own starts' suns "
             f"more than {FAR_DEG:g}° off how many it beats, and how far its sun then is)* |" + " |" * len(parts)]
    for model in dict.fromkeys(r["model"] for r in rows):
        for geometry in GEOMETRIES:
            sel = [r for r in rows if r["model"] == model and r["geometry"] == geometry]
            for variant in VARIANTS:
                cells = []
                for part in parts.values():
                    in_part = [r for r in sel if part is None or r["split"] == part]
                    own = {r["case"]: r for r in in_part if r["variant"] == "own starts"}
                    cells.append(_summary([r for r in in_part if r["variant"] == variant], own))
                if any(c != "—" for c in cells):
                    lines.append(f"| {model} | {geometry} | {variant} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_search(rows: list[dict], out_dir: Path, held_out: bool = False) -> Path:
    return write_table(rows, out_dir, "search_share", "The search's share of the sun error, or the objective's",
                       search_table(rows, held_out))
