"""The realistic face renderer (f2l render-faces): map conventions, ground truth, a tiny case."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("mitsuba")
pytest.importorskip("anny")

from f2l.lighting.grid import LatLongGrid, direction_from_angles  # noqa: E402
from f2l.render.hdri import HELD_OUT_MAPS, OUTDOOR_MAPS, decode_js_module, load_map, repair_ringing  # noqa: E402
from f2l.render.scene import (MapLighting, RenderSettings, SunSkyLighting, ground_truth_probe,  # noqa: E402
                              mitsuba, render_head)


def _eval_emitter(emitter, direction):
    mi = mitsuba()
    si = mi.SurfaceInteraction3f()
    si.wi = mi.ScalarVector3f(*(-np.asarray(direction, dtype=float)))
    return np.array(emitter.eval(si))


def test_shipped_maps_are_outdoor_daylight_in_f2l_layout():
    grid = LatLongGrid(256, 512)
    for name in OUTDOOR_MAPS + HELD_OUT_MAPS:
        radiance = load_map(name)
        assert radiance.shape == (256, 512, 3) and radiance.dtype == np.float32
        assert np.isfinite(radiance).all() and radiance.min() >= 0.0
        energy = (radiance.mean(axis=-1) * grid.solid_angles)
        assert energy[:128].sum() > energy[128:].sum(), f"{name}: the sky (row 0 = zenith) must be the upper half"


def test_held_out_maps_are_drawn_only_when_asked_and_the_eval_draws_stay():
    """`--maps held-out` draws only the three maps no default was chosen on; the evaluation set's
    draws (make eval-real, seed 0) are those it was rendered with."""
    from f2l.render.dataset import RenderOptions, draw_case

    held_out = RenderOptions(maps="held-out", sunsky_fraction=0.0)
    sources = {draw_case(1, i, held_out)["lighting"]["source"] for i in range(24)}
    assert sources == set(HELD_OUT_MAPS) and not sources & set(OUTDOOR_MAPS)
    assert draw_case(0, 3)["lighting"] == {"source": "bridge", "rotation_deg": 321.8667}
    assert draw_case(0, 5)["lighting"]["source"] == "sunsky"
    assert {draw_case(0, i)["lighting"]["source"] for i in range(64)} <= set(OUTDOOR_MAPS) | {"sunsky"}
    with pytest.raises(ValueError, match="maps must be one of"):
        RenderOptions(maps="indoor")


def test_repair_ringing_keeps_energy_and_removes_negatives():
    grid = LatLongGrid(64, 128)
    img = np.full((64, 128, 3), 2.0)
    img[20, 40] = 5000.0  # a sun with a ringing cross of negative and positive lobes
    img[19, 40] = img[21, 40] = img[20, 39] = img[20, 41] = -400.0
    img[18, 40] = img[22, 40] = 150.0
    fixed = repair_ringing(img)
    d_omega = grid.solid_angles[..., None]
    assert fixed.min() >= 0.0
    np.testing.assert_allclose((fixed * d_omega).sum((0, 1)), (img * d_omega).sum((0, 1)), rtol=1e-5)
    assert fixed[20, 40, 0] == fixed[..., 0].max() and fixed[0, 0, 0] == 2.0


def test_decode_js_module_reads_the_data_url():
    payload = b"\x76\x2f\x31\x01 exr bytes"
    import base64

    text = "export default 'data:application/exr;base64," + base64.b64encode(payload).decode() + "'\n"
    assert decode_js_module(text) == payload
    with pytest.raises(ValueError):
        decode_js_module("export default 42")


def test_envmap_orientation_matches_f2l_layout():
    """Mitsuba's envmap, fed by MapLighting, is bright exactly in the f2l direction of the lit texel."""
    mi = mitsuba()
    grid = LatLongGrid(64, 128)
    radiance = np.full((64, 128, 3), 0.01, np.float32)
    row, col = 20, 90
    radiance[row, col] = 100.0
    emitter = mi.load_dict(MapLighting(radiance).emitters(mi)["sky"])
    lit = grid.directions[row, col]
    assert _eval_emitter(emitter, lit)[0] > 50.0
    for other in [(row, 128 - 1 - col), (row, (col + 64) % 128), (63 - row, col)]:  # mirror, half turn, flip
        assert _eval_emitter(emitter, grid.directions[other])[0] < 1.0


def test_sunsky_ground_truth_has_the_sun_in_its_texel_and_a_lit_ground():
    grid = LatLongGrid(128, 256)
    sun = direction_from_angles(np.radians(30.0), np.radians(70.0))
    lighting = SunSkyLighting(sun, turbidity=3.0, ground_albedo=0.2)
    probe = ground_truth_probe(lighting, grid)
    assert np.isfinite(probe).all() and probe.min() >= 0.0
    row, col = grid.direction_to_texel(sun)
    lum = probe.mean(-1)
    assert (lum.argmax() // 256, lum.argmax() % 256) == (int(row), int(col))
    d_omega = grid.solid_angles
    # the sun carries most of a clear sky's energy; its power matches the emitter's disc radiance
    sun_power = probe[row, col].mean() * d_omega[row, col]
    sky_power = (lum[:64] * d_omega[:64]).sum() - sun_power
    assert sun_power > sky_power
    disc = np.pi * np.radians(0.5358 / 2) ** 2
    centre = _eval_emitter(mitsuba().load_dict(lighting._emitter(mitsuba(), sky_scale=0.0)), sun).mean()
    assert 0.6 * centre * disc < sun_power < 1.05 * centre * disc  # limb darkening: below the centre's
    # ground: rho_g E_h / pi, uniform (E_h of the sky texels and the sun, to the map's resolution)
    up = np.clip(grid.directions[..., 1], 0, None)
    e_h = (probe[:64] * (up[:64] * d_omega[:64])[..., None]).sum((0, 1))
    np.testing.assert_allclose(probe[100, 17], 0.2 * e_h / np.pi, rtol=1e-2)  # the sun: its texel centre
    assert np.ptp(probe[64:], axis=(0, 1)).max() < 1e-9


def _ball():
    import trimesh

    from f2l.render.heads import PART_SKIN, Head

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=8.0)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    return Head(v, f, np.full((len(v), 3), 0.5), np.full(len(f), PART_SKIN), v / 8.0)


@pytest.mark.parametrize("kind", ["map", "sunsky"])
def test_a_sun_at_plus_x_lights_the_image_right_side(kind):
    """The convention check the issue asks for: +X is the camera's right in both light sources."""
    sun = direction_from_angles(np.radians(20.0), np.radians(90.0))  # +X, low
    if kind == "map":
        grid = LatLongGrid(64, 128)
        radiance = np.full((64, 128, 3), 0.05, np.float32)
        row, col = grid.direction_to_texel(sun)
        radiance[row, col] = 2000.0
        lighting = MapLighting(radiance)
    else:
        lighting = SunSkyLighting(sun, turbidity=3.0, ground_albedo=0.2)
    out = render_head(_ball(), lighting, RenderSettings(width_px=48, height_px=48, fov_x_deg=40.0,
                                                        camera_distance_cm=40.0, spp=8, specular=False))
    image, depth = out["image"].mean(-1), out["depth_cm"]
    on_ball = (depth > 0) & (depth < 60)
    right, left = image[:, 24:][on_ball[:, 24:]].mean(), image[:, :24][on_ball[:, :24]].mean()
    assert right > 2.0 * left


def test_render_faces_tiny_case_resumes_and_ablations_keep_the_case(tmp_path):
    """One small case through the CLI: files, meta and EXIF; a rerun skips it; a variant re-renders
    the same drawn person, pose, camera and sky."""
    from PIL import Image

    from f2l.io.exr import read_exr
    from f2l.render.dataset import RenderOptions, draw_case

    out = tmp_path / "pbr"
    cmd = [sys.executable, "-m", "f2l.cli", "eval", "render-faces", "--out", str(out), "--n", "1", "--seed", "3",
           "--image-px", "96", "--spp", "4", "--json"]
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr
    assert "CUDA" not in first.stderr, first.stderr  # warp's no-GPU notice goes to the debug log
    summary = json.loads(first.stdout.strip().splitlines()[-1])
    assert summary["ok"] == 1 and not summary["errors"]
    fid = "pbr-s3-00000"
    meta = json.loads((out / "meta" / f"{fid}.json").read_text())
    assert meta["head"]["source"] == "anny" and meta["face_id"] == fid
    probe = read_exr(out / "probes" / f"{fid}.exr")
    assert probe.shape == (128, 256, 3) and np.isfinite(probe).all() and probe.min() >= 0
    photo = Image.open(out / "photos" / f"{fid}.jpg")
    assert photo.size == (96, 96)
    exif = photo.getexif().get_ifd(0x8769)
    focal_mm, per_mm = float(exif[0x920A]), float(exif[0xA20E])
    assert focal_mm * per_mm == pytest.approx(meta["focal_px"], rel=1e-3)
    png = np.asarray(Image.open(out / "png" / f"{fid}.png"))
    assert png.shape == (96, 96, 3) and png.dtype == np.uint8
    assert 0.0 < meta["face_clipped_fraction"] < 0.5
    np.testing.assert_allclose(np.load(out / "truth" / f"{fid}.npz")["normals"][0].astype(float) ** 2 @ np.ones(3),
                               1.0, rtol=1e-3)
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert json.loads(again.stdout.strip().splitlines()[-1])["skipped_existing"] == 1
    base = draw_case(3, 0, RenderOptions())
    for variant in (RenderOptions(specular=False), RenderOptions(max_depth=2), RenderOptions(head="canonical"),
                    RenderOptions(clipping=False)):
        assert draw_case(3, 0, variant) == base


def test_canonical_head_ablation_renders(tmp_path):
    from f2l.render.dataset import RenderOptions, draw_case, render_case

    options = RenderOptions(image_px=64, spp=2, head="canonical", clipping=False)
    out = render_case(draw_case(5, 1, options), options)
    assert out["meta"]["head"]["source"] == "mediapipe-canonical"
    assert out["photo"].shape == (64, 64, 3) and out["meta"]["face_clipped_fraction"] == 0.0


def test_baselines_are_exact_where_they_should_be():
    from f2l.lighting import sh
    from f2l.evaluation.evaluate import baseline_probes

    grid = LatLongGrid(64, 128)
    smooth = np.clip(1.0 + sh.reconstruct(np.eye(9)[2] * 0.8, grid), 0, None)  # 1 + y-dipole: in SH9
    probes = baseline_probes(smooth, grid)
    # texel-mean quadrature: exact for a constant, to the texel's curvature for a dipole
    np.testing.assert_allclose(probes["SH9 oracle"], smooth, atol=2e-3)
    np.testing.assert_allclose(probes["SH25 oracle"], smooth, atol=2e-3)
    np.testing.assert_allclose(baseline_probes(np.ones((64, 128, 3)), grid)["SH25 oracle"], 1.0, atol=1e-12)
    uniform = probes["uniform sky"]
    assert np.ptp(uniform[:32]) == 0 and np.ptp(uniform[32:]) == 0 and uniform[40, 0, 0] == 0.2


def test_eval_real_chain_on_two_rendered_faces(tmp_path):
    """render-faces -> fit-faces -> twin-geometry -> estimate -> eval-real, small: the make
    eval-real chain with its real code paths (tables with baselines, splits, breakdowns)."""
    f2l = [sys.executable, "-m", "f2l.cli"]

    def run(*args):
        proc = subprocess.run([*f2l, *map(str, args)], capture_output=True, text=True, timeout=900)
        assert proc.returncode == 0, proc.stderr[-2000:]
        return proc.stdout

    pbr, fitted, twins = tmp_path / "pbr", tmp_path / "fitted", tmp_path / "twins"
    run("eval", "render-faces", "--out", pbr, "--n", "2", "--seed", "0", "--image-px", "256", "--spp", "16", "--json")
    run("fit-faces", pbr / "photos", "--out", fitted, "--gt-probes", pbr / "probes", "--json", "--no-overlays")
    twin = json.loads(run("eval", "twin-geometry", fitted, "--render", pbr, "--out", twins, "--json"))
    assert twin["twins"] == 2
    from pathlib import Path

    from f2l.io.shards import iter_records

    for rec in iter_records(twins):  # the true mesh seen from f2l's camera at the origin
        meta = json.loads((pbr / "meta" / f"{Path(rec.source_path).stem}.json").read_text())
        depth = -np.asarray(rec.points, float)[np.asarray(rec.mask)][:, 2]
        assert rec.mask.sum() > 100
        assert abs(np.median(depth) - meta["settings"]["camera_distance_cm"]) < 12.0
    run("estimate", fitted, "-m", "sh9", "--out", tmp_path / "est", "--json")
    run("estimate", twins, "-m", "sh9", "--out", tmp_path / "est_twin", "--json")
    text = run("eval", "real", pbr, "--est", tmp_path / "est", "--est", f"true geometry={tmp_path / 'est_twin'}",
               "--out", tmp_path / "report")
    md = (tmp_path / "report" / "eval_real.md").read_text()
    for needed in ("uniform sky", "SH9 oracle", "SH25 oracle", "| sh9 |", "sh9 (true geometry)",
                   "Reporting part (1 cases", "Tuning part (1 cases", "Breakdowns",
                   "What the sun's direction and the light's colour are worth"):
        assert needed in md, needed
    assert md in text
    import csv

    with open(tmp_path / "report" / "eval_real_rows.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert {r["split"] for r in rows} == {"tune", "report"}
    oracle = [float(r["MAE (s)"]) for r in rows if r["method"] == "SH25 oracle"]
    assert all(0.0 <= v < 0.5 for v in oracle)
    # photo residuals: each estimate and the truth through the record's own transport (the
    # baselines have none)
    est_rows = [r for r in rows if r["method"].startswith("sh9")]
    for r in est_rows:
        assert 0.0 < float(r["photo residual"]) < 1.0 and 0.0 < float(r["photo residual, truth"]) < 1.0
    assert all(r["photo residual"] == "nan" for r in rows if r["method"] == "uniform sky")
    # the sun moved onto the true one: scored for the estimates on clear cases, not for baselines
    from f2l.evaluation.evaluate import BASELINES

    for r in rows:
        moved = float(r["MAE (s), sun at the truth"])
        if r["method"] in BASELINES or r["sky_kind"] != "clear":
            assert math.isnan(moved)
        else:
            assert 0.0 <= moved < 1.0, r
            assert 0.0 <= float(r["Full-dω MAE (l), sun at the truth"]) < 1.0
    assert "Does the photo prefer the truth?" in md
    # a set held out from tuning (`--held-out`): one table over every case, no tuning part
    # ... with sunsky fitted to each true probe (its family's oracle), cached for the next run
    run("eval", "real", pbr, "--est", tmp_path / "est", "--out", tmp_path / "held_out", "--held-out", "--fit-truth", "sunsky")
    held = (tmp_path / "held_out" / "eval_real.md").read_text()
    assert "All cases, held out from tuning (2 cases" in held and "Tuning part" not in held
    assert "Breakdowns (all cases)" in held
    assert "| sunsky fitted to the truth | 2 |" in held and "| sunsky fitted to the truth, sun 5° off | 2 |" in held
    assert len(list((tmp_path / "held_out" / "truth_fits" / "sunsky").glob("*.exr"))) == 2
    with open(tmp_path / "held_out" / "eval_real_rows.csv") as fh:
        fits = [r for r in csv.DictReader(fh) if r["method"] == "sunsky fitted to the truth"]
    assert len(fits) == 2 and all(0.0 <= float(r["MAE (s)"]) < 0.5 and float(r["runtime_s"]) > 0 for r in fits)
    proc = subprocess.run([*f2l, "eval", "real", str(pbr), "--est", str(tmp_path / "est"), "--out", str(tmp_path / "x"),
                           "--fit-truth", "no-such-model"], capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0 and "--fit-truth no-such-model" in proc.stderr
    # the geometry share on the same folder layout as make eval-real: seven variants per face; the
    # "true" variant is the twin record itself, so it scores what `estimate` on the twins scored;
    # the ideal photo (f2l's own render of the truth) is scored like the others
    eval_dir = tmp_path / "eval"
    eval_dir.mkdir()
    for name, src in (("pbr", pbr), ("fitted", fitted), ("true_geometry", twins)):
        (eval_dir / name).symlink_to(src)
    share = run("eval", "geometry", eval_dir, "-m", "sh9", "--threads", "1")
    from f2l.evaluation.geometry_share import VARIANTS

    assert all(f"| sh9 | {v} |" in share for v in VARIANTS)
    share_rows = json.loads((eval_dir / "geometry_share_rows.json").read_text())
    assert len(share_rows) == 2 * len(VARIANTS)
    twin_rows = {r["case"]: float(r["MAE (s)"]) for r in rows if r["method"] == "sh9 (true geometry)"}
    for r in share_rows:
        if r["variant"] == "true":
            assert abs(r["MAE (s)"] - twin_rows[r["case"]]) < 1e-3 * max(1.0, twin_rows[r["case"]])
    ideal = [r for r in share_rows if r["variant"] == "true, ideal photo"]
    assert len(ideal) == 2 and all(0.0 <= r["MAE (s)"] < 1.0 for r in ideal)
    # the search's share: each clear face fitted from its own starts and from the true sun, on both
    # meshes; the own-start fit has the elevation profile off, so it is not the estimate scored above
    from f2l.evaluation.search_share import GEOMETRIES
    from f2l.evaluation.search_share import VARIANTS as SEARCH_VARIANTS

    clear = {r["case"] for r in rows if r["sky_kind"] == "clear"}
    assert len(clear) == 2  # seed 0's first two cases (esplanade)
    table = run("eval", "search", eval_dir, "-m", "sunsky", "--threads", "1")
    assert all(f"| sunsky | {g} | {v} |" in table for g in GEOMETRIES for v in SEARCH_VARIANTS)
    search_rows = json.loads((eval_dir / "search_share_rows.json").read_text())
    assert len(search_rows) == len(clear) * len(GEOMETRIES) * len(SEARCH_VARIANTS)
    for r in search_rows:
        assert r["case"] in clear and np.isfinite(r["objective"]) and 0.0 <= r["Sun-ang (°)"] <= 180.0
    from f2l.evaluation.search_share import search_table

    held = search_table(search_rows, held_out=True)
    assert "| all cases |" in held.splitlines()[0] and "tuning part" not in held
    assert held.count("lower objective 2/2") + held.count("lower objective 1/2") + held.count("lower objective 0/2") == 3
    proc = subprocess.run([*f2l, "eval", "search", str(eval_dir), "-m", "sh9"], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode != 0 and "not a compact-sun model" in proc.stderr


def test_render_skies_writes_a_hosek_wilkie_corpus_that_build_prior_reads(tmp_path):
    """`f2l render-skies`: Hosek-Wilkie probes with side files; the same draw for the same index
    whatever --n is; the sun where the side file says; a warm sun and a blue sky (physics, not
    f2l's own sun-colour model); and `f2l build-prior` fits them."""
    from f2l.prior.build import fit_probes, list_probes
    from f2l.io.exr import read_exr
    from f2l.metrics.lighting import angle_deg, sun_direction
    from f2l.models.registry import load_model
    from f2l.render.skies import write_hosek_wilkie_corpus

    grid = LatLongGrid(64, 128)
    paths = write_hosek_wilkie_corpus(tmp_path / "a", 3, seed=5)
    again = write_hosek_wilkie_corpus(tmp_path / "b", 1, seed=5)
    assert [p.name for p in paths] == ["sky_0000.exr", "sky_0001.exr", "sky_0002.exr"]
    assert np.array_equal(read_exr(paths[0]), read_exr(again[0]))
    for path in paths:
        probe = read_exr(path).astype(np.float64)
        side = json.loads(path.with_suffix(".json").read_text())
        assert probe.shape == (64, 128, 3) and np.isfinite(probe).all() and probe.min() >= 0.0
        assert side["source"] == "hosek-wilkie" and 5.0 <= side["sun_elevation_deg"] <= 80.0
        assert angle_deg(sun_direction(probe, grid), np.asarray(side["sun_direction"])) < 2.0
        row, col = grid.direction_to_texel(np.asarray(side["sun_direction"]))
        sun_rgb = probe[int(row), int(col)]
        sky = probe[: grid.sky_rows].reshape(-1, 3)
        sky_rgb = np.median(sky, axis=0)
        assert sun_rgb[0] > sun_rgb[2] and sky_rgb[2] > sky_rgb[0], (sun_rgb, sky_rgb)
    records = fit_probes(list_probes([tmp_path / "a"]), load_model("sunsky", grid))
    assert [r.status for r in records] == ["ok"] * 3
    assert all(r.sun_angle_deg is None or r.sun_angle_deg < 3.0 for r in records)
