"""The probe's sun spread over the sun direction's posterior (f2l.estimate.sun_spread): the vMF
algebra in closed form, the written lobe's energy, centre and 68% radius on the default grid, and
the estimator's setting (parameters unchanged, header, overcast and off untouched)."""

import doctest
import math

import numpy as np
import pytest
import torch

import f2l.estimate.sun_spread as ss
from f2l.estimate import EstimatorConfig, FaceObservation, estimate
from f2l.lighting.grid import LatLongGrid, direction_from_angles
from f2l.testing import check_model, model_probe

DEFAULT = (64, 128)  # the estimator's grid: 2.8 deg texels
SMALL = (32, 64)


def test_doctests():
    assert doctest.testmod(ss).failed == 0


@pytest.mark.parametrize("radius_deg", [0.01, 0.5, 5.0, 30.0, 90.0, 110.0])
def test_kappa_for_radius_puts_68_percent_of_a_vmf_inside_the_radius(radius_deg):
    r = math.radians(radius_deg)
    k = ss.kappa_for_radius(r)
    held = -math.expm1(-k * 2 * math.sin(r / 2) ** 2) / -math.expm1(-2 * k)  # 1 - cos r without cancellation
    assert held == pytest.approx(0.68, abs=1e-9)


def test_kappa_for_radius_limits():
    assert ss.kappa_for_radius(0.0) == ss.KAPPA_MAX
    assert ss.kappa_for_radius(math.radians(150.0)) == ss.KAPPA_MIN  # uniform already holds 68% there
    assert ss.kappa_for_radius(math.radians(1.0)) > ss.kappa_for_radius(math.radians(2.0))
    with pytest.raises(ValueError):
        ss.kappa_for_radius(0.1, level=1.0)


@pytest.mark.parametrize("ka,kb", [(8192.0, 1e12), (6000.0, 500.0), (1024.0, 3.0), (8.0, 0.01), (8192.0, 8192.0)])
def test_convolved_kappa_multiplies_mean_cosines(ka, kb):
    k = ss.convolved_kappa(ka, kb)
    assert k <= min(ka, kb) + 1e-9
    if kb < ss.KAPPA_MAX:
        assert ss.mean_cosine(k) == pytest.approx(ss.mean_cosine(ka) * ss.mean_cosine(kb), rel=1e-9, abs=1e-12)
    else:
        assert k == ka


def test_convolved_kappa_floors_at_the_widest_lobe():
    assert ss.convolved_kappa(8.0, 1e-6) == ss.KAPPA_MIN


def sunsky_params(model, elevation_deg: float, azimuth_deg: float, kappa: float) -> np.ndarray:
    p = model.initial_points()[0].copy()
    lay = model.sun_layout
    p[list(lay.sky_rgb)] = (0.3, 0.4, 0.6)
    p[list(lay.sun_rgb)] = (50.0, 45.0, 40.0)
    p[lay.elevation], p[lay.azimuth], p[lay.kappa] = math.radians(elevation_deg), math.radians(azimuth_deg), kappa
    return p


def sun_part(model, params: np.ndarray, upper: torch.Tensor) -> np.ndarray:
    """(sky_rows * W,) the sun's share (red channel / w_sun red) of a radiance on the sky rows."""
    p = torch.as_tensor(params[None], dtype=torch.float64)
    sky, w_sky, _ = model.light_parts(p)
    return ((upper[0] - sky[0] * w_sky[0][None, :])[:, 0] / params[model.sun_layout.sun_rgb[0]]).numpy()


@pytest.fixture(scope="module")
def sunsky():
    return check_model("sunsky", DEFAULT)


# (kappa, elevation, cone): the narrowest and widest suns, at the horizon, just above it, halfway
# and at the zenith, under no cone, a vanishing one, a texel's, a wide one and a quarter sphere
CASES = [(8192.0, 0.0, 0.0), (8192.0, 45.0, 1e-4), (8192.0, 90.0, 4.0), (8192.0, 3.0, 25.0), (8192.0, 0.0, 90.0),
         (1024.0, 0.0, 4.0), (1024.0, 45.0, 90.0), (8.0, 90.0, 1e-4), (8.0, 3.0, 25.0), (8.0, 45.0, 90.0)]


@pytest.mark.parametrize("horizon", ss.HORIZONS)
@pytest.mark.parametrize("kappa,elevation_deg,cone_deg", CASES)
def test_the_spread_keeps_the_suns_energy(sunsky, kappa, elevation_deg, cone_deg, horizon):
    from f2l.lighting.sun_lobe import sun_lobe

    grid = sunsky.grid
    t = lambda v: torch.tensor([v], dtype=torch.float64)  # noqa: E731
    args = (t(math.radians(90.0 - elevation_deg)), t(math.radians(70.0)), t(kappa))
    lobe, kappas = ss.spread_lobe(grid, *args, math.radians(cone_deg), horizon)
    sharp = sun_lobe(grid, *args, n_rows=lobe.shape[1] // grid.width)  # over the same rows
    assert torch.isfinite(lobe).all() and (lobe >= 0).all()
    assert 0 < kappas[0] <= kappa
    sa = torch.tensor(grid.solid_angles_flat[: lobe.shape[1]])
    assert float(lobe[0] @ sa) == pytest.approx(float(sharp[0] @ sa), rel=1e-9)
    # the probe's sky rows: the sharp lobe's energy there (renormalise) or at most its full one (drop)
    params = sunsky_params(sunsky, elevation_deg, 70.0, kappa)
    p = torch.as_tensor(params[None], dtype=torch.float64)
    upper, _ = ss.spread_sky_radiance(sunsky, p, math.radians(cone_deg), horizon)
    assert torch.isfinite(upper).all() and (upper >= 0).all()
    e_sky = sun_part(sunsky, params, upper) @ sa[: upper.shape[1]].numpy()
    assert e_sky <= float(lobe[0] @ sa) * (1 + 1e-9)


def test_the_spread_keeps_the_models_sky(sunsky):
    grid = sunsky.grid
    params = sunsky_params(sunsky, 20.0, 70.0, 6000.0)
    params[list(sunsky.sun_layout.sun_rgb)] = 0.0  # without a sun the two are the same
    q = torch.as_tensor(params[None], dtype=torch.float64)
    np.testing.assert_allclose(ss.spread_sky_radiance(sunsky, q, math.radians(10.0))[0].numpy(),
                               sunsky.radiance(q)[:, : grid.sky_rows * grid.width].numpy(), rtol=0, atol=1e-12)


@pytest.mark.parametrize("elevation_deg", [3.0, 45.0, 90.0])
@pytest.mark.parametrize("cone_deg", [4.0, 25.0])
def test_the_spread_lobe_keeps_its_centre(sunsky, elevation_deg, cone_deg):
    params = sunsky_params(sunsky, elevation_deg, -120.0, 6000.0)
    p = torch.as_tensor(params[None], dtype=torch.float64)
    sharp = sun_part(sunsky, params, sunsky.radiance(p)[:, : sunsky.grid.sky_rows * sunsky.grid.width])
    spread = sun_part(sunsky, params, ss.spread_sky_radiance(sunsky, p, math.radians(cone_deg))[0])
    assert int(spread.argmax()) == int(sharp.argmax())
    assert spread.max() < sharp.max()


def radius_holding(lobe: np.ndarray, grid: LatLongGrid, centre: np.ndarray, share: float) -> float:
    """The angle (deg) from ``centre`` inside which the texels hold ``share`` of ``lobe``'s energy."""
    energy = lobe * grid.solid_angles_flat[: lobe.size]
    angle = np.degrees(np.arccos(np.clip(grid.directions_flat[: lobe.size] @ centre, -1, 1)))
    order = np.argsort(angle)
    cum = np.cumsum(energy[order]) / energy.sum()
    return float(angle[order][np.searchsorted(cum, share)])


@pytest.mark.parametrize("cone_deg", [5.0, 10.0, 20.0, 40.0])
def test_the_written_lobes_68_percent_radius_is_the_cone_within_a_texel(sunsky, cone_deg):
    grid = sunsky.grid
    params = sunsky_params(sunsky, 60.0, 30.0, 6000.0)
    p = torch.as_tensor(params[None], dtype=torch.float64)
    lobe = sun_part(sunsky, params, ss.spread_sky_radiance(sunsky, p, math.radians(cone_deg))[0])
    centre = direction_from_angles(math.radians(60.0), math.radians(30.0))
    texel_deg = 180.0 / grid.height
    assert radius_holding(lobe, grid, centre, 0.68) == pytest.approx(cone_deg, abs=texel_deg)


@pytest.fixture(scope="module")
def sunny_face():
    from f2l.synth.render import render_face

    model = check_model("sunsky", SMALL)
    params = sunsky_params(model, 35.0, 150.0, 6000.0)
    grid = LatLongGrid(*SMALL)
    face = render_face(grid, model_probe(model, params), np.random.default_rng(3), image_size=64,
                       albedo=[0.6, 0.45, 0.35], head_pose_deg=[0.0, 0.0, 0.0], threads=1)
    obs = FaceObservation(face.normals, face.observed_rgb, face.mask, face.visibility_bits, grid)
    off = estimate(obs, model, EstimatorConfig(threads=1, skin_gloss=0.0, sun_spread=0.0))
    on = estimate(obs, model, EstimatorConfig(threads=1, skin_gloss=0.0, sun_spread=1.0))
    return model, off, on


def test_the_setting_spreads_the_probe_and_keeps_the_estimate(sunny_face):
    model, off, on = sunny_face
    grid = model.grid
    assert off.sun_spread_kappa is None and on.sun_spread_kappa is not None
    np.testing.assert_array_equal(on.params, off.params)
    np.testing.assert_array_equal(on.sun_direction, off.sun_direction)
    assert on.sun_uncertainty.cone68_deg == off.sun_uncertainty.cone68_deg
    kappa_sun = off.params[model.sun_layout.kappa]
    expected = ss.convolved_kappa(min(kappa_sun, 8192.0), ss.kappa_for_radius(math.radians(off.sun_uncertainty.cone68_deg)))
    assert on.sun_spread_kappa == pytest.approx(expected, rel=1e-9)
    sky = slice(0, grid.sky_rows)
    sa = grid.solid_angles[sky, :, None]
    # the sky rows' energy is kept (float32 probes); the sun's peak is lower
    assert (on.probe[sky] * sa).sum() == pytest.approx((off.probe[sky] * sa).sum(), rel=1e-5)
    assert on.probe.max() < off.probe.max()
    assert np.isfinite(on.probe).all() and (on.probe >= 0).all()


def test_the_exr_header_says_which_sun_it_holds(tmp_path, sunny_face):
    from f2l.estimate.record import _base_row, write_result
    from f2l.io.exr import read_exr_with_metadata

    _, off, on = sunny_face
    headers = {}
    for name, result in (("off", off), ("on", on)):
        row = _base_row({"face_id": name, "source_path": "", "grid_height": SMALL[0], "grid_width": SMALL[1]}, "sunsky")
        write_result(row, result, None, "", "sunsky", tmp_path, name, name, "")
        probe, headers[name] = read_exr_with_metadata(tmp_path / row["probe_path"])
        np.testing.assert_array_equal(probe, result.probe)
    assert "f2l_sun_spread_kappa" not in headers["off"] and "f2l_sun_lobe" not in headers["off"]
    assert float(headers["on"]["f2l_sun_spread_kappa"]) == on.sun_spread_kappa


def test_an_overcast_fit_is_not_spread():
    from f2l.synth.render import render_face

    model = check_model("sunsky", SMALL)
    params = sunsky_params(model, 35.0, 150.0, 6000.0)
    params[list(model.sun_layout.sun_rgb)] = 0.0  # no sun
    grid = LatLongGrid(*SMALL)
    face = render_face(grid, model_probe(model, params), np.random.default_rng(4), image_size=64,
                       albedo=[0.6, 0.45, 0.35], head_pose_deg=[0.0, 0.0, 0.0], threads=1)
    obs = FaceObservation(face.normals, face.observed_rgb, face.mask, face.visibility_bits, grid)
    # every fit judged overcast (sun share below 1): no exact sun core, no profile
    cfg = dict(threads=1, skin_gloss=0.0, sun_elevation_profile_deg=(), sun_core_min_share=1.0)
    off = estimate(obs, model, EstimatorConfig(**cfg, sun_spread=0.0))
    on = estimate(obs, model, EstimatorConfig(**cfg, sun_spread=1.0))
    assert off.timings["sun_core"] == 0.0 and on.sun_spread_kappa is None
    np.testing.assert_array_equal(on.probe, off.probe)


def full_sphere_energy(grid, elevation_deg: float, kappa: float) -> float:
    from f2l.lighting.sun_lobe import sun_lobe_sparse

    t = lambda v: torch.tensor([v], dtype=torch.float64)  # noqa: E731
    vals, flat = sun_lobe_sparse(grid, t(math.radians(90.0 - elevation_deg)), t(math.radians(70.0)), t(kappa))
    return float((vals[0] * torch.tensor(grid.solid_angles_flat)[flat[0]]).sum())


@pytest.mark.parametrize("elevation_deg", [0.0, 5.0, 80.0])
def test_the_horizon_either_drops_or_renormalises_the_part_below_it(sunsky, elevation_deg):
    grid = sunsky.grid
    params = sunsky_params(sunsky, elevation_deg, 70.0, 6000.0)
    p = torch.as_tensor(params[None], dtype=torch.float64)
    cone = math.radians(20.0 if elevation_deg < 45.0 else 10.0)  # 80 deg, 10 deg: below e^-60 under the horizon
    kept = sun_part(sunsky, params, ss.spread_sky_radiance(sunsky, p, cone, "renormalise")[0])
    dropped = sun_part(sunsky, params, ss.spread_sky_radiance(sunsky, p, cone, "drop")[0])
    sharp = sun_part(sunsky, params, sunsky.radiance(p)[:, : grid.sky_rows * grid.width])
    sa = grid.solid_angles_flat[: kept.size]
    assert kept @ sa == pytest.approx(sharp @ sa, rel=1e-9)  # the sharp lobe's energy above the horizon
    if elevation_deg == 0.0:  # half of either lobe is below the horizon
        assert dropped @ sa == pytest.approx(0.5, abs=0.01) and kept @ sa == pytest.approx(0.5, abs=0.01)
    elif elevation_deg == 5.0:  # the sharp lobe is all above, the spread one partly below
        assert 0.5 < dropped @ sa < 0.8 < kept @ sa
    else:  # far above the horizon: both hold the sharp lobe's full energy
        assert dropped @ sa == pytest.approx(full_sphere_energy(grid, elevation_deg, 6000.0), rel=1e-9)
        np.testing.assert_allclose(dropped, kept, rtol=1e-6, atol=1e-9 * kept.max())
    with pytest.raises(ValueError):
        ss.spread_sky_radiance(sunsky, p, cone, "fold")
