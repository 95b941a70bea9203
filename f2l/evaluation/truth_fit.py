"""Each lighting model fitted to the true probe itself (no face): what its family can reach.

``eval-real --fit-truth MODEL`` scores, next to the face estimates, ``MODEL`` fitted directly to
each case's true probe by :func:`f2l.prior.probe_fit.fit_probe` (the paper's Table 1 fit: a
log-compressed, dω-weighted loss over the model's domain plus each channel's energy). The row,
"<model> fitted to the truth", is an oracle of the model family: an estimate from a face can come
near it, not below it, unless the face tells the metric something the probe fit's loss does not
weigh. A second row, "<model> fitted to the truth, sun 5° off", moves that fit's sun by
``MOVED_SUN_DEG`` in a fixed direction per case (:func:`f2l.evaluation.evaluate.sun_moved`): the same
family with a sun as close as a good face estimate puts it.

Fits are cached per case under ``cache_dir/<model>/<case>.exr`` with a JSON beside it (the fit's
sun direction, run time, loss, the model's version and the grid); a cache whose model version or
grid differs is refitted. Writes are atomic, so an interrupted run resumes.
"""

from __future__ import annotations

import json
import math
import zlib
from pathlib import Path

import numpy as np

from f2l.io.atomic import write_text_atomic
from f2l.io.exr import read_exr, write_exr
from f2l.lighting.grid import LatLongGrid
from f2l.models.registry import load_model
from f2l.prior.probe_fit import fit_probe

__all__ = ["FIT_SUFFIX", "MOVED_SUFFIX", "MOVED_SUN_DEG", "is_truth_fit", "moved_direction", "truth_fit"]

FIT_SUFFIX = " fitted to the truth"
MOVED_SUN_DEG = 5.0
MOVED_SUFFIX = f"{FIT_SUFFIX}, sun {MOVED_SUN_DEG:g}° off"


def is_truth_fit(method: str) -> bool:
    return method.endswith(FIT_SUFFIX) or method.endswith(MOVED_SUFFIX)


def moved_direction(direction: np.ndarray, angle_deg: float, case: str) -> np.ndarray:
    """``direction`` (unit) turned by ``angle_deg`` about an axis perpendicular to it, the axis a
    fixed function of ``case`` (crc32 seed), so every run moves a case's sun the same way."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    rng = np.random.default_rng(zlib.crc32(case.encode()))
    axis = np.cross(d, rng.normal(size=3))
    axis /= np.linalg.norm(axis)
    t = math.radians(angle_deg)
    return d * math.cos(t) + np.cross(axis, d) * math.sin(t)


def truth_fit(truth: np.ndarray, model_name: str, grid: LatLongGrid, case: str,
              cache_dir: Path | None) -> tuple[np.ndarray, np.ndarray | None, float]:
    """(probe (H, W, 3) float64, sun direction or None, fit time in s) of ``model_name`` fitted to
    ``truth`` on ``grid``; from ``cache_dir`` when a matching fit is there. Raises
    :class:`~f2l.prior.probe_fit.ProbeFitError` when the probe cannot be fitted."""
    model = load_model(model_name, grid)
    key = {"model": model_name, "model_version": str(model.version), "grid": [grid.height, grid.width]}
    exr = json_path = None
    if cache_dir is not None:
        exr = Path(cache_dir) / model_name / f"{case}.exr"
        json_path = exr.with_suffix(".json")
        if exr.is_file() and json_path.is_file():
            meta = json.loads(json_path.read_text())
            if all(meta.get(k) == v for k, v in key.items()):
                sun = meta["sun_direction"]
                return (read_exr(exr).astype(np.float64), None if sun is None else np.asarray(sun, np.float64),
                        float(meta["runtime_s"]))
    fit = fit_probe(np.asarray(truth, np.float32), model)
    probe = np.asarray(fit.probe, np.float64)
    sun = None if fit.sun_direction is None else np.asarray(fit.sun_direction, np.float64)
    if exr is not None:
        exr.parent.mkdir(parents=True, exist_ok=True)
        write_exr(exr, probe.astype(np.float32))
        write_text_atomic(json_path, json.dumps({**key, "sun_direction": None if sun is None else sun.tolist(),
                                                 "runtime_s": fit.runtime_s, "loss": fit.loss}))
    return probe, sun, float(fit.runtime_s)
