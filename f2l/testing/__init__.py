"""Test helpers for plugin authors: synthetic faces, a round-trip check, the capability checks.

A plugin package tests its model the way f2l tests its own::

    from f2l.testing import check_model, round_trip

    def test_my_model():
        model = check_model("my_model")          # registry load + every declared capability
        cases = round_trip("my_model", n=3)      # faces rendered under the model's own probes
        assert max(c["sun_angle_deg"] for c in cases) < 5

The same helpers are pytest fixtures (``f2l_check_model``, ``f2l_round_trip``,
``f2l_synthetic_faces``) once f2l is installed: its ``pytest11`` entry point loads
:mod:`f2l.testing.pytest_plugin`. ``docs/plugins.md`` explains what each check means.

Faces are rendered by f2l's own forward model (``f2l.synth.render.render_face``: Lambertian
skin, the canonical head, exact visibility), so a round trip checks the plugin's contract and
its optimisation, not accuracy on real photos.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from f2l.lighting.grid import LatLongGrid

DEFAULT_GRID = (64, 128)


@dataclass
class FaceCase:
    """One synthetic face: the estimator's input and its ground truth."""

    observation: object  # f2l.estimate.FaceObservation
    gt_probe: np.ndarray  # (H, W, 3) float32
    gt_sun_direction: np.ndarray | None  # (3,) unit, None for an overcast sky
    overcast: bool
    params: np.ndarray | None = None  # the model parameters it was rendered with (round trips)


def _grid(grid) -> LatLongGrid:
    if isinstance(grid, LatLongGrid):
        return grid
    h, w = grid
    return LatLongGrid(int(h), int(w))


def check_model(name: str, grid=DEFAULT_GRID):
    """Load ``name`` through the registry on ``grid``: the entry point, the abstract methods and
    every declared capability are checked (``f2l.models.capabilities.check_model``)."""
    from f2l.models.registry import load_model

    return load_model(name, _grid(grid))


def synthetic_faces(n: int = 3, grid=DEFAULT_GRID, seed: int = 0, image_size: int = 96,
                    overcast_fraction: float = 0.0) -> list[FaceCase]:
    """``n`` faces under f2l's synthetic skies (CIE clear skies with a vMF sun; independent of
    any plugin's model), ready for ``f2l.estimate.estimate``."""
    from f2l.estimate import FaceObservation
    from f2l.synth.render import make_synthetic_set

    g = _grid(grid)
    out = []
    for face in make_synthetic_set(n, g, seed, image_size=image_size, overcast_fraction=overcast_fraction, threads=1):
        sky = face.meta.get("sky", {})
        overcast = sky.get("kind") == "overcast"
        sun = None if overcast or sky.get("sun_direction") is None else np.asarray(sky["sun_direction"], np.float64)
        obs = FaceObservation(face.normals, face.observed_rgb, face.mask, face.visibility_bits, g)
        out.append(FaceCase(obs, face.gt_probe, sun, overcast))
    return out


def model_probe(model, params: np.ndarray, ground_albedo: float = 0.2) -> np.ndarray:
    """(H, W, 3) float32 probe of ``params``; for ``domain == "sky"`` models with the Lambertian
    ground bounce the estimator assumes (rho_g / pi times the sky's horizontal irradiance)."""
    grid = model.grid
    probe = np.maximum(model.probe(np.asarray(params, np.float64)).astype(np.float64), 0.0)
    if model.domain == "sky":
        rows = grid.sky_rows
        up = np.maximum(grid.directions[:rows, :, 1], 0.0) * grid.solid_angles[:rows]
        probe[rows:] = ground_albedo / np.pi * np.einsum("hwc,hw->c", probe[:rows], up)
    return probe.astype(np.float32)


def random_params(model, rng: np.random.Generator) -> np.ndarray:
    """A plausible parameter vector: one of ``initial_points()``; for a model whose sun angles
    are parameters (``sun-angles``), the sun at a random azimuth and an elevation in 10-70 deg."""
    from f2l.models.capabilities import SunAngles

    starts = np.atleast_2d(np.asarray(model.initial_points(), dtype=np.float64))
    p = starts[rng.integers(len(starts))].copy()
    if isinstance(model, SunAngles):
        lay = model.sun_angles
        p[lay.elevation] = np.radians(rng.uniform(10.0, 70.0))
        p[lay.azimuth] = rng.uniform(-np.pi, np.pi)
    lo, hi = model.bounds()
    return np.clip(p, lo, hi)


def round_trip(model, n: int = 3, seed: int = 0, grid=DEFAULT_GRID, image_size: int = 96,
               params: np.ndarray | None = None, config=None) -> list[dict]:
    """Render ``n`` faces under the model's own probes, estimate each with the model, and score.

    ``model`` is a registered name (loaded and checked through the registry) or an instance;
    ``params`` (n, P) fixes the parameters (default :func:`random_params`). Each dict holds
    ``sun_angle_deg`` (None when either side has no sun), the §5.1 ``metrics``, ``runtime_s``,
    ``params`` (true) and ``estimate`` (the EstimateResult)."""
    from f2l.estimate import EstimatorConfig, FaceObservation, estimate
    from f2l.metrics import evaluate_pair
    from f2l.synth.render import render_face

    if isinstance(model, str):
        model = check_model(model, grid)
    g = model.grid
    rng = np.random.default_rng(seed)
    cases = []
    for i in range(n):
        p = random_params(model, rng) if params is None else np.asarray(params[i], np.float64)
        probe = model_probe(model, p)
        sun = model.sun_direction(p)
        face = render_face(g, probe, np.random.default_rng([seed, i]), image_size=image_size, threads=1,
                           sun_direction=sun)
        obs = FaceObservation(face.normals, face.observed_rgb, face.mask, face.visibility_bits, g)
        t0 = time.perf_counter()
        res = estimate(obs, model, config or EstimatorConfig(threads=1))
        runtime = time.perf_counter() - t0
        angle = None
        if sun is not None and res.sun_direction is not None:
            angle = float(np.degrees(np.arccos(np.clip(np.dot(sun, res.sun_direction), -1.0, 1.0))))
        metrics = evaluate_pair(res.probe, probe, g, overcast=sun is None, est_sun_dir=res.sun_direction,
                                gt_sun_dir=sun)
        cases.append({"sun_angle_deg": angle, "metrics": metrics, "runtime_s": runtime, "params": p,
                      "estimate": res})
    return cases
