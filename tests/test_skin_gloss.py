"""The skin's gloss in the forward model (EstimatorConfig.skin_gloss): s = (rho + g) ⊙ (T l)."""

import dataclasses

import numpy as np
import pytest

from f2l.estimate import EstimatorConfig, FaceObservation, estimate
from f2l.lighting.grid import LatLongGrid
from f2l.models.registry import load_model

GRID = LatLongGrid(32, 64)
SKIN = np.array([0.30, 0.19, 0.14])  # a mid skin tone (linear), the renderer's range
GLOSS = 0.05


def _faces(n: int = 2):
    """(Lambertian face, the same face with an untinted gloss, true probe): the gloss's pixels are
    (rho + g) ⊙ (T l) (noise-free linear shading, so only the colour model differs)."""
    from f2l.synth.render import make_synthetic_set

    for face in make_synthetic_set(n, GRID, 11, image_size=80, overcast_fraction=0.0, threads=1, albedo=SKIN,
                                   sun_elevation_range_deg=(25.0, 55.0)):
        observed = {"lambertian": face.clean_rgb, "glossy": face.clean_rgb * ((SKIN + GLOSS) / SKIN)[None, :]}
        ok = face.mask & (observed["glossy"].max(1) < 0.95)
        yield {k: FaceObservation(face.normals, v.astype(np.float32), ok, face.visibility_bits, GRID)
               for k, v in observed.items()}, face.gt_probe


def _colour(probe: np.ndarray) -> np.ndarray:
    """(R/G, B/G) of the probe's energy (sum of radiance x solid angle)."""
    e = (np.asarray(probe, np.float64).reshape(-1, 3) * GRID.solid_angles_flat[:, None]).sum(0)
    return np.array([e[0] / e[1], e[2] / e[1]])


def test_the_gloss_term_gives_the_light_the_colour_a_lambertian_face_gives_it():
    """With the skin's albedo known, a Lambertian reading (g = 0) of a glossy face gives the light
    the gloss's colour shift (less red, bluer: the photo's skin is); with the gloss in the forward
    model the light comes out as from the same face without gloss read as Lambertian."""
    model = load_model("sunsky", GRID)
    base = dataclasses.replace(EstimatorConfig(), threads=1, fixed_albedo=tuple(SKIN), skin_gloss=0.0)
    shift = np.array([(SKIN[0] + GLOSS) / (SKIN[1] + GLOSS) / (SKIN[0] / SKIN[1]),
                      (SKIN[2] + GLOSS) / (SKIN[1] + GLOSS) / (SKIN[2] / SKIN[1])])
    assert shift[0] < 0.93 and shift[1] > 1.03
    for obs, truth in _faces():
        reference = _colour(estimate(obs["lambertian"], model, base).probe)
        lambertian = _colour(estimate(obs["glossy"], model, dataclasses.replace(base, skin_gloss=0.0)).probe)
        glossy = _colour(estimate(obs["glossy"], model, dataclasses.replace(base, skin_gloss=GLOSS)).probe)
        np.testing.assert_allclose(lambertian / reference, shift, rtol=0.02)
        # the same up to how the L1 data term weighs the channels (their scales differ by the gloss)
        np.testing.assert_allclose(glossy / reference, 1.0, rtol=0.04)
        assert (np.abs(np.log(glossy / reference)) < 0.5 * np.abs(np.log(lambertian / reference))).all()
        assert np.abs(np.log(reference / _colour(truth))).max() < 0.1  # and the reference is near the truth


def test_apparent_albedo_for_sun_models_only():
    from f2l.estimate.problem import FaceProblem

    obs = next(_faces(1))[0]["glossy"]
    rho = np.array([0.3, 0.2, 0.1])
    assert EstimatorConfig().skin_gloss == pytest.approx(0.1)
    cfg = dataclasses.replace(EstimatorConfig(), threads=1, skin_gloss=0.04)
    np.testing.assert_allclose(FaceProblem(obs, load_model("sunsky", GRID), cfg).apparent(rho), rho + 0.04)
    assert FaceProblem(obs, load_model("sh9", GRID), cfg).apparent(rho) is rho  # linear models: Lambertian
    cfg = dataclasses.replace(cfg, skin_gloss=0.0)
    assert FaceProblem(obs, load_model("sunsky", GRID), cfg).apparent(rho) is rho


def test_estimate_cli_skin_gloss(small_shards, tmp_path):
    """``f2l estimate --skin-gloss`` sets the gloss (recorded in run.json, part of the settings that
    a rerun compares); the linear SH models read the skin as Lambertian either way."""
    import json
    import subprocess

    from f2l.io.exr import read_exr
    from tests.plugin_helpers import f2l_cmd

    runs = {}
    for name, extra in (("default", []), ("lambertian", ["--skin-gloss", "0"])):
        out = tmp_path / name
        proc = subprocess.run(f2l_cmd("estimate", str(small_shards), "-m", "sh9", "--out", str(out), "--json", *extra),
                              capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr
        runs[name] = (json.loads((out / "run.json").read_text()), out)
    assert runs["default"][0]["config"]["skin_gloss"] == pytest.approx(0.1)
    assert runs["lambertian"][0]["config"]["skin_gloss"] == 0.0
    assert runs["default"][0]["config_hashes"] != runs["lambertian"][0]["config_hashes"]
    probes = sorted((runs["default"][1] / "probes" / "sh9").glob("*.exr"))
    assert probes
    for p in probes:
        np.testing.assert_array_equal(read_exr(p), read_exr(runs["lambertian"][1] / "probes" / "sh9" / p.name))
    bad = subprocess.run(f2l_cmd("estimate", str(small_shards), "-m", "sh9", "--out", str(tmp_path / "bad"),
                                 "--skin-gloss", "-1"), capture_output=True, text=True, timeout=600)
    assert bad.returncode != 0 and "skin-gloss" in bad.stderr
