"""A corpus of physically based clear skies for priors (``f2l eval render-skies``; needs ``f2l[render]``).

Each sky is Mitsuba 3's Hosek–Wilkie ``sunsky`` over a Lambertian ground, made into a probe
exactly as ``f2l eval render-faces`` makes its ground truth (:func:`f2l.render.scene.ground_truth_probe`:
the sky's area average per texel, the ground lit by sky and sun below the horizon, the sun's
disc power in the texel of its direction). Random draws, independent of any evaluation set's:
sun elevation uniform in 5–80°, azimuth uniform, turbidity uniform in 2–8, ground albedo uniform
in 0.1–0.3 (the ranges of ``render-faces``). Files follow ``f2l prior sky-corpus``: ``sky_0000.exr``, …
(float32, the DESIGN lat-long convention) with a JSON side file holding the kind ("clear", or
"overcast" where the §5.1 heuristic says so), the sun direction and the draw.

``f2l prior build`` takes this folder next to the CIE corpus of ``f2l prior sky-corpus``: the CIE skies
carry f2l's own sun-colour model, these carry Hosek–Wilkie's measured-spectrum sun and sky colours.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from f2l.lighting.grid import LatLongGrid, direction_from_angles

ELEVATION_DEG = (5.0, 80.0)
TURBIDITY = (2.0, 8.0)
GROUND_ALBEDO = (0.1, 0.3)


def draw_sky(rng: np.random.Generator) -> dict:
    """One random Hosek–Wilkie sky (JSON-ready): elevation/azimuth in degrees, turbidity, ground albedo."""
    return {"sun_elevation_deg": float(rng.uniform(*ELEVATION_DEG)), "sun_azimuth_deg": float(rng.uniform(-180.0, 180.0)),
            "turbidity": float(rng.uniform(*TURBIDITY)), "ground_albedo": float(rng.uniform(*GROUND_ALBEDO))}


def sky_probe(draw: dict, grid: LatLongGrid) -> np.ndarray:
    """(H, W, 3) float64 probe of one draw (module docstring)."""
    from f2l.render.scene import SunSkyLighting, ground_truth_probe

    sun = direction_from_angles(np.radians(draw["sun_elevation_deg"]), np.radians(draw["sun_azimuth_deg"]))
    return ground_truth_probe(SunSkyLighting(sun, draw["turbidity"], draw["ground_albedo"]), grid)


def write_hosek_wilkie_corpus(out_dir: str | Path, n: int, seed: int = 0, grid: LatLongGrid | None = None,
                              progress: Callable | None = None) -> list[Path]:
    """Write ``n`` skies to ``out_dir`` (``sky_0000.exr`` + ``.json``); returns the EXR paths in order.
    Sky ``i`` of a seed is the same whatever ``n`` is."""
    from f2l.io.atomic import write_text_atomic
    from f2l.io.exr import write_exr
    from f2l.metrics.lighting import is_overcast

    grid = grid or LatLongGrid(64, 128)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, child in enumerate(np.random.SeedSequence([int(seed), 0x4857]).spawn(int(n))):
        draw = draw_sky(np.random.default_rng(child))
        probe = sky_probe(draw, grid)
        if not np.isfinite(probe).all() or probe.min() < 0:
            raise ValueError(f"Hosek-Wilkie sky {i} of seed {seed} is not finite and non-negative: {draw}")
        path = out / f"sky_{i:04d}.exr"
        write_exr(path, probe.astype(np.float32))
        sun = direction_from_angles(np.radians(draw["sun_elevation_deg"]), np.radians(draw["sun_azimuth_deg"]))
        side = {"kind": "overcast" if is_overcast(probe, grid) else "clear", "source": "hosek-wilkie",
                "sun_direction": [float(c) for c in sun], **draw, "seed": int(seed), "index": i}
        write_text_atomic(path.with_suffix(".json"), json.dumps(side) + "\n")
        paths.append(path)
        if progress:
            progress(1)
    return paths
