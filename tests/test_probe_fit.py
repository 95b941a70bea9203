"""fit_probe (a lighting model fitted directly to an HDR probe), its loss, and the Sun+Sky prior
features (sunsky_prior) that the fitted parameters feed into."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from f2l.prior.probe_fit import EPS, REC709_LUMA, ProbeFitError, fit_probe, probe_fit_loss
from f2l.lighting.grid import LatLongGrid, direction_from_angles
from f2l.lighting.resample import resample
from f2l_builtin_models import sunsky_prior
from f2l_builtin_models.sunsky import SunSky

GRID = LatLongGrid(32, 64)
COARSE = LatLongGrid(16, 32)
# w_sky rgb, w_sun rgb, elevation 35 deg, azimuth 100 deg, t = 3, kappa = 2000
TRUE = np.array([0.8, 1.0, 1.3, 40.0, 38.0, 33.0, math.radians(35.0), math.radians(100.0), 3.0, 2000.0])
BIG = 1e6


def _angle_deg(a, b) -> float:
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def _loss_of(model, params, probe) -> float:
    """The fit's loss E (probe_fit module docstring) of ``params`` against ``probe``, computed
    with the weights and scale the module documents (sky hemisphere, dOmega, mean luminance)."""
    grid = model.grid
    target = np.asarray(probe, dtype=np.float64).reshape(-1, 3)
    w = np.where(grid.upper_mask.reshape(-1), grid.solid_angles_flat, 0.0)
    w = w / w.sum()
    scale = float((target @ REC709_LUMA) @ w)
    with torch.no_grad():
        rad = model.radiance(torch.as_tensor(np.atleast_2d(params), dtype=torch.float64))
        return float(probe_fit_loss(rad, torch.as_tensor(target), torch.as_tensor(w), scale)[0])


@pytest.fixture(scope="module")
def model():
    return SunSky(GRID)


@pytest.fixture(scope="module")
def own_probe(model):
    """A probe rendered by SunSky itself from TRUE (float64, 32 x 64)."""
    return model.probe(TRUE).astype(np.float64)


@pytest.fixture(scope="module")
def fit_unit(model, own_probe):
    return fit_probe(own_probe, model)


@pytest.fixture(scope="module")
def fit_big(model, own_probe):
    return fit_probe(own_probe * BIG, model)


# -- 1. round trip on the model's own rendering --------------------------------------------------------
def test_own_probe_has_zero_loss_at_the_true_parameters(model, own_probe):
    assert _loss_of(model, TRUE, own_probe) < 1e-9
    # and the same for the 1e6 x brighter copy with w x 1e6: the loss is scale invariant
    big = TRUE.copy()
    big[:6] *= BIG
    assert _loss_of(model, big, own_probe * BIG) < 1e-9


def test_round_trip_recovers_sun_turbidity_kappa(model, fit_unit):
    f = fit_unit
    true_sun = direction_from_angles(TRUE[6], TRUE[7])
    assert f.sun_direction is not None
    assert _angle_deg(f.sun_direction, true_sun) < 0.5
    assert abs(f.params[8] - TRUE[8]) / TRUE[8] < 0.10
    assert TRUE[9] / 2 < f.params[9] < TRUE[9] * 2
    np.testing.assert_allclose(f.params[:3], TRUE[:3], rtol=0.02)  # sky colour and scale
    assert 0.0 <= f.loss < 1e-3
    assert f.loss == pytest.approx(min(f.start_losses))
    assert len(f.start_losses) == 2  # SunSky.probe_starts: kappa 1024 and 8192
    assert f.probe.shape == (GRID.height, GRID.width, 3) and f.probe.dtype == np.float32
    assert np.all(f.probe[GRID.sky_rows:] == 0.0)  # sky-domain model: nothing below the horizon
    assert f.iterations > 0 and f.runtime_s > 0
    # the loss of the returned parameters, evaluated alone (each sun keeps its own lobe quadrature): the fit scored
    # l/s, this call l, a few ulp apart, which |rho'(r)| <= sqrt(2 rho/eps) bounds by 16u sqrt(2 loss/eps)
    assert _loss_of(model, f.params, model.probe(TRUE)) == pytest.approx(
        f.loss, rel=1e-9, abs=16 * 2**-53 * math.sqrt(2 * f.loss / EPS))


def test_round_trip_recovers_sun_intensity_and_reaches_zero_loss(fit_unit):
    np.testing.assert_allclose(fit_unit.params[3:6], TRUE[3:6], rtol=0.05)
    assert fit_unit.loss < 1e-5  # the truth gives 1e-11 (see test_scaled_probe_gives_scaled_intensities)


def test_scaled_probe_gives_the_same_sun_direction(fit_unit, fit_big):
    true_sun = direction_from_angles(TRUE[6], TRUE[7])
    assert _angle_deg(fit_big.sun_direction, true_sun) < 0.5
    assert _angle_deg(fit_big.sun_direction, fit_unit.sun_direction) < 0.5
    assert np.all(fit_big.params[:6] > 1e3 * fit_unit.params[:6])  # intensities follow the probe


def test_fit_loss_is_scale_invariant(model, own_probe, fit_unit):
    """Same parameters up to the intensity scale -> exactly the same loss (the loss is not to blame
    for the scale dependence of the fit below)."""
    scaled = fit_unit.params.copy()
    scaled[:6] *= BIG
    unit = _loss_of(model, fit_unit.params, own_probe)
    # l/s and t/s differ by a few ulp between the scales: |rho'(r)| <= sqrt(2 rho/eps) bounds that by 32u sqrt(2 loss/eps)
    assert _loss_of(model, scaled, own_probe * BIG) == pytest.approx(
        unit, rel=1e-9, abs=32 * 2**-53 * math.sqrt(2 * unit / EPS))


def test_scaled_probe_gives_scaled_intensities(fit_unit, fit_big):
    """The fit is the same problem at any exposure, so both reach the same optimum. The truth's
    loss is ~1e-11; the Charbonnier term (eps = 1e-6) is |r|-like near r = 0, so L-BFGS stops
    wherever its line search meets that kink: within ~1e-6 of the optimum's loss on every
    OpenBLAS/ATen code path (`make test-cpu-paths`: 1e-11 to 2.3e-6), parameters within 1e-4."""
    assert fit_unit.loss < 1e-5 and fit_big.loss < 1e-5
    np.testing.assert_allclose(fit_big.params[:6] / BIG, fit_unit.params[:6], rtol=1e-3)
    np.testing.assert_allclose(fit_big.params[6:], fit_unit.params[6:], rtol=1e-3)
    np.testing.assert_allclose(fit_unit.params, TRUE, rtol=1e-3)


# -- 2. a CIE clear sky (not the model's own sky) --------------------------------------------------
def test_cie_clear_sky_sun_within_one_degree():
    from f2l.synth.skies import random_sky

    grid = LatLongGrid(64, 128)
    probe, info = random_sky(grid, np.random.default_rng(0), overcast_fraction=0.0)
    assert info["kind"] == "clear"
    fit = fit_probe(probe, SunSky(grid))
    assert _angle_deg(fit.sun_direction, info["sun_direction"]) < 1.0
    assert np.isfinite(fit.loss) and fit.loss < 0.1
    assert np.all(np.isfinite(fit.params))


# -- 3. resampling and input validation ----------------------------------------------------------------
def test_probe_on_another_grid_is_resampled(own_probe):
    coarse = SunSky(COARSE)
    fit = fit_probe(own_probe, coarse)  # 32 x 64 probe, 16 x 32 model
    assert fit.probe.shape == (COARSE.height, COARSE.width, 3)
    assert _angle_deg(fit.sun_direction, direction_from_angles(TRUE[6], TRUE[7])) < 2.0
    assert fit.params[8] == pytest.approx(TRUE[8], rel=0.1)
    # the same as fitting the explicitly (energy-preserving) resampled probe
    a = fit_probe(own_probe, coarse, max_iter=5)
    b = fit_probe(resample(own_probe, COARSE.height, COARSE.width), coarse, max_iter=5)
    np.testing.assert_array_equal(a.params, b.params)
    # and a finer probe works too (upsampling)
    up = fit_probe(resample(own_probe, 64, 128).astype(np.float32), coarse, max_iter=5)
    assert np.all(np.isfinite(up.params))


def _black_sky_bright_ground():
    p = np.zeros((COARSE.height, COARSE.width, 3))
    p[COARSE.sky_rows:] = 1.0
    return p


def _nan_fine():
    p = np.ones((32, 64, 3))
    p[3, 5, 1] = np.nan
    return p


def _inf():
    p = np.ones((16, 32, 3))
    p[2, 2, 0] = np.inf
    return p


def _neg():
    p = np.ones((16, 32, 3))
    p[4, 7, 2] = -1e-3
    return p


BAD_PROBES = [
    pytest.param(lambda: np.ones((16, 48, 3)), r"lat-long \(H, 2H, 3\).*\(16, 48, 3\)", id="not-2-to-1"),
    pytest.param(lambda: np.ones((16, 32)), r"lat-long \(H, 2H, 3\).*\(16, 32\)", id="2-d"),
    pytest.param(lambda: np.ones((16, 32, 4)), r"lat-long \(H, 2H, 3\).*\(16, 32, 4\)", id="rgba"),
    pytest.param(lambda: np.ones(32), r"lat-long", id="1-d"),
    pytest.param(lambda: np.ones((0, 0, 3)), r"lat-long|empty|shape", id="empty"),
    pytest.param(lambda: np.full((16, 32, 3), np.nan), r"NaN", id="nan"),
    pytest.param(_nan_fine, r"NaN", id="nan-other-grid"),
    pytest.param(_inf, r"NaN or inf", id="inf"),
    pytest.param(_neg, r"negative", id="negative"),
    pytest.param(lambda: np.zeros((16, 32, 3)), r"black", id="all-black"),
    pytest.param(lambda: np.zeros((32, 64, 3)), r"black", id="all-black-other-grid"),
    pytest.param(_black_sky_bright_ground, r"black over the model's domain", id="black-sky"),
]


@pytest.mark.parametrize("make, message", BAD_PROBES)
def test_bad_probes_raise_probe_fit_error(make, message):
    try:
        fit_probe(make(), SunSky(COARSE), max_iter=2)
    except ProbeFitError as exc:
        import re

        assert re.search(message, str(exc)), str(exc)
    except Exception as exc:  # noqa: BLE001
        raise AssertionError(f"expected ProbeFitError, got {type(exc).__name__}: {exc}") from exc
    else:
        raise AssertionError("no error raised")


def test_probe_fit_error_is_a_value_error():
    assert issubclass(ProbeFitError, ValueError)


def test_explicit_starts_replace_the_models(own_probe):
    coarse = SunSky(COARSE)
    starts = coarse.initial_points()[:3]
    fit = fit_probe(own_probe, coarse, starts=starts, max_iter=3)
    assert len(fit.start_losses) == 3
    fit1 = fit_probe(own_probe, coarse, starts=starts[0], max_iter=3)  # 1-D start is accepted
    assert len(fit1.start_losses) == 1


# -- 4. the loss -------------------------------------------------------------------------------------
def _rho(r: float) -> float:
    return math.sqrt(r * r + EPS * EPS) - EPS


def test_probe_fit_loss_hand_computed():
    target = [[1.0, 2.0, 3.0], [0.0, 0.5, 4.0]]
    rad = [[2.0, 2.0, 2.0], [1.0, 0.0, 8.0]]
    weights = [0.25, 0.75]
    scale = 2.0
    expected = 0.0
    for t_row, l_row, w in zip(target, rad, weights):
        expected += w * sum(_rho(math.log(1 + l / scale) - math.log(1 + t / scale)) for t, l in zip(t_row, l_row)) / 3
    # + the squared relative energy error per channel, averaged over channels
    for c in range(3):
        e_l = sum(w * row[c] for row, w in zip(rad, weights))
        e_t = sum(w * row[c] for row, w in zip(target, weights))
        expected += ((e_l - e_t) / e_t) ** 2 / 3
    got = probe_fit_loss(torch.tensor([rad], dtype=torch.float64), torch.tensor(target, dtype=torch.float64),
                         torch.tensor(weights, dtype=torch.float64), scale)
    assert got.shape == (1,)
    assert float(got[0]) == pytest.approx(expected, rel=1e-12)


def test_probe_fit_loss_negative_radiance_is_leaky_and_clamped():
    target = torch.tensor([[1.0, 1.0, 1.0]], dtype=torch.float64)
    w = torch.tensor([1.0], dtype=torch.float64)
    # l = -1, s = 2: leaky -0.01 (> -1 = -0.5 s): r = log1p(-0.005) - log1p(0.5)
    rad = torch.tensor([[[-1.0, -1.0, -1.0]]], dtype=torch.float64, requires_grad=True)
    loss = probe_fit_loss(rad, target, w, 2.0)
    energy = ((-1.0 - 1.0) / 1.0) ** 2  # relative energy error per channel, l = -1 vs 1
    assert float(loss.detach()[0]) == pytest.approx(_rho(math.log1p(-0.005) - math.log1p(0.5)) + energy, rel=1e-12)
    loss.sum().backward()
    assert torch.all(torch.isfinite(rad.grad)) and torch.all(rad.grad < 0)  # pushes l up
    # l = -1000: leaky -10, clamped to -0.5 s = -1: r = log1p(-0.5) - log1p(0.5), finite
    far = probe_fit_loss(torch.full((1, 1, 3), -1000.0, dtype=torch.float64), target, w, 2.0)
    energy = ((-1000.0 - 1.0) / 1.0) ** 2
    assert float(far[0]) == pytest.approx(_rho(math.log1p(-0.5) - math.log1p(0.5)) + energy, rel=1e-12)


def test_probe_fit_loss_zero_for_identical_and_scale_only_through_s():
    gen = torch.Generator().manual_seed(0)
    target = torch.rand(50, 3, generator=gen, dtype=torch.float64) * 10
    rad = torch.rand(4, 50, 3, generator=gen, dtype=torch.float64) * 10
    w = torch.rand(50, generator=gen, dtype=torch.float64)
    w = w / w.sum()
    same = probe_fit_loss(target[None].expand(3, -1, -1), target, w, 1.7)
    assert same.shape == (3,) and torch.all(same == 0.0)
    base = probe_fit_loss(rad, target, w, 1.7)
    assert base.shape == (4,) and torch.all(base > 0)
    for k in (1e-6, 3.0, 1e6):
        torch.testing.assert_close(probe_fit_loss(rad * k, target * k, w, 1.7 * k), base, rtol=1e-10, atol=1e-14)
    # without scaling s, scaling both radiances changes the loss (the log1p is not scale-free)
    assert not torch.allclose(probe_fit_loss(rad * 1e3, target * 1e3, w, 1.7), base, rtol=1e-3)
    # texels of zero weight do not count
    w0 = w.clone()
    w0[:10] = 0.0
    rad2 = rad.clone()
    rad2[:, :10] = 123.0
    torch.testing.assert_close(probe_fit_loss(rad2, target, w0, 1.7), probe_fit_loss(rad, target, w0, 1.7))


# -- 5. Sun+Sky prior features ------------------------------------------------------------------------
def _random_params(n=200, seed=0):
    rng = np.random.default_rng(seed)
    p = np.column_stack([
        rng.uniform(0.0, 50.0, (n, 3)), 10.0 ** rng.uniform(-3, 4, (n, 3)),
        rng.uniform(0.0, 0.5 * math.pi, n), rng.uniform(-math.pi, math.pi, n),
        rng.uniform(1.7, 35.0, n), np.exp(rng.uniform(math.log(8.0), math.log(8192.0), n)),
    ])
    p[::10, 3:6] = 0.0  # overcast: no sun
    if n < 10:
        return p
    p[7, 0:3] = 0.0  # black sky
    p[8, 6], p[9, 6] = 0.0, 0.5 * math.pi  # the bounds themselves
    p[8, 8:10] = (1.7, 8.0)
    p[9, 8:10] = (35.0, 8192.0)
    return p


def test_features_numpy_and_torch_agree_and_are_finite():
    p = _random_params()
    fn = sunsky_prior.features_numpy(p)
    ft = sunsky_prior.features_torch(torch.tensor(p, dtype=torch.float64)).numpy()
    assert fn.shape == (200, 8) == ft.shape
    assert len(sunsky_prior.FEATURE_NAMES) == 8
    assert np.all(np.isfinite(fn)) and np.all(np.isfinite(ft))
    np.testing.assert_allclose(ft, fn, rtol=1e-10, atol=1e-12)
    # overcast (w_sun = 0): the ratio feature is at its floor, the sun colour neutral
    np.testing.assert_allclose(fn[::10, 3], math.log(sunsky_prior.RATIO_FLOOR), rtol=1e-12)
    np.testing.assert_allclose(fn[::10, 6:8], 0.0, atol=1e-12)
    # hand values on one vector
    q = p[1]
    luma = np.asarray(sunsky_prior.REC709_LUMA)
    assert fn[1, 0] == q[6] and fn[1, 1] == pytest.approx(math.log(q[8])) and fn[1, 2] == pytest.approx(math.log(q[9]))
    assert fn[1, 3] == pytest.approx(math.log((q[3:6] @ luma) / (math.pi * (q[0:3] @ luma)) + 1e-3))
    assert fn[1, 4] == pytest.approx(math.log(q[0] / q[1])) and fn[1, 5] == pytest.approx(math.log(q[2] / q[1]))
    assert fn[1, 6] == pytest.approx(math.log(q[3] / q[4]), rel=1e-4)
    # no azimuth, no exposure: rotating the sun or scaling all w changes nothing
    # (row 7, the black sky, is excluded: w_sky is floored at 1e-12 there, so scaling it is not free)
    r = p.copy()
    r[:, 7] += 1.0
    r[:, :6] *= 37.0
    keep = np.arange(len(p)) != 7
    np.testing.assert_allclose(sunsky_prior.features_numpy(r)[keep], fn[keep], rtol=1e-10, atol=1e-12)


def test_params_from_features_round_trip():
    rng = np.random.default_rng(1)
    p = _random_params(seed=1)
    p[:, 3:6] = 10.0 ** rng.uniform(-2, 4, (len(p), 1)) * rng.uniform(0.3, 1.5, (len(p), 3))  # suns
    p[:, 6] = np.clip(p[:, 6], 0.03, 0.5 * math.pi - 0.03)  # params_from_features keeps 0.02 off the ends
    p[:, 0:3] = np.maximum(p[:, 0:3], 0.05)
    luma = np.asarray(sunsky_prior.REC709_LUMA)
    ratio = (p[:, 3:6] @ luma) / (math.pi * (p[:, 0:3] @ luma))
    keep = ratio > 1e-2  # far above RATIO_FLOOR, so the ratio survives the log(r + 1e-3)
    p, ratio = p[keep], ratio[keep]
    f = sunsky_prior.features_numpy(p)
    q = sunsky_prior.params_from_features(f)
    n_az = len(sunsky_prior.START_AZIMUTHS_RAD)
    assert q.shape == (n_az * len(p), 10)
    q = q.reshape(len(p), n_az, 10)
    np.testing.assert_allclose(q[:, :, 7], np.broadcast_to(sunsky_prior.START_AZIMUTHS_RAD, (len(p), n_az)))
    for j in range(n_az):
        qj = q[:, j]
        np.testing.assert_allclose(qj[:, 6], p[:, 6], rtol=1e-12)
        np.testing.assert_allclose(qj[:, 8], p[:, 8], rtol=1e-12)
        np.testing.assert_allclose(qj[:, 9], p[:, 9], rtol=1e-12)
        np.testing.assert_allclose(qj[:, 0:3] @ luma, 1.0, rtol=1e-12)  # w_sky of unit luminance
        np.testing.assert_allclose((qj[:, 3:6] @ luma) / (math.pi * (qj[:, 0:3] @ luma)), ratio, rtol=1e-8)
        np.testing.assert_allclose(qj[:, [0, 2]] / qj[:, [1]], p[:, [0, 2]] / p[:, [1]], rtol=1e-10)
        # sun colour as the features define it: (w + 1e-6 lum(w)) ratios
        eps_sun = p[:, 3:6] + 1e-6 * (p[:, 3:6] @ luma)[:, None]
        np.testing.assert_allclose(qj[:, [3, 5]] / qj[:, [4]], eps_sun[:, [0, 2]] / eps_sun[:, [1]], rtol=1e-10)
        np.testing.assert_allclose(qj[:, [3, 5]] / qj[:, [4]], p[:, [3, 5]] / p[:, [4]], rtol=1e-5)
    # and its features are the features we started from
    # (the sun colours to ~1e-6: the features add 1e-6 lum(w_sun) to each channel once more)
    fq = sunsky_prior.features_numpy(q[:, 0])
    np.testing.assert_allclose(fq[:, :6], f[:, :6], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fq[:, 6:], f[:, 6:], atol=1e-5)


def test_params_from_features_of_overcast_is_finite():
    p = _random_params()[::10]  # all w_sun = 0
    q = sunsky_prior.params_from_features(sunsky_prior.features_numpy(p))
    assert np.all(np.isfinite(q)) and np.all(q[:, 0:6] > 0)


def test_features_torch_gradients():
    p = _random_params(n=40, seed=2)
    x = torch.tensor(p, dtype=torch.float64, requires_grad=True)
    gen = torch.Generator().manual_seed(0)
    weights = torch.randn(40, 8, generator=gen, dtype=torch.float64)
    (sunsky_prior.features_torch(x) * weights).sum().backward()
    assert torch.all(torch.isfinite(x.grad))
    assert torch.all(x.grad[:, 7] == 0.0)  # no azimuth
    # analytic gradient == finite differences at interior points
    inner = torch.tensor(_random_params(n=6, seed=3)[1:6], dtype=torch.float64)
    inner[:, 6] = inner[:, 6].clamp(0.1, 1.4)
    inner[:, 8] = inner[:, 8].clamp(2.0, 30.0)
    inner[:, 9] = inner[:, 9].clamp(10.0, 8000.0)
    inner[:, 0:3] = inner[:, 0:3].clamp_min(0.1)
    assert torch.autograd.gradcheck(sunsky_prior.features_torch, (inner.requires_grad_(True),), eps=1e-7, atol=1e-5)
