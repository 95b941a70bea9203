"""The skin's GGX highlight of a whole probe (f2l.synth.gloss) and the glossy synthetic faces."""

import json
import math

import numpy as np
import pytest

from f2l.lighting.grid import LatLongGrid
from f2l.synth.gloss import (F0_PER_SPECULAR, ROUGHNESS_RANGE, SPECULAR_RANGE, SkinGloss, glossy_highlight,
                             sample_skin_gloss)
from f2l.synth.render import make_synthetic_set
from f2l.synth.skies import sun_lobe_energy

GRID = LatLongGrid(64, 128)


def _all_visible(n_pixels: int, grid: LatLongGrid = GRID) -> np.ndarray:
    return np.packbits(np.ones((n_pixels, grid.size), bool), axis=1, bitorder="little")


def _unit(x) -> np.ndarray:
    x = np.asarray(x, np.float64)
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _brdf_cos(n, v, w, roughness, f0):
    """GGX f_r(v, w) <n, w> for one normal and view and (M, 3) light directions, written out
    independently of the module (Walter et al. 2007, principled α = roughness²)."""
    a2 = roughness ** 4
    h = _unit(w + v)
    nh, vh, nw, nv = h @ n, h @ v, w @ n, float(n @ v)
    d = a2 / (math.pi * (nh ** 2 * (a2 - 1.0) + 1.0) ** 2)
    g1 = lambda c: 2.0 * c / (c + np.sqrt(a2 + (1.0 - a2) * c * c))  # noqa: E731
    f = f0 + (1.0 - f0) * (1.0 - vh) ** 5
    return np.where(nw > 0, d * g1(np.maximum(nw, 1e-9)) * g1(nv) * f / (4.0 * nv), 0.0)


def _directional_albedo(n, v, roughness, f0, steps=(400, 800)):
    """∫ f_r cos dω over the hemisphere of ``n`` by a fine midpoint rule in (θ, φ) about n."""
    th = (np.arange(steps[0]) + 0.5) * (math.pi / 2) / steps[0]
    ph = (np.arange(steps[1]) + 0.5) * 2 * math.pi / steps[1]
    t, p = np.meshgrid(th, ph, indexing="ij")
    a = _unit(np.cross(n, [0.0, 1.0, 0.0] if abs(n[1]) < 0.9 else [1.0, 0.0, 0.0]))
    b = np.cross(n, a)
    w = (np.sin(t)[..., None] * (np.cos(p)[..., None] * a + np.sin(p)[..., None] * b)
         + np.cos(t)[..., None] * n).reshape(-1, 3)
    dw = (np.sin(t) * (math.pi / 2 / steps[0]) * (2 * math.pi / steps[1])).reshape(-1)
    return float((_brdf_cos(n, v, w, roughness, f0) * dw).sum())


@pytest.mark.parametrize("roughness,f0,view_deg", [(0.5, 1.0, 0.0), (0.5, 0.04, 45.0), (0.7, 1.0, 60.0),
                                                   (0.3, 0.04, 30.0)])
def test_white_sky_gives_the_directional_albedo(roughness, f0, view_deg):
    """A uniform white probe, nothing occluded, a flat patch: the highlight is the BRDF's
    directional albedo, against an independent fine quadrature (the grid's texels are 2.8°; they
    agree to ~2e-4)."""
    n = _unit([0.0, 0.0, 1.0])
    v = _unit([math.sin(math.radians(view_deg)), 0.0, math.cos(math.radians(view_deg))])
    spec = glossy_highlight(n[None], -60.0 * v[None], _all_visible(1), GRID, np.ones(GRID.shape + (3,)),
                            roughness, f0)[0]
    assert np.allclose(spec, spec[0])
    assert spec[0] == pytest.approx(_directional_albedo(n, v, roughness, f0), rel=0.003)


def test_energy_is_conserved_even_for_a_mirror_fresnel():
    """Directional albedo ≤ 1 for F0 = 1 at every roughness and view, down to grazing views, and
    it tends to 1 as the lobe sharpens (single-scattering GGX only loses energy)."""
    views = np.radians([0.0, 30.0, 60.0, 80.0, 89.0])
    v = np.stack([np.sin(views), np.zeros_like(views), np.cos(views)], axis=1)
    n = np.tile([0.0, 0.0, 1.0], (len(views), 1))
    white = np.ones(GRID.shape + (3,))
    by_roughness = []
    for roughness in (0.3, 0.5, 0.7, 1.0):
        albedo = glossy_highlight(n, -60.0 * v, _all_visible(len(views)), GRID, white, roughness, 1.0)[:, 0]
        assert np.all(np.isfinite(albedo)) and np.all(albedo <= 1.01) and np.all(albedo > 0.0)
        by_roughness.append(albedo[0])
    assert by_roughness[0] > 0.97 and np.all(np.diff(by_roughness) < 0)


def test_an_extreme_sun_is_finite_and_carries_its_energy():
    """A κ = 8192 sun (a few texels of huge radiance): over random suns around the mirror direction
    the texel-centred highlight stays within 15% of a point sun's exact one and within 2% on
    average; and the flux a unit sun's highlight reflects into the hemisphere of views is at most
    its irradiance (F0 = 1), nearly all of it at roughness 0.3."""
    rng = np.random.default_rng(1)
    v = np.array([0.0, 0.0, 1.0])
    for roughness in (0.3, 0.5):
        got, exact = [], []
        for _ in range(40):
            el, az = np.radians(rng.uniform(20, 60)), np.radians(rng.uniform(-40, 40))
            sun = np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
            n = _unit(_unit(sun + v) + rng.normal(0.0, np.radians(6.0), 3))
            probe = np.repeat(sun_lobe_energy(GRID, sun, 8192.0)[..., None], 3, axis=-1) * 1e4  # E_sun = 1e4
            got.append(glossy_highlight(n[None], -60.0 * v[None], _all_visible(1), GRID, probe, roughness, 0.04)[0, 0])
            exact.append(1e4 * float(_brdf_cos(n, v, sun[None], roughness, 0.04)[0]))
        got, exact = np.array(got), np.array(exact)
        assert np.all(np.isfinite(got))
        assert np.all(np.abs(got / exact - 1.0) < 0.15) and abs(got.sum() / exact.sum() - 1.0) < 0.02
    # reflected flux of a unit-irradiance sun 40° off a +Z patch: ∫ L_r(v) cos θ_v dω_v over views
    sun = np.array([np.sin(np.radians(40.0)), 0.0, np.cos(np.radians(40.0))])
    probe = np.repeat(sun_lobe_energy(GRID, sun, 8192.0)[..., None], 3, axis=-1)
    irradiance = float((probe[..., 0] * GRID.solid_angles * np.maximum(GRID.directions[..., 2], 0)).sum())
    th = (np.arange(45) + 0.5) * (np.pi / 2) / 45
    ph = (np.arange(90) + 0.5) * 2 * np.pi / 90
    t, p = np.meshgrid(th, ph, indexing="ij")
    views = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    dw = (np.sin(t) * (np.pi / 2 / 45) * (2 * np.pi / 90)).reshape(-1)
    n = np.tile([0.0, 0.0, 1.0], (len(views), 1))
    radiance = glossy_highlight(n, -60.0 * views, _all_visible(len(views)), GRID, probe, 0.3, 1.0)[:, 0]
    assert np.all(np.isfinite(radiance))
    flux = float((radiance * views[:, 2] * dw).sum())
    assert 0.9 * irradiance < flux <= 1.02 * irradiance


def test_visibility_is_respected_and_the_sum_splits_over_texels():
    """Hidden texels add nothing: a sun whose texels are hidden gives 0, and the highlights of two
    disjoint visible sets add up to that of their union; float32 agrees with float64, and the
    result does not depend on the pixels' order or the chunk size."""
    rng = np.random.default_rng(0)
    probe = rng.uniform(0.0, 2.0, GRID.shape + (3,))
    sun = _unit([0.3, 0.6, 0.74])
    probe += 1e3 * sun_lobe_energy(GRID, sun, 8192.0)[..., None]
    n = _unit(rng.normal(size=(50, 3)) * [1, 1, 0.3] + [0, 0, 1])
    points = np.column_stack([rng.uniform(-5, 5, (50, 2)), np.full(50, -60.0)])
    vis = rng.uniform(size=(50, GRID.size)) < 0.7
    pack = lambda m: np.packbits(m, axis=1, bitorder="little")  # noqa: E731
    full = glossy_highlight(n, points, pack(vis), GRID, probe, 0.4, 0.04)
    part_a = vis & (rng.uniform(size=vis.shape) < 0.5)
    split = (glossy_highlight(n, points, pack(part_a), GRID, probe, 0.4, 0.04)
             + glossy_highlight(n, points, pack(vis & ~part_a), GRID, probe, 0.4, 0.04))
    assert np.allclose(split, full, rtol=1e-10)
    sun_texels = sun_lobe_energy(GRID, sun, 8192.0).reshape(-1) > 0
    only_sun = np.zeros(GRID.shape + (3,))
    only_sun.reshape(-1, 3)[sun_texels] = probe.reshape(-1, 3)[sun_texels]
    hidden = np.tile(~sun_texels, (50, 1))
    assert np.all(glossy_highlight(n, points, pack(hidden), GRID, only_sun, 0.4, 0.04) == 0.0)
    assert glossy_highlight(n, points, pack(~hidden), GRID, only_sun, 0.4, 0.04).max() > 0.0
    f32 = glossy_highlight(n, points, pack(vis), GRID, probe, 0.4, 0.04, dtype=np.float32)
    assert np.allclose(f32, full, rtol=1e-4, atol=1e-6 * full.max())
    perm = rng.permutation(50)
    shuffled = glossy_highlight(n[perm], points[perm], pack(vis[perm]), GRID, probe, 0.4, 0.04, chunk=7)
    assert np.allclose(shuffled, full[perm], rtol=1e-12)


def test_sampled_gloss_lies_in_the_path_tracers_ranges():
    rng = np.random.default_rng(3)
    draws = [sample_skin_gloss(rng) for _ in range(200)]
    r = np.array([g.roughness for g in draws])
    f0 = np.array([g.f0 for g in draws])
    assert ROUGHNESS_RANGE[0] <= r.min() and r.max() <= ROUGHNESS_RANGE[1] and np.ptp(r) > 0.3
    lo, hi = (F0_PER_SPECULAR * s for s in SPECULAR_RANGE)
    assert lo <= f0.min() and f0.max() <= hi and 0.027 < lo and hi < 0.05


# --- glossy synthetic faces -----------------------------------------------------------------------
SMALL = LatLongGrid(32, 64)


@pytest.fixture(scope="module")
def twins():
    """The same two clear-sky faces rendered Lambertian (the library default) and glossy."""
    kw = dict(image_size=64, overcast_fraction=0.0, threads=1, noise_sigma=0.0)
    plain = list(make_synthetic_set(2, SMALL, seed=6, **kw))  # seed 6: both suns in front of the face
    glossy = list(make_synthetic_set(2, SMALL, seed=6, gloss=True, **kw))
    return plain, glossy


def test_glossy_twin_differs_only_by_the_highlight(twins):
    """Sky, pose, albedo, pixels and visibility are the Lambertian face's (the gloss draws from a
    generator of its own); the linear shading differs by exactly the recorded gloss's highlight;
    meta['gloss'] holds roughness and F0, and the Lambertian record has none."""
    for plain, glossy in zip(*twins):
        assert "gloss" not in plain.meta
        g = glossy.meta["gloss"]
        assert ROUGHNESS_RANGE[0] <= g["roughness"] <= ROUGHNESS_RANGE[1] and 0.02 < g["f0"] < 0.05
        for key in ("pose_deg", "albedo", "sky", "num_pixels"):
            assert plain.meta[key] == glossy.meta[key]
        for a in ("pixel_rc", "visibility_bits", "normals", "points", "gt_probe"):
            if a == "gt_probe":  # same probe, another exposure
                assert np.allclose(plain.gt_probe / plain.meta["exposure_scale"],
                                   glossy.gt_probe / glossy.meta["exposure_scale"], rtol=1e-6)
            else:
                assert np.array_equal(getattr(plain, a), getattr(glossy, a))
        probe = plain.gt_probe / plain.meta["exposure_scale"]
        highlight = glossy_highlight(glossy.normals, glossy.points, glossy.visibility_bits, SMALL, probe,
                                     g["roughness"], g["f0"])
        diff = glossy.clean_rgb / glossy.meta["exposure_scale"] - plain.clean_rgb / plain.meta["exposure_scale"]
        assert np.all(highlight >= 0.0) and highlight.max() > 0.0
        assert np.allclose(diff, highlight, rtol=1e-3, atol=1e-4 * float(np.abs(diff).max()))


def test_glossy_faces_are_brighter_where_they_mirror_the_sun(twins):
    """The highlight's share of the shading peaks where the normal is near the half vector of the
    sun and the view (the sun's mirror direction), and is small where it is far from it."""
    for plain, glossy in zip(*twins):
        sun = np.asarray(plain.meta["sky"]["sun_direction"], np.float64)
        v = _unit(-np.asarray(plain.points, np.float64))
        cos_h = np.einsum("nc,nc->n", np.asarray(plain.normals, np.float64), _unit(v + sun))
        lit = np.einsum("nc,c->n", np.asarray(plain.normals, np.float64), sun) > 0.2
        gain = ((glossy.clean_rgb / glossy.meta["exposure_scale"]).sum(1)
                / (plain.clean_rgb / plain.meta["exposure_scale"]).sum(1))
        near, far = lit & (cos_h > np.cos(np.radians(12.0))), lit & (cos_h < np.cos(np.radians(35.0)))
        assert near.sum() >= 20 and far.sum() >= 20
        assert np.median(gain[near]) > 1.0 + 3.0 * (np.median(gain[far]) - 1.0)
        assert np.median(gain[near]) > 1.1


def test_a_fixed_gloss_and_the_lambertian_default():
    kw = dict(image_size=48, overcast_fraction=1.0, threads=1)
    fixed = next(iter(make_synthetic_set(1, SMALL, seed=2, gloss=SkinGloss(0.5, 0.04), **kw)))
    assert fixed.meta["gloss"] == {"roughness": 0.5, "f0": 0.04}  # overcast skies are glossy too
    plain = next(iter(make_synthetic_set(1, SMALL, seed=2, **kw)))
    off = next(iter(make_synthetic_set(1, SMALL, seed=2, gloss=False, **kw)))
    assert np.array_equal(plain.photo_srgb, off.photo_srgb) and plain.meta == off.meta
    assert fixed.clean_rgb.sum() / fixed.meta["exposure_scale"] > plain.clean_rgb.sum() / plain.meta["exposure_scale"]


def test_cli_synth_is_glossy_unless_lambertian(tmp_path):
    """`f2l eval synth` renders glossy skin by default; --lambertian gives the library's Lambertian
    records, array for array."""
    from typer.testing import CliRunner

    from f2l.cli import app
    from f2l.io.shards import iter_records
    from f2l.synth.dataset import write_synthetic_shards

    runner = CliRunner()
    args = ["eval", "synth", "--n", "2", "--seed", "4", "--grid", "16x32", "--image-size", "32", "--json"]
    for name, extra in (("glossy", []), ("lambertian", ["--lambertian"])):
        res = runner.invoke(app, [*args, "--out", str(tmp_path / name), *extra])
        assert res.exit_code == 0, res.output
        assert json.loads(res.output)["faces"] == 2
    write_synthetic_shards(tmp_path / "library", n=2, seed=4, grid=LatLongGrid(16, 32), image_size=32, progress=False)
    glossy, lamb, lib = (list(iter_records(tmp_path / d)) for d in ("glossy", "lambertian", "library"))
    assert all("gloss" in r.meta for r in glossy) and not any("gloss" in r.meta for r in lamb)
    for a, b, c in zip(lamb, lib, glossy):
        assert np.array_equal(a.observed_rgb, b.observed_rgb) and np.array_equal(a.visibility_bits, b.visibility_bits)
        assert a.meta == b.meta
        assert np.array_equal(a.pixel_rc, c.pixel_rc) and not np.array_equal(a.observed_rgb, c.observed_rgb)


def test_the_demo_renders_glossy_faces(tmp_path):
    from f2l.demo import run_demo
    from f2l.io.shards import iter_records

    result = run_demo(tmp_path, n=2, seed=3, models=["sh9"], echo=lambda *_: None, grid=LatLongGrid(16, 32),
                      image_size=48)
    assert "MAE (s)" in result["markdown"]
    records = list(iter_records(tmp_path / "shards"))
    assert len(records) == 2 and all(ROUGHNESS_RANGE[0] <= r.meta["gloss"]["roughness"] <= ROUGHNESS_RANGE[1]
                                     for r in records)
