"""The face fit's share of the error, split into normals and occluders (``f2l eval geometry``),
and what is left on an ideal photo.

For each fitted face of a ``make eval-real`` folder that has a true-geometry twin
(``f2l eval twin-geometry``), the same photo pixels (those both meshes cover) are estimated with the
normals and the visibility taken from different meshes:

============================================  ==========================================================
variant                                       normals / visibility
============================================  ==========================================================
fitted                                        the fitted face mask's
fitted normals, no occluder                   fitted / front hemisphere of the fitted normals only
fitted normals, true occlusion                fitted / the true body's, cut to the fitted hemisphere
fitted mesh + true body below the chin        fitted / fitted, also blocked by the true body's
                                              triangles below the chin (seen from the fitted points)
true normals, no occluder                     true / front hemisphere of the true normals only
true                                          true / true (the twin record itself)
true, ideal photo                             true / true, and the photo replaced by f2l's own
                                              Lambertian render of the true probe through them
                                              (:func:`f2l.evaluation.photo_residual.ideal_photo`)
true, ideal photo + gloss                     the same plus the skin's glossy highlight of the
                                              whole probe, at the case's own roughness and
                                              specular level (:mod:`f2l.evaluation.highlight`)
============================================  ==========================================================

The table gives per variant and part (tuning: even cases, reporting: odd) the mean Sun-ang over
sunny cases (and split by the sun in front of the face or behind the head), MAE (s) and
Full-dω MAE (l). It attributes the geometry gap to shading normals and to cast shadows. The last
row is the floor the lighting model and its priors set: what remains when the photo holds nothing
the estimator leaves out (no specular, interreflection, skin texture, clipping or noise); the gap
between it and "true" is the renderer's physics. The row with gloss puts the first of those back
on its own. The Lambertian ideal photo is read as Lambertian (``skin_gloss = 0``, the model that
made it); every other row, glossy, with the estimator's default skin gloss.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from f2l.estimate import EstimationError, EstimatorConfig, FaceObservation, estimate
from f2l.evaluation.eval_report import write_table
from f2l.evaluation.evaluate import _truth_on, case_of_source, load_cases, split_of
from f2l.evaluation.highlight import Gloss
from f2l.evaluation.photo_residual import ideal_photo
from f2l.io.shards import iter_records
from f2l.metrics import evaluate_pair
from f2l.models.registry import load_model
from f2l.transport import compute_visibility
from f2l.transport.visibility import front_mask

VARIANTS = ("fitted", "fitted normals, no occluder", "fitted normals, true occlusion",
            "fitted mesh + true body below the chin", "true normals, no occluder", "true", "true, ideal photo",
            "true, ideal photo + gloss")
BELOW_CHIN_CM = 1.0  # true triangles whose centroid lies this far below the lowest percent of face points


def _pack(mask: np.ndarray) -> np.ndarray:
    return np.packbits(mask, axis=1, bitorder="little")


def variant_inputs(fitted, twin, render_dir: Path, meta: dict, truth_probe: np.ndarray,
                   threads: int = 2) -> dict:
    """{variant: (normals, visibility_bits, observed_rgb)} for one face; pixels are the twin's, and so
    are the colours except in the ideal photo (``truth_probe``: the true probe on the record's grid)."""
    grid = fitted.grid
    fn = np.asarray(fitted.normals, np.float64)
    tn = np.asarray(twin.normals, np.float64)
    front_fitted = _pack(front_mask(fn, grid))
    truth = np.load(Path(render_dir) / "truth" / f"{meta['face_id']}.npz")
    vertices = truth["vertices_cm"].astype(np.float64) - [0.0, 0.0, meta["settings"]["camera_distance_cm"]]
    faces = truth["faces"].astype(np.int64)
    points = np.asarray(fitted.points, np.float64)
    chin_y = float(np.percentile(points[np.asarray(fitted.mask)][:, 1], 1))
    below = vertices[faces].mean(1)[:, 1] < chin_y - BELOW_CHIN_CM
    body_below = compute_visibility(vertices, faces[below], points, fn, grid, threads=threads) if below.any() \
        else np.full_like(fitted.visibility_bits, 255)
    photo = twin.observed_rgb
    return {
        "fitted": (fn, fitted.visibility_bits, photo),
        "fitted normals, no occluder": (fn, front_fitted, photo),
        "fitted normals, true occlusion": (fn, np.bitwise_and(twin.visibility_bits, front_fitted), photo),
        "fitted mesh + true body below the chin": (fn, np.bitwise_and(fitted.visibility_bits, body_below), photo),
        "true normals, no occluder": (tn, _pack(front_mask(tn, grid)), photo),
        "true": (tn, twin.visibility_bits, photo),
        "true, ideal photo": (tn, twin.visibility_bits, ideal_photo(twin, truth_probe, threads=threads)),
        "true, ideal photo + gloss": (tn, twin.visibility_bits,
                                      ideal_photo(twin, truth_probe, threads=threads, gloss=case_gloss(meta))),
    }


def case_gloss(meta: dict):
    """The rendered skin's gloss (:class:`f2l.evaluation.highlight.Gloss`) from a case's meta file:
    principled roughness, F0 = 0.08 × specular, and the head's skin albedo."""
    material = meta["material"]
    return Gloss(float(material["skin_roughness"]), 0.08 * float(material["skin_specular"]),
                 tuple(float(c) for c in meta["head"]["skin_albedo"]))


def geometry_share(eval_dir: Path, models: list[str], threads: int = 2, progress=None) -> list[dict]:
    """One row per (model, variant, case) for the ``make eval-real`` folder ``eval_dir``
    (``pbr/``, ``fitted/``, ``true_geometry/``)."""
    eval_dir = Path(eval_dir)
    render_dir = eval_dir / "pbr"
    cases = load_cases(render_dir)
    twins = {r.face_id: r for r in iter_records(eval_dir / "true_geometry") if getattr(r, "ok", False)}
    cache: dict = {}
    rows = []
    cfg = EstimatorConfig(threads=threads, sun_prior_from_capture=False)
    lambertian = dataclasses.replace(cfg, skin_gloss=0.0)  # for f2l's own Lambertian render
    for fitted in iter_records(eval_dir / "fitted"):
        if not getattr(fitted, "ok", False):
            continue
        twin = twins.get(fitted.face_id)
        case = case_of_source(fitted.source_path) if twin is not None else None
        if case not in cases:
            continue
        meta = cases[case]
        grid = fitted.grid
        truth = _truth_on(render_dir, case, grid, cache)
        sky = meta["sky"]
        overcast = sky["kind"] == "overcast"
        gt_sun = None if overcast else np.asarray(sky["sun_direction"], np.float64)
        inputs = variant_inputs(fitted, twin, render_dir, meta, truth, threads)
        for name in models:
            model = load_model(name, grid)
            for variant, (normals, bits, photo) in inputs.items():
                obs = FaceObservation(normals, photo, twin.mask, bits, grid, face_id=fitted.face_id)
                try:
                    res = estimate(obs, model, lambertian if variant == "true, ideal photo" else cfg)
                except EstimationError:
                    continue
                m = evaluate_pair(res.probe.astype(np.float64), truth, grid, overcast=overcast,
                                  est_sun_dir=res.sun_direction, gt_sun_dir=gt_sun)
                rows.append({"model": name, "variant": variant, "case": case, "split": split_of(meta),
                             "sun_behind_head": bool(sky.get("sun_behind_head")), "overcast": overcast, **m})
        if progress:
            progress(1)
    return rows


def share_table(rows: list[dict]) -> str:
    """Markdown: per model and variant, each part's mean Sun-ang (front / behind), MAE (s), Full-dω."""
    def cell(rs):
        if not rs:
            return "—"
        sa = np.array([r["Sun-ang (°)"] for r in rs], float)
        behind = np.array([r["sun_behind_head"] for r in rs])
        sunny = np.isfinite(sa)
        mean = lambda a: f"{np.mean(a):.1f}" if a.size else "—"  # noqa: E731
        return (f"{mean(sa[sunny])}° ({mean(sa[sunny & ~behind])} / {mean(sa[sunny & behind])}), "
                f"{np.mean([r['MAE (s)'] for r in rs]):.3f}, {np.mean([r['Full-dω MAE (l)'] for r in rs]):.4f}")

    lines = ["| model | geometry given to the estimator | tuning part | reporting part |", "|---|---|---|---|",
             "| | *(each cell: mean Sun-ang (sun in front / behind the head), MAE (s), Full-dω MAE (l))* | | |"]
    for model in dict.fromkeys(r["model"] for r in rows):
        for variant in VARIANTS:
            rs = [r for r in rows if r["model"] == model and r["variant"] == variant]
            if rs:
                lines.append(f"| {model} | {variant} | {cell([r for r in rs if r['split'] == 'tune'])} | "
                             f"{cell([r for r in rs if r['split'] == 'report'])} |")
    return "\n".join(lines)


def write_share(rows: list[dict], out_dir: Path) -> Path:
    return write_table(rows, out_dir, "geometry_share", "The face fit's share: normals or occluders, and an ideal photo",
                       share_table(rows))
