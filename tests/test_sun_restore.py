"""Restoring a sun clipped in every frame from the sky (f2l.capture.sun_restore): against
Hosek–Wilkie skies the table did not tabulate (off its elevation/turbidity grid, noisy, another
exposure), refused on real outdoor maps, and end to end through `make-probes --restore-sun`."""

from __future__ import annotations

import json
import math

import numpy as np
import pyarrow.parquet as pq
import pytest

from f2l.capture.sun_restore import restore_sun
from f2l.io.exr import read_exr
from f2l.lighting.grid import LatLongGrid, direction_from_angles
from f2l.lighting.resample import resample

LUMA = np.array([0.2126, 0.7152, 0.0722])
GRID = LatLongGrid(128, 256)


def _hw(elevation_deg: float, turbidity: float, azimuth_rad: float = 0.7):
    pytest.importorskip("mitsuba", reason="Hosek-Wilkie skies come from f2l[render] (Mitsuba)")
    from f2l.render.scene import SunSkyLighting

    sun = direction_from_angles(math.radians(elevation_deg), azimuth_rad)
    light = SunSkyLighting(sun_direction=sun, turbidity=turbidity, ground_albedo=0.2)
    return sun, light.sky_map(), np.asarray(light.sun_power(), dtype=np.float64)


@pytest.mark.parametrize("elevation_deg, turbidity", [(4, 2.2), (13, 6.5), (33, 3.3), (58, 8.5), (84, 1.8)])
def test_restores_hosek_wilkie_suns_off_the_table(elevation_deg, turbidity):
    sun, sky_map, power = _hw(elevation_deg, turbidity)
    rng = np.random.default_rng(int(elevation_deg))
    sky = resample(sky_map, GRID.height, GRID.width) * 7.3  # another exposure
    sky *= np.exp(rng.normal(0, 0.02, GRID.shape))[..., None]  # 2% noise per texel
    coverage = np.zeros(GRID.shape, bool)
    coverage[: GRID.height // 2] = True  # an up-looking fisheye: no ground
    saturated = np.degrees(np.arccos(np.clip(GRID.directions @ sun, -1, 1))) < 1.5
    sky[saturated] = 3 * np.median(sky[:64].reshape(-1, 3), axis=0)  # what a clipped merge keeps
    out, result = restore_sun(sky.astype(np.float32), saturated, coverage, sun, GRID)
    assert result.restored, result.reason
    energy = np.asarray(result.sun_energy)
    assert energy @ LUMA == pytest.approx(7.3 * power @ LUMA, rel=0.15)
    np.testing.assert_allclose(energy / (energy @ LUMA), power / (power @ LUMA), atol=0.05)  # its colour
    sa = GRID.solid_angles
    added = ((out - sky) * sa[..., None]).sum(axis=(0, 1))
    np.testing.assert_allclose(added, energy - np.asarray(result.lower_bound_energy), rtol=1e-4)
    assert result.factor > 10 and "Hosek-Wilkie" in result.message()


def test_refuses_skies_that_are_not_clear():
    """f2l's real CC0 maps (trees, buildings, clouds): the match is refused with the reason."""
    from f2l.metrics.lighting import sun_direction
    from f2l.render.hdri import load_map

    probe = resample(load_map("forest"), GRID.height, GRID.width)
    lum = probe @ LUMA
    saturated = lum > 0.5 * lum.max()
    out, result = restore_sun(probe, saturated, np.ones(GRID.shape, bool), sun_direction(probe, GRID), GRID)
    assert not result.restored and "not match a clear sky" in result.reason
    assert out is probe
    nothing = restore_sun(probe, np.zeros(GRID.shape, bool), np.ones(GRID.shape, bool), np.array([0, 1.0, 0]), GRID)
    assert not nothing[1].restored and "nothing to restore" in nothing[1].reason


def test_make_probes_restores_the_clipped_sun(tmp_path):
    """A fisheye session of a Hosek-Wilkie sky whose sun clips in all 7 frames: the probe holds
    a lower bound; with --restore-sun its sun energy is the truth's within 15%, flagged."""
    from typer.testing import CliRunner

    from f2l.testing.sessions import write_fisheye_session
    from f2l.cli import app

    sun, sky_map, power = _hw(37.0, 3.7, azimuth_rad=1.0)  # between the table's nodes
    scene = np.repeat(np.repeat(sky_map, 4, axis=0), 4, axis=1)  # 1024 x 2048: the disc on ~7 texels
    fine = LatLongGrid(*scene.shape[:2])
    disc = np.degrees(np.arccos(np.clip(fine.directions @ sun, -1, 1))) <= 0.2665
    scene[disc] += power / fine.solid_angles[disc].sum()
    truth = write_fisheye_session(tmp_path / "raw", scene.astype(np.float32), sun_elevation_deg=37.0,
                                  sun_azimuth_deg=math.degrees(1.0))
    fs = float(np.median(scene[: fine.height // 2]) / np.median(truth.probe[: fine.height // 2]))
    root, work = tmp_path / "raw", tmp_path / "work"
    runner = CliRunner()
    assert runner.invoke(app, ["ingest", str(root), "--work", str(work), "--no-detect-roles", "--json"]).exit_code == 0
    energies = {}
    for flag in ([], ["--restore-sun"]):
        res = runner.invoke(app, ["make-probes", str(root), "--work", str(work), "--json", *flag])
        assert res.exit_code == 0, res.output
        (row,) = [r for r in pq.read_table(work / "probes.parquet").to_pylist() if r["kind"] == "probe"]
        probe = read_exr(work / row["path"])
        cap = np.degrees(np.arccos(np.clip(GRID.directions @ sun, -1, 1))) < 2.0
        sky_only = resample(sky_map, GRID.height, GRID.width) / fs
        energies[bool(flag)] = float((((probe - sky_only) * GRID.solid_angles[..., None])[cap]).sum(axis=0) @ LUMA)
        assert row["sun_restored"] is (True if flag else None), row["message"]
    true = float(power @ LUMA) / fs
    assert energies[False] < 0.5 * true  # clipped: a lower bound only
    assert energies[True] == pytest.approx(true, rel=0.15), energies
    assert json.loads(json.dumps(row))["message"].count("sun restored") == 1
