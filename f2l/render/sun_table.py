"""The Hosek–Wilkie sun/sky table that ``f2l make-probes --restore-sun`` ships with
(:mod:`f2l.capture.sun_restore`), made and checked here with Mitsuba 3 (``f2l[render]``):
``make sun-table`` runs ``python -m f2l.render.sun_table``."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from f2l.capture.sun_restore import (_LUMA, PHI_STEP_DEG, TABLE_ELEVATIONS_DEG, TABLE_FILE, TABLE_TURBIDITIES,
                                     THETA_STEP_DEG, _sun_frame, _table, restore_sun)


def build_table(path: Path = TABLE_FILE) -> dict:
    """Tabulate Hosek–Wilkie skies and suns (needs ``f2l[render]``: Mitsuba's ``sunsky``)."""
    from f2l.lighting.grid import direction_from_angles
    from f2l.render.scene import SunSkyLighting, _eval, mitsuba

    mi = mitsuba()
    thetas = np.arange(0.0, 90.0 + 1e-9, THETA_STEP_DEG)
    phis = np.arange(0.0, 180.0 + 1e-9, PHI_STEP_DEG)
    tt, pp = np.meshgrid(np.radians(thetas), np.radians(phis), indexing="ij")
    log_rel = np.zeros((len(TABLE_ELEVATIONS_DEG), len(TABLE_TURBIDITIES), len(thetas), len(phis)), np.float32)
    ratio = np.zeros(log_rel.shape[:2])
    rgb = np.zeros(log_rel.shape[:2] + (3,))
    for i, elev in enumerate(TABLE_ELEVATIONS_DEG):
        sun = direction_from_angles(math.radians(elev), 0.0)
        e1, e2 = _sun_frame(sun)
        dirs = (np.cos(tt)[..., None] * np.array([0.0, 1.0, 0.0])
                + np.sin(tt)[..., None] * (np.cos(pp)[..., None] * e1 + np.sin(pp)[..., None] * e2))
        dirs[..., 1] = np.maximum(dirs[..., 1], math.cos(math.radians(89.5)))  # the horizon row: just above it
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        for j, t in enumerate(TABLE_TURBIDITIES):
            light = SunSkyLighting(sun_direction=sun, turbidity=float(t), ground_albedo=0.2)
            sky = mi.load_dict(light._emitter(mi, sun_scale=0.0))
            lum = _eval(sky, mi, dirs.reshape(-1, 3)).reshape(dirs.shape) @ _LUMA
            log_rel[i, j] = np.log(np.maximum(lum, 1e-12) / lum[0, 0])
            power = np.asarray(light.sun_power(), dtype=np.float64)
            ratio[i, j] = float(power @ _LUMA) / float(lum[0, 0])
            rgb[i, j] = power / float(power @ _LUMA)
    np.savez_compressed(path, elevation_deg=np.asarray(TABLE_ELEVATIONS_DEG, np.float64),
                        turbidity=np.asarray(TABLE_TURBIDITIES, np.float64), log_rel=log_rel.astype(np.float16),
                        sun_over_zenith=ratio, sun_rgb=rgb,
                        description=np.asarray("Hosek-Wilkie (Mitsuba 3 sunsky) clear skies: log(L / L_zenith) over "
                                               f"zenith angle 0..90 step {THETA_STEP_DEG} x azimuth from the sun "
                                               f"0..180 step {PHI_STEP_DEG} deg, per sun elevation x turbidity; sun "
                                               "illuminance at normal incidence / zenith luminance; sun Rec.709 "
                                               "colour (luminance 1). Made by `make sun-table`."))
    _table.cache_clear()
    return _table()


def check_table(elevations_deg=(4, 10, 18, 27, 33, 47, 58, 73, 84), turbidities=(1.8, 2.7, 3.3, 4.5, 6.5, 8.5),
                noise: float = 0.02, seed: int = 0) -> np.ndarray:
    """Restored / true sun energy on Hosek–Wilkie skies between the table's nodes (2% noise per
    texel, an up-looking hemisphere, the sun's 1.5° cap clipped): (elevations, turbidities)."""
    from f2l.lighting.grid import LatLongGrid, direction_from_angles
    from f2l.lighting.resample import resample
    from f2l.render.scene import SunSkyLighting

    grid = LatLongGrid(128, 256)
    rng = np.random.default_rng(seed)
    out = np.full((len(elevations_deg), len(turbidities)), np.nan)
    coverage = np.zeros(grid.shape, bool)
    coverage[: grid.height // 2] = True
    for i, elev in enumerate(elevations_deg):
        for j, t in enumerate(turbidities):
            sun = direction_from_angles(math.radians(elev), 0.7)
            light = SunSkyLighting(sun_direction=sun, turbidity=float(t), ground_albedo=0.2)
            sky = resample(light.sky_map(), grid.height, grid.width) * np.exp(rng.normal(0, noise, grid.shape))[..., None]
            clipped = np.degrees(np.arccos(np.clip(grid.directions @ sun, -1, 1))) < 1.5
            sky[clipped] = 3 * np.median(sky[: grid.height // 2].reshape(-1, 3), axis=0)
            _, result = restore_sun(sky.astype(np.float32), clipped, coverage, sun, grid)
            if result.restored:
                out[i, j] = float(np.asarray(result.sun_energy) @ _LUMA) / float(np.asarray(light.sun_power()) @ _LUMA)
    return out


if __name__ == "__main__":  # make sun-table
    build_table()
    print(f"wrote {TABLE_FILE}")
    ratios = check_table()
    print("restored / true sun energy, Hosek-Wilkie skies between the table's nodes (rows: elevation 4, 10, 18, 27, "
          "33, 47, 58, 73, 84 deg; columns: turbidity 1.8, 2.7, 3.3, 4.5, 6.5, 8.5):")
    for row in ratios:
        print("  " + " ".join(f"{v:5.2f}" for v in row))
    errors = np.abs(np.log(ratios[np.isfinite(ratios)]))
    print(f"restored {np.isfinite(ratios).sum()}/{ratios.size}; median |log ratio| {np.median(errors):.3f}, "
          f"max {errors.max():.3f}")
