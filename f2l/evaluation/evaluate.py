"""``f2l eval real``'s scoring: the paper's Table 2 rows on ``f2l eval render-faces`` cases, with baselines.

This module scores one row per (method, case); :mod:`f2l.evaluation.eval_report` writes the tables.

Inputs: the render folder (``meta/``, ``probes/``, ``truth/``) and one or more estimate folders
written by ``f2l estimate`` (from ``f2l fit-faces`` records of the render's photos, or from their
true-geometry twins, :func:`write_true_geometry_twins`). A record belongs to the case whose id is
its photo's stem.

Every row is scored by :func:`f2l.metrics.evaluate_pair` on the estimate's grid against the case's
128 × 256 truth area-resampled to that grid, with the case's own sky kind and sun direction
(exact for the Hosek–Wilkie cases, the brightest texel of a map). Baselines, scored the same way:

- ``uniform sky``: constant radiance over the upper hemisphere and a grey (albedo 0.2) ground it
  lights: what one knows with no estimate at all (every metric is scale-invariant);
- ``SH9 oracle`` / ``SH25 oracle``: the truth projected onto real SH of order 2 / 4 (texel-mean
  quadrature) and reconstructed, negative lobes clipped at 0 — the best those bases can do;
- ``truth without its sun disk``: the truth with the texels that hold the sun's disk (centres within
  :func:`sun_disk_radius_deg` of the true sun) replaced by the median of the ring around them (clear cases; overcast ones keep the truth):
  an estimate that is exact everywhere except the sun's own disk. Its Full-dω MAE (l) is the floor
  for every estimate whose sun misses the disk; its Sun-ang is not scored (NaN);
- ``<model> fitted to the truth`` and ``<model> fitted to the truth, sun 5° off`` (``fit_truth``):
  the model fitted to the true probe itself, no face (:mod:`f2l.evaluation.truth_fit`), as fitted and
  with its sun moved 5°: what the model's family reaches under the probe fit's loss, and what a
  sun as close as a good face estimate costs it.

The cases are split by index: even = the tuning part (look at it freely while changing f2l),
odd = the reporting part (the figures of the README and docs/results/eval_real.md). Each row carries its breakdown keys: sky source,
sun elevation, sun behind the head.

Diagnostics (not §5.1 metrics; they say where the error of each method comes from), per row:

- ``colour R/G``, ``colour B/G``: the estimate's upper-hemisphere energy ratio R/G (B/G) over the
  truth's (1 = the light's colour is right; the face alone cannot tell the light's colour from
  the skin's, so the priors decide it);
- ``MAE (s), colour matched``: MAE (s) after scaling each channel of the estimate so its
  upper-hemisphere energy matches the truth's: what is left once the colour is right;
- ``sun share``: the estimate's energy share in the 13° cap around the true sun (the metric's sun
  region) minus the truth's (clear cases; < 0 = too little of the light there);
- ``sun elevation error (°)``: the elevation of the estimate's sun (the direction Sun-ang scores)
  minus the true sun's (clear cases; > 0 = too high). :func:`~f2l.evaluation.eval_report.elevation_bias_table` gives its
  median per sun elevation band and sky source: a mean Sun-ang says how far off the sun is, this
  says whether the estimates lean one way.
- ``MAE (s), sun at the truth`` / ``MAE (s), sun at the truth, colour matched`` / ``Full-dω MAE
  (l), sun at the truth`` (clear cases, estimates only): the estimate with its sun moved onto the
  true one (:func:`sun_moved`: the light in the ``SUN_MOVE_RADIUS_DEG`` cap around the estimate's
  sun, above the median of the ring around it, put into the true sun's disk texels, per channel),
  and also colour matched as above. Against the row's MAE (s) and Full-dω MAE they split the error
  into the sun's direction, the light's colour and the rest (the sky's shape, the sun's share);
  :func:`~f2l.evaluation.eval_report.sun_direction_table` lists them.
- ``sun_cone68_deg``, ``sun_cone90_deg``, ``predicted_mae_s`` (estimates only, NaN elsewhere):
  the estimate's own sun uncertainty (f2l.estimate.uncertainty), as written in estimates.parquet;
  :func:`~f2l.evaluation.eval_report.calibration_section` scores it (f2l.evaluation.calibration).
- ``photo residual`` / ``photo residual, truth``: how well the estimate's probe and the truth each
  explain the face's usable pixels through that record's own transport, skin albedo free per
  channel (:mod:`f2l.evaluation.photo_residual`; NaN for the baselines). :func:`~f2l.evaluation.eval_report.residual_table`
  counts the far-off suns whose estimate fits the photo at least as well as the truth: errors
  that the data term, as f2l reads the photo, does not correct.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from f2l.estimate.observation import EstimationError
from f2l.evaluation.compare_geometry import twin_from_mesh
from f2l.evaluation.photo_residual import PhotoResidual
from f2l.evaluation.truth_fit import FIT_SUFFIX, MOVED_SUFFIX, MOVED_SUN_DEG, moved_direction, truth_fit
from f2l.io.exr import read_exr
from f2l.io.shards import ShardWriter, iter_records
from f2l.io.side_files import load_gt_probe, write_side_probe
from f2l.lighting import sh
from f2l.lighting.grid import LatLongGrid
from f2l.lighting.resample import resample
from f2l.metrics import evaluate_pair, probe_metrics
from f2l.metrics.lighting import cap_mask
from f2l.metrics.lighting import sun_direction as probe_sun_direction
from f2l.metrics.render_metrics import image_metrics
from f2l.metrics.scene import evaluation_scene
from f2l.prior.probe_fit import ProbeFitError

__all__ = ["baseline_probes", "sun_disk_radius_deg", "without_sun_disk", "sun_moved", "evaluate_real", "diagnostics",
           "write_true_geometry_twins", "case_of_source", "load_cases", "split_of"]

BASELINES = ("uniform sky", "SH9 oracle", "SH25 oracle", "truth without its sun disk")
SUN_RADIUS_DEG = 0.27  # the sun's angular radius
SUN_RING_DEG = 4.0  # width of the ring whose median radiance replaces the disk
SUN_MOVE_RADIUS_DEG = 4.0  # the cap around an estimate's sun that sun_moved takes as its sun (sunsky's lobe: ~1°)
ELEVATION_BANDS_DEG = ((0.0, 15.0), (15.0, 45.0), (45.0, 90.0))
SPLITS = {"tune": 0, "report": 1}


def case_of_source(source_path: str) -> str:
    return Path(source_path).stem


def load_cases(render_dir: Path) -> dict[str, dict]:
    cases = {}
    for path in sorted((Path(render_dir) / "meta").glob("*.json")):
        meta = json.loads(path.read_text())
        cases[meta["face_id"]] = meta
    return cases


def records_by_case(fitted, cases) -> dict[str, list]:
    """The fitted face records of each render case in ``cases`` (its photo's file stem), every
    photo's faces sorted by face id; unreadable records are skipped."""
    records: dict[str, list] = {}
    for rec in iter_records(fitted):
        if not hasattr(rec, "source_path") or not hasattr(rec, "meta"):
            continue
        stem = case_of_source(rec.source_path)
        if stem in cases:
            records.setdefault(stem, []).append(rec)
    return {cid: sorted(recs, key=lambda r: r.face_id) for cid, recs in records.items()}


def split_of(meta: dict) -> str:
    return "report" if meta["index"] % 2 == SPLITS["report"] else "tune"


def baseline_probes(truth: np.ndarray, grid: LatLongGrid, sun_direction: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The baselines (module docstring) for one truth probe on ``grid``; ``sun_direction`` (unit,
    grid frame) is the true sun of a clear case, None for an overcast one."""
    uniform = np.ones(grid.shape + (3,))
    uniform[grid.sky_rows:] = 0.2
    out = {"uniform sky": uniform}
    for name, order in (("SH9 oracle", 2), ("SH25 oracle", 4)):
        coeffs = sh.project(truth, grid, order)
        out[name] = np.clip(sh.reconstruct(coeffs, grid), 0.0, None)
    out["truth without its sun disk"] = without_sun_disk(truth, grid, sun_direction)
    return out


def sun_disk_radius_deg(grid: LatLongGrid) -> float:
    """Radius of the cap whose texel centres include every texel the sun's disk can touch: the
    sun's radius plus half a texel's diagonal at the horizon (2.3° on 64 × 128)."""
    return SUN_RADIUS_DEG + 0.5 * math.sqrt(2.0) * 180.0 / grid.height


def without_sun_disk(truth: np.ndarray, grid: LatLongGrid, sun_direction: np.ndarray | None) -> np.ndarray:
    """``truth`` with its texels within :func:`sun_disk_radius_deg` of ``sun_direction`` set to the
    per-channel median of the ``SUN_RING_DEG`` wide ring around them (upper hemisphere); a copy of
    ``truth`` when ``sun_direction`` is None."""
    out = np.array(truth, dtype=np.float64, copy=True)
    if sun_direction is None:
        return out
    radius = sun_disk_radius_deg(grid)
    disk = cap_mask(grid, sun_direction, radius)
    ring = cap_mask(grid, sun_direction, radius + SUN_RING_DEG) & ~disk & grid.upper_mask
    if disk.any() and ring.any():
        out[disk] = np.median(out[ring], axis=0)
    return out


def sun_moved(probe: np.ndarray, grid: LatLongGrid, from_direction: np.ndarray, to_direction: np.ndarray,
              radius_deg: float = SUN_MOVE_RADIUS_DEG) -> np.ndarray:
    """``probe`` with its sun moved from ``from_direction`` onto ``to_direction`` (unit, grid frame).

    The sun is the light, per channel, in the texels within ``radius_deg`` of ``from_direction``
    above the median of the ``SUN_RING_DEG`` wide ring around them (upper hemisphere); those texels
    are set to that median, and the sun's energy Σ (l − median) dΩ goes, spread evenly in radiance,
    into the texels within :func:`sun_disk_radius_deg` of ``to_direction``. The upper hemisphere's
    energy is kept exactly when both caps lie above the horizon."""
    out = np.array(probe, dtype=np.float64, copy=True)
    source = cap_mask(grid, from_direction, radius_deg) & grid.upper_mask
    ring = cap_mask(grid, from_direction, radius_deg + SUN_RING_DEG) & ~source & grid.upper_mask
    target = cap_mask(grid, to_direction, sun_disk_radius_deg(grid)) & grid.upper_mask
    if not (source.any() and ring.any() and target.any()):
        return out
    fill = np.median(out[ring], axis=0)
    sun = np.clip(out[source] - fill, 0.0, None)
    energy = (sun * grid.solid_angles[source][:, None]).sum(0)
    out[source] = np.minimum(out[source], fill)
    out[target] += energy / grid.solid_angles[target].sum()
    return out


def write_true_geometry_twins(fitted_dir: Path, render_dir: Path, out_dir: Path, threads: int = 2) -> dict:
    """Twin every fitted record of a rendered photo on the renderer's true mesh (f2l's camera at
    the origin: the render's camera sat at +Z ``camera_distance_cm``); ground-truth probes copied."""
    cases = load_cases(render_dir)
    written, skipped = 0, 0
    with ShardWriter(out_dir, overwrite=True) as writer:
        for rec in iter_records(fitted_dir):
            meta = cases.get(case_of_source(rec.source_path)) if getattr(rec, "ok", False) else None
            if meta is None:
                skipped += 1
                continue
            truth = np.load(Path(render_dir) / "truth" / f"{meta['face_id']}.npz")
            vertices = truth["vertices_cm"].astype(np.float64) - [0.0, 0.0, meta["settings"]["camera_distance_cm"]]
            twin, _ = twin_from_mesh(rec, vertices, truth["faces"].astype(np.int64),
                                     truth["normals"].astype(np.float64), meta["focal_px"],
                                     (meta["settings"]["height_px"], meta["settings"]["width_px"]),
                                     {"truth_id": meta["face_id"]}, threads)
            probe = load_gt_probe(fitted_dir, rec) if rec.gt_probe_path else None
            twin.gt_probe_path = write_side_probe(out_dir, twin.face_id, probe) if probe is not None else None
            twin.photo_path = None
            writer.write(twin)
            written += 1
    return {"twins": written, "skipped": skipped, "out": str(out_dir)}


def _record_cases(shards: list[Path]) -> dict[str, str]:
    import pyarrow.parquet as pq

    out = {}
    for shard in shards:
        for f in sorted(Path(shard).glob("*.parquet")):
            table = pq.read_table(f, columns=["face_id", "source_path"])
            for fid, src in zip(table.column("face_id").to_pylist(), table.column("source_path").to_pylist()):
                out[fid] = case_of_source(src)
    return out


def _truth_on(render_dir: Path, case: str, grid: LatLongGrid, cache: dict) -> np.ndarray:
    key = (case, grid.shape)
    if key not in cache:
        cache[key] = resample(read_exr(Path(render_dir) / "probes" / f"{case}.exr").astype(np.float64),
                              grid.height, grid.width)
    return cache[key]


def evaluate_real(render_dir: Path, runs: dict[str, Path], grid: LatLongGrid = LatLongGrid(64, 128),
                  photo_residuals: bool = True, fit_truth: tuple[str, ...] = (),
                  fit_cache: Path | None = None) -> list[dict]:
    """One row per (method, case): the seven metrics, run time, split and breakdown keys.

    ``runs`` maps a label (e.g. "fitted", "true geometry") to an ``f2l estimate`` output folder;
    its rows are named "<model>" for the label "fitted" and "<model> (<label>)" otherwise.
    ``fit_truth`` names models to fit to each true probe as well (:mod:`f2l.evaluation.truth_fit`,
    cached in ``fit_cache``); a probe a model cannot fit is reported on stderr and left out.
    """
    import pyarrow.parquet as pq

    render_dir = Path(render_dir)
    cases = load_cases(render_dir)
    cache: dict = {}
    rows = []

    def row(method, case, metrics, runtime_s, est=None):
        meta = cases[case]
        sky = meta["sky"]
        return {"method": method, "case": case, "split": split_of(meta), "source": meta["lighting"]["source"],
                "sky_kind": sky["kind"], "sun_elevation_deg": sky["sun_elevation_deg"],
                "sun_behind_head": sky["sun_behind_head"], "runtime_s": runtime_s, **metrics,
                **uncertainty_of(est)}

    for case, meta in cases.items():
        truth = _truth_on(render_dir, case, grid, cache)
        true_sun = None if meta["sky"]["kind"] == "overcast" else np.asarray(meta["sky"]["sun_direction"])
        for name, probe in baseline_probes(truth, grid, true_sun).items():
            metrics = _pair(probe, truth, grid, meta, None, sun_at_truth=False)
            if name == "truth without its sun disk":  # its "sun" is the ring's median: not scored
                metrics["Sun-ang (°)"] = metrics["sun elevation error (°)"] = math.nan
            metrics.update(dict.fromkeys(RESIDUAL_NAMES, math.nan))
            rows.append(row(name, case, metrics, 0.0))
        for model_name in fit_truth:
            rows.extend(row(name, case, metrics, runtime_s)
                        for name, metrics, runtime_s in _truth_fit_rows(truth, model_name, grid, case, meta, fit_cache))
    for label, est_dir in runs.items():
        est_dir = Path(est_dir)
        run = json.loads((est_dir / "run.json").read_text())
        shards = [Path(s) for s in run["shards"]]
        record_case = _record_cases(shards)
        by_face = defaultdict(list)
        for est in pq.read_table(est_dir / "estimates.parquet").to_pylist():
            if est["status"] == "ok" and record_case.get(est["face_id"]) in cases:
                by_face[est["face_id"]].append(est)
        residuals = _photo_residuals(shards, by_face, est_dir, render_dir, record_case, cache) if photo_residuals else {}
        for face_id, ests in by_face.items():
            case = record_case[face_id]
            for est in ests:
                g = LatLongGrid(est["grid_height"], est["grid_width"])
                truth = _truth_on(render_dir, case, g, cache)
                probe = read_exr(est_dir / est["probe_path"]).astype(np.float64)
                sun = est.get("sun_direction")
                metrics = _pair(probe, truth, g, cases[case], None if sun is None else np.asarray(sun))
                metrics.update(residuals.get((face_id, est["model"]), dict.fromkeys(RESIDUAL_NAMES, math.nan)))
                method = est["model"] if label == "fitted" else f"{est['model']} ({label})"
                rows.append(row(method, case, metrics, float(est["runtime_s"]), est))
    return rows


UNCERTAINTY_NAMES = ("sun_cone68_deg", "sun_cone90_deg", "predicted_mae_s")


def uncertainty_of(est: dict | None) -> dict:
    """An estimates row's sun-uncertainty columns (f2l.estimate.uncertainty), NaN where null or
    without an estimate (baselines, models fitted to the truth)."""
    est = est or {}
    return {k: math.nan if est.get(k) is None else float(est[k]) for k in UNCERTAINTY_NAMES}


RESIDUAL_NAMES = ("photo residual", "photo residual, truth")


def _elevation_deg(direction) -> float:
    d = np.asarray(direction, np.float64)
    return float(np.degrees(np.arcsin(np.clip(d[1] / np.linalg.norm(d), -1.0, 1.0))))


def _truth_fit_rows(truth, model_name, grid, case, meta, fit_cache):
    """(method, metrics, run time) of ``model_name`` fitted to ``truth``, as fitted and with its
    sun moved by MOVED_SUN_DEG (:mod:`f2l.evaluation.truth_fit`); none when the fit fails."""
    import sys

    try:
        probe, sun, runtime_s = truth_fit(truth, model_name, grid, case, fit_cache)
    except ProbeFitError as exc:
        print(f"{case}: {model_name} could not be fitted to the true probe: {exc}", file=sys.stderr)
        return []
    out = []
    for name, moved in ((model_name + FIT_SUFFIX, False), (model_name + MOVED_SUFFIX, True)):
        p, s = probe, sun
        if moved and sun is not None:
            s = moved_direction(sun, MOVED_SUN_DEG, case)
            p = sun_moved(probe, grid, sun, s)
        metrics = _pair(p, truth, grid, meta, s)
        metrics.update(dict.fromkeys(RESIDUAL_NAMES, math.nan))
        out.append((name, metrics, runtime_s))
    return out


def _photo_residuals(shards, by_face, est_dir, render_dir, record_case, cache) -> dict:
    """{(face_id, model): {"photo residual": r(estimate), "photo residual, truth": r(truth)}}
    through each record's own transport (:mod:`f2l.evaluation.photo_residual`); a record that cannot
    be read or has no usable pixels gets none (its rows keep NaN)."""
    out = {}
    for rec in iter_records(shards):
        ests = by_face.get(getattr(rec, "face_id", None)) if getattr(rec, "ok", False) else None
        if not ests:
            continue
        try:
            fit = PhotoResidual(rec)
        except EstimationError:
            continue
        truth = _truth_on(render_dir, record_case[rec.face_id], fit.grid, cache)
        r_truth = fit.residual(truth)
        for est in ests:
            probe = read_exr(Path(est_dir) / est["probe_path"]).astype(np.float64)
            if probe.shape[:2] == fit.grid.shape:
                out[(rec.face_id, est["model"])] = {"photo residual": fit.residual(probe), "photo residual, truth": r_truth}
    return out


def _pair(probe, truth, grid, meta, est_sun, sun_at_truth: bool = True):
    sky = meta["sky"]
    overcast = sky["kind"] == "overcast"
    true_sun = None if overcast else np.asarray(sky["sun_direction"])
    metrics = evaluate_pair(probe, truth, grid, overcast=overcast, est_sun_dir=est_sun, gt_sun_dir=true_sun)
    return {**metrics, **diagnostics(probe, truth, grid, true_sun, est_sun, sun_at_truth)}


SUN_AT_TRUTH_NAMES = ("MAE (s), sun at the truth", "MAE (s), sun at the truth, colour matched",
                      "Full-dω MAE (l), sun at the truth")
DIAGNOSTIC_NAMES = ("colour R/G", "colour B/G", "MAE (s), colour matched", "sun share", "sun elevation error (°)",
                    *SUN_AT_TRUTH_NAMES)


def diagnostics(probe: np.ndarray, truth: np.ndarray, grid: LatLongGrid, sun_direction: np.ndarray | None,
                est_sun_direction: np.ndarray | None = None, sun_at_truth: bool = True) -> dict:
    """The module docstring's diagnostics of one estimate (NaN where undefined). ``sun_direction``:
    the true sun (None when overcast); ``est_sun_direction``: the estimate's own sun direction when
    it reports one, else the probe's (:func:`f2l.metrics.lighting.sun_direction`, as Sun-ang);
    ``sun_at_truth``: also score the estimate with its sun moved onto the true one (False for the
    baselines)."""
    weights = (grid.solid_angles * grid.upper_mask)[..., None]
    est_rgb = (np.asarray(probe, np.float64) * weights).sum((0, 1))
    true_rgb = (np.asarray(truth, np.float64) * weights).sum((0, 1))
    out = dict.fromkeys(DIAGNOSTIC_NAMES, math.nan)
    if not (est_rgb > 0).all() or not (true_rgb > 0).all():
        return out
    if sun_direction is not None:
        est_sun = probe_sun_direction(probe, grid) if est_sun_direction is None else np.asarray(est_sun_direction, np.float64)
        out["sun elevation error (°)"] = _elevation_deg(est_sun) - _elevation_deg(sun_direction)
    out["colour R/G"] = float((est_rgb[0] / est_rgb[1]) / (true_rgb[0] / true_rgb[1]))
    out["colour B/G"] = float((est_rgb[2] / est_rgb[1]) / (true_rgb[2] / true_rgb[1]))
    # the scene's rendering is linear in the probe: a colour gain scales its channels
    scene = evaluation_scene(grid)
    truth_pixels = scene.render_pixels(truth)

    def scene_mae(pixels, gain=np.ones(3)) -> float:
        return float(image_metrics(pixels.astype(np.float64) * gain, truth_pixels)["MAE (s)"])

    out["MAE (s), colour matched"] = scene_mae(scene.render_pixels(probe), true_rgb / est_rgb)
    if sun_direction is not None:
        cap = (cap_mask(grid, sun_direction) & grid.upper_mask)[..., None]
        out["sun share"] = float((np.asarray(probe, np.float64) * weights * cap).sum() / est_rgb.sum()
                                 - (np.asarray(truth, np.float64) * weights * cap).sum() / true_rgb.sum())
        if sun_at_truth:
            moved = sun_moved(probe, grid, est_sun, sun_direction)
            moved_rgb = (moved * weights).sum((0, 1))
            moved_pixels = scene.render_pixels(moved)
            out["MAE (s), sun at the truth"] = scene_mae(moved_pixels)
            out["MAE (s), sun at the truth, colour matched"] = scene_mae(moved_pixels, true_rgb / moved_rgb)
            out["Full-dω MAE (l), sun at the truth"] = float(probe_metrics(moved, truth, grid, overcast=False)["Full-dω MAE (l)"])
    return out
