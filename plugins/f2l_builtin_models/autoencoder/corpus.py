"""The autoencoder's default sky corpus (``f2l ae corpus``): physically based clear skies plus
partly cloudy and overcast skies, written as float32 lat-long EXR probes with JSON side files.

Each sky draws, in this order, from its own child of ``numpy.random.SeedSequence(seed)``:

- kind: clear (p = 0.40), partly cloudy (0.35) or overcast (0.25);
- sun elevation U[0.5, 89.5] deg (the full range), azimuth U[-180, 180) deg,
  turbidity t log-uniform in [1.7, 12], vMF sun concentration kappa log-uniform in [2048, 8192];
- clear sky: the Preetham (1999) sky of the Sun+Sky plugin (``f2l_builtin_models.sunsky``:
  Perez distribution, Preetham chromaticity, Rec.709), scaled so that its horizontal irradiance is
  r times the sun's luminance at normal incidence, r = r(t) (1 + 2 e^{-elevation / 8 deg}) x
  U[0.8, 1.25], r(t) = ``f2l.synth.skies.sky_to_sun_ratio`` (0.15-0.25: hazier skies are
  relatively brighter; a low sun is dimmed more than the sky);
- sun: the vMF lobe integrated per texel (``f2l.synth.skies.sun_lobe_energy``) times its RGB
  irradiance at normal incidence (``sun_rgb_irradiance``: extra-terrestrial white, Rayleigh and
  aerosol extinction over the Kasten-Young air mass: warmer and dimmer near the horizon);
- partly cloudy: cover U[0.1, 0.9] of procedural clouds (:mod:`f2l_builtin_models.autoencoder.clouds`) over that sky,
  occluding the sun partly or fully where they cross it;
- overcast: :func:`f2l_builtin_models.autoencoder.clouds.overcast_radiance` (no direct sun) at the brightness of the
  clear sky's horizontal irradiance plus a random share (U[0.2, 0.6]) of the sun's;
- ground: Lambertian, albedo U[0.1, 0.35], lit by the sky (rows below the horizon).

Layout: ``OUT/train/sky_00000.exr`` ... (``n_train``) and ``OUT/heldout/sky_00000.exr`` ...
(``n_heldout``, later children of the same seed: never trained on), each with ``.json`` (kind, sun
direction (None when overcast), elevation, azimuth, turbidity, kappa, cloud parameters, the sun's
transmittance, seed, split, index), and ``OUT/corpus.json`` (the recipe). Deterministic from the seed.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Callable

import numpy as np

from f2l_builtin_models.autoencoder import clouds
from f2l.io.atomic import write_text_atomic
from f2l.lighting.grid import LatLongGrid, direction_from_angles

KIND_PROBABILITIES = (("clear", 0.40), ("partly", 0.35), ("overcast", 0.25))
ELEVATION_RANGE_DEG = (0.5, 89.5)
TURBIDITY_RANGE = (1.7, 12.0)
KAPPA_RANGE = (2048.0, 8192.0)
DEFAULT_GRID = LatLongGrid(128, 256)
REC709_LUMA = np.array([0.2126, 0.7152, 0.0722])


def _normalised_preetham(grid: LatLongGrid, elevation: float, azimuth: float, turbidity: float) -> np.ndarray:
    """(sky_rows, W, 3) Preetham sky of mean luminance 1 (``SunSky.sky``), float64."""
    import torch

    from f2l_builtin_models.sunsky import SunSky

    params = torch.tensor([[1.0, 1.0, 1.0, 0.0, 0.0, 0.0, elevation, azimuth, turbidity, 1024.0]], dtype=torch.float64)
    with torch.no_grad():
        sky = SunSky(grid).sky(params)[0].numpy()
    return sky.reshape(grid.sky_rows, grid.width, 3)


def _horizontal_weights(grid: LatLongGrid) -> np.ndarray:
    """(sky_rows, W) max(cos zenith, 0) dω: horizontal irradiance = Σ weights · radiance."""
    rows = grid.sky_rows
    return np.maximum(np.array(grid.directions[:rows])[..., 1], 0.0) * np.array(grid.solid_angles[:rows])


def _sun(elevation: float, azimuth: float, turbidity: float, ratio_jitter: float):
    """(sun direction, RGB irradiance at normal incidence, its luminance, sky-to-sun ratio r)."""
    from f2l.synth.skies import sky_to_sun_ratio, sun_rgb_irradiance

    sun_rgb = sun_rgb_irradiance(elevation, turbidity)
    ratio = sky_to_sun_ratio(turbidity) * (1.0 + 2.0 * math.exp(-math.degrees(elevation) / 8.0)) * ratio_jitter
    return direction_from_angles(elevation, azimuth), sun_rgb, float(sun_rgb @ REC709_LUMA), ratio


def _clear_and_sun(grid: LatLongGrid, elevation: float, azimuth: float, turbidity: float, kappa: float,
                   ratio_jitter: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The clear corpus sky's two parts on the sky rows, (rows, W, 3) float64 each: the Preetham sky
    at r times the sun's luminance in horizontal irradiance, and the vMF sun lobe (module docstring)."""
    from f2l.synth.skies import sun_lobe_energy

    sun_dir, sun_rgb, sun_lum, ratio = _sun(elevation, azimuth, turbidity, ratio_jitter)
    clear = _normalised_preetham(grid, elevation, azimuth, turbidity)
    clear *= ratio * sun_lum / float(np.einsum("hwc,c,hw->", clear, REC709_LUMA, _horizontal_weights(grid)))
    return clear, sun_lobe_energy(grid, sun_dir, kappa)[: grid.sky_rows, :, None] * sun_rgb


def clear_sky_probe(grid: LatLongGrid, elevation_rad: float, azimuth_rad: float = 0.0, turbidity: float = 3.0,
                    kappa: float = 4096.0, ground_albedo: float = 0.2) -> np.ndarray:
    """A cloudless corpus sky (ratio jitter 1) as a full probe (H, W, 3) float32 with its ground:
    the autoencoder's face search encodes a ladder of these (``AE.search_codes``)."""
    from f2l.synth.skies import horizontal_irradiance

    clear, lobe = _clear_and_sun(grid, elevation_rad, azimuth_rad, turbidity, kappa)
    probe = np.zeros((grid.height, grid.width, 3), dtype=np.float64)
    probe[: grid.sky_rows] = clear + lobe
    probe[grid.sky_rows:] = ground_albedo / math.pi * horizontal_irradiance(grid, probe)
    return probe.astype(np.float32)


def random_ae_sky(grid: LatLongGrid, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """One random sky (module docstring): (probe (H, W, 3) float32 with ground, info dict)."""
    from f2l.synth.skies import horizontal_irradiance

    u = rng.uniform()
    cumulative = np.cumsum([p for _, p in KIND_PROBABILITIES])
    kind = KIND_PROBABILITIES[min(int(np.searchsorted(cumulative, u, side="right")), len(cumulative) - 1)][0]
    elevation = math.radians(rng.uniform(*ELEVATION_RANGE_DEG))
    azimuth = math.radians(rng.uniform(-180.0, 180.0))
    turbidity = float(math.exp(rng.uniform(*np.log(TURBIDITY_RANGE))))
    kappa = float(math.exp(rng.uniform(*np.log(KAPPA_RANGE))))
    ratio_jitter = float(rng.uniform(0.8, 1.25))
    ground_albedo = float(rng.uniform(0.1, 0.35))
    sub = np.random.default_rng(rng.integers(0, 2**63 - 1))

    rows = grid.sky_rows
    dirs = np.array(grid.directions[:rows])
    sa = np.array(grid.solid_angles[:rows])
    sun_dir, sun_rgb, sun_lum, ratio = _sun(elevation, azimuth, turbidity, ratio_jitter)
    info = dict(kind=kind, sun_direction=[float(v) for v in sun_dir], sun_elevation_deg=math.degrees(elevation),
                sun_azimuth_deg=math.degrees(azimuth), turbidity=turbidity, sun_kappa=kappa,
                ground_albedo=ground_albedo, sun_transmittance=1.0)

    probe = np.zeros((grid.height, grid.width, 3), dtype=np.float64)
    if kind == "overcast":
        sky, extra = clouds.overcast_radiance(dirs, sa, sun_dir, sub)
        target = ratio * sun_lum + float(sub.uniform(0.2, 0.6)) * sun_lum  # horizontal irradiance
        sky *= target / float(np.einsum("hwc,c,hw->", sky, REC709_LUMA, _horizontal_weights(grid)))
        info.update(extra, sun_direction=None, sun_transmittance=0.0)
        probe[:rows] = sky
    else:
        clear, lobe = _clear_and_sun(grid, elevation, azimuth, turbidity, kappa, ratio_jitter)
        if kind == "partly":
            cover = float(sub.uniform(0.1, 0.9))
            sky, trans, extra = clouds.partly_cloudy(clear, dirs, sa, sun_dir, sun_rgb, sub, cover)
            energy = float((lobe.sum(-1) * sa).sum())
            seen = float((lobe.sum(-1) * trans * sa).sum())
            info.update(extra, sun_transmittance=seen / energy if energy > 0 else 0.0)
            lobe = lobe * trans[..., None]
        else:
            sky = clear
        probe[:rows] = sky + lobe
    probe[rows:] = ground_albedo / math.pi * horizontal_irradiance(grid, probe)
    return probe.astype(np.float32), info


def recipe(n_train: int, n_heldout: int, seed: int, grid: LatLongGrid) -> dict:
    # "f2l.ae.corpus": the recipe's stable id (the module's name when the shipped weights were trained)
    return {"generator": "f2l.ae.corpus", "n_train": int(n_train), "n_heldout": int(n_heldout), "seed": int(seed),
            "grid": [grid.height, grid.width], "kinds": dict(KIND_PROBABILITIES),
            "sun_elevation_deg": list(ELEVATION_RANGE_DEG), "turbidity": list(TURBIDITY_RANGE),
            "kappa": list(KAPPA_RANGE)}


def write_ae_corpus(out_dir: str | Path, n_train: int, n_heldout: int, seed: int = 0,
                    grid: LatLongGrid = DEFAULT_GRID, progress: Callable | None = None,
                    splits: tuple[str, ...] = ("train", "heldout")) -> dict:
    """Write the corpus (module docstring); returns {"train": [paths], "heldout": [paths]}.

    Existing files with the same recipe are kept (a rerun completes an interrupted corpus).
    ``splits`` limits what is written: ``("heldout",)`` gives exactly the held-out skies of the
    full corpus (each sky has its own seed child) without its training skies, for evaluation."""
    if not splits or any(s not in ("train", "heldout") for s in splits):
        raise ValueError(f"splits must be a non-empty subset of ('train', 'heldout'), got {splits!r}")
    from f2l.io.exr import write_exr

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    info = recipe(n_train, n_heldout, seed, grid)
    manifest = out / "corpus.json"
    if manifest.exists():
        old = json.loads(manifest.read_text())
        if old != info:
            raise ValueError(f"{manifest}: {out} holds another corpus ({old}); choose another --out")
    write_text_atomic(manifest, json.dumps(info, indent=1) + "\n")
    children = np.random.SeedSequence(int(seed)).spawn(int(n_train) + int(n_heldout))
    paths: dict[str, list[Path]] = {"train": [], "heldout": []}
    for i, child in enumerate(children):
        split, index = ("train", i) if i < n_train else ("heldout", i - n_train)
        if split not in splits:
            continue
        path = out / split / f"sky_{index:05d}.exr"
        side = path.with_suffix(".json")
        if not (path.exists() and side.exists()):
            path.parent.mkdir(parents=True, exist_ok=True)
            probe, sky_info = random_ae_sky(grid, np.random.default_rng(child))
            write_exr(path, probe, metadata={"f2l_convention": "latlong,+Y up,centre=-Z"})
            write_text_atomic(side, json.dumps({**sky_info, "seed": int(seed), "split": split, "index": index}) + "\n")
        paths[split].append(path)
        if progress:
            progress(1)
    return paths
