"""The project's default sky corpus for a model's prior (``f2l prior sky-corpus``).

``f2l prior sky-corpus --out skies/ --n 400 --seed 0`` writes 400 float32 EXR probes (64 x 128)
from :func:`f2l.synth.skies.random_sky`: CIE 2003 standard clear skies (type 12, Perez form with the
CIE's coefficients, not those of a model's own sky formula, so a prior is not fitted to its own
model) with a vMF sun (κ = 8192) whose colour and intensity follow Rayleigh + aerosol extinction,
sun elevation 5–80°, any azimuth, turbidity 2–6, and 25% CIE overcast skies. Each probe has a JSON
side file with its kind and sun direction. Any other folder of lat-long sky EXRs works the same
(e.g. captured probes from ``f2l ingest``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from f2l.io.atomic import write_text_atomic
from f2l.io.exr import write_exr
from f2l.lighting.grid import LatLongGrid
from f2l.synth.skies import random_sky

__all__ = ["write_sky_corpus"]


def write_sky_corpus(out_dir: str | Path, n: int, seed: int = 0, grid=None,
                     overcast_fraction: float = 0.25, progress: Callable | None = None) -> list[Path]:
    """Write ``n`` random skies (:func:`f2l.synth.skies.random_sky`; the corpus above) to ``out_dir``: ``sky_0000.exr``,
    ``sky_0001.exr``, ... (index zero-padded to 4 digits), each with a ``.json`` side file holding
    its kind, sun direction, turbidity, seed and index. Returns the EXR paths in order."""
    grid = grid or LatLongGrid(64, 128)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, child in enumerate(np.random.SeedSequence(int(seed)).spawn(int(n))):
        probe, info = random_sky(grid, np.random.default_rng(child), overcast_fraction=overcast_fraction)
        path = out / f"sky_{i:04d}.exr"
        write_exr(path, probe)
        write_text_atomic(path.with_suffix(".json"), json.dumps({**info, "seed": int(seed), "index": i}) + "\n")
        paths.append(path)
        if progress:
            progress(1)
    return paths
