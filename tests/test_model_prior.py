"""GMM priors (model_prior), the sky corpus and prior building (f2l.prior), and the
`f2l sky-corpus` / `f2l fit-probe` / `f2l build-prior` commands."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from f2l.cli import app
from f2l.estimate.model_prior import FORMAT, GmmPrior, fit_gmm, load_prior, save_prior
from f2l.prior.build import ProbeRecord, build_prior, fit_probes, list_probes
from f2l.prior.corpus import write_sky_corpus
from f2l.prior.fit_report import write_fit_report
from f2l.io.exr import read_exr
from f2l.lighting.grid import LatLongGrid
from f2l_builtin_models import sunsky_prior
from f2l_builtin_models.sunsky import SunSky

GRID = LatLongGrid(16, 32)
MEANS = np.array([[0.0, 0.0], [4.0, 3.0]])
WEIGHTS = np.array([0.3, 0.7])
COVS = np.array([[[1.0, 0.3], [0.3, 0.5]], [[0.6, -0.2], [-0.2, 0.8]]])


def _mixture_samples(n=3000, seed=0):
    rng = np.random.default_rng(seed)
    comp = rng.choice(2, size=n, p=WEIGHTS)
    out = np.empty((n, 2))
    for k in range(2):
        sel = comp == k
        out[sel] = rng.multivariate_normal(MEANS[k], COVS[k], size=int(sel.sum()))
    return out


@pytest.fixture(scope="module")
def gmm():
    return fit_gmm(_mixture_samples(), ["a", "b"], n_components=2, seed=0, model="toy", corpus={"n": 3000})


# -- 6. the GMM ---------------------------------------------------------------------------------------
def test_fit_gmm_recovers_a_known_mixture(gmm):
    assert gmm.num_components == 2 and gmm.features == ["a", "b"] and gmm.model == "toy"
    order = np.argsort(gmm.means[:, 0])  # match components by position
    np.testing.assert_allclose(gmm.means[order], MEANS, atol=0.15)
    np.testing.assert_allclose(gmm.weights[order], WEIGHTS, atol=0.1)
    np.testing.assert_allclose(gmm.covariances[order], COVS, atol=0.15)
    assert gmm.weights.sum() == pytest.approx(1.0)


def test_nll_matches_torch_and_scipy(gmm):
    from scipy.special import logsumexp
    from scipy.stats import multivariate_normal

    x = np.random.default_rng(1).normal(2.0, 3.0, size=(100, 2))
    x[0] = [40.0, -30.0]  # far from both components: the log-sum-exp must not underflow
    nll = gmm.nll(x)
    assert nll.shape == (100,) and np.all(np.isfinite(nll))
    nll_t = gmm.nll_torch(torch.tensor(x, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(nll_t, nll, rtol=1e-12, atol=1e-12)
    logs = np.stack([np.log(w) + multivariate_normal(m, c).logpdf(x)
                     for w, m, c in zip(gmm.weights, gmm.means, gmm.covariances)], axis=1)
    np.testing.assert_allclose(nll, -logsumexp(logs, axis=1), rtol=1e-10)
    # in float32 too (cached constants per dtype), and differentiable
    xt = torch.tensor(x[:5], dtype=torch.float64, requires_grad=True)
    gmm.nll_torch(xt).sum().backward()
    assert torch.all(torch.isfinite(xt.grad))
    assert torch.autograd.gradcheck(gmm.nll_torch, (torch.tensor(x[1:4], dtype=torch.float64, requires_grad=True),))
    # float32: ~10 ulp (4e-7) for these well-conditioned covariances, inputs' own rounding included
    np.testing.assert_allclose(gmm.nll_torch(torch.tensor(x, dtype=torch.float32)).numpy(), nll, rtol=1e-4)


def test_nll_single_gaussian_by_hand():
    prior = GmmPrior([1.0], [[1.0, -2.0]], [[[4.0, 0.0], [0.0, 0.25]]], ["u", "v"])
    # -log N(x; mu, diag(4, 1/4)) at x = (3, -1): d = (2, 1), maha = 4/4 + 1/0.25 = 5, det = 1
    assert prior.nll(np.array([[3.0, -1.0]]))[0] == pytest.approx(math.log(2 * math.pi) + 2.5, rel=1e-14)


def test_marginal_integrates_the_dropped_feature_out():
    """The marginal of a mixture over "b": log ∫ p(a, b) db, integrated numerically on a fine grid of
    b, equals the marginal's own log-likelihood; the features can be re-ordered, and one unknown
    name is refused."""
    prior = GmmPrior(WEIGHTS, MEANS, COVS, ["a", "b"])
    marginal = prior.marginal(["a"])
    assert marginal.features == ["a"] and marginal.means.shape == (2, 1) and marginal.covariances.shape == (2, 1, 1)
    a = np.array([-1.0, 0.5, 2.0, 4.5])
    b = np.linspace(-15.0, 18.0, 20001)
    for ai, nll in zip(a, marginal.nll(a[:, None])):
        density = np.exp(-prior.nll(np.column_stack([np.full_like(b, ai), b])))
        assert nll == pytest.approx(-math.log(np.trapezoid(density, b)), rel=1e-9)
    swapped = prior.marginal(["b", "a"])
    x = np.array([[0.3, -0.7], [2.0, 5.0]])
    np.testing.assert_allclose(swapped.nll(x[:, ::-1]), prior.nll(x), rtol=1e-12)
    with pytest.raises(ValueError):
        prior.marginal(["c"])


def test_sunsky_prior_prefers_no_sun_elevation():
    """The sunsky prior term is the GMM marginalised over the sun's elevation: moving only the
    elevation of any parameter vector leaves it unchanged, while the other features still count."""
    model = SunSky(GRID)
    assert model.prior is not None and "sun_elevation_rad" not in model.scored_prior.features
    starts = torch.as_tensor(model.initial_points())
    nll = model.prior_nll(starts)
    for elevation in (0.0, 0.3, 0.8, 1.2, math.pi / 2):
        moved = starts.clone()
        moved[:, 6] = elevation
        torch.testing.assert_close(model.prior_nll(moved), nll, rtol=0, atol=0)
    turbid = starts.clone()
    turbid[:, 8] = 30.0  # far outside the corpus' turbidities
    assert torch.all(model.prior_nll(turbid) > nll + 1.0)


def test_fit_gmm_drops_non_finite_rows_and_caps_components():
    x = _mixture_samples(n=400, seed=2)
    a = fit_gmm(x, ["a", "b"], n_components=2, seed=3)
    noisy = np.vstack([x[:100], [[np.nan, 1.0], [np.inf, 0.0]], x[100:]])
    b = fit_gmm(noisy, ["a", "b"], n_components=2, seed=3)
    np.testing.assert_array_equal(a.means, b.means)
    np.testing.assert_array_equal(a.covariances, b.covariances)
    # at most n / (2 D) components: 10 two-D samples -> 2 components, 3 samples -> 1
    assert fit_gmm(x[:10], ["a", "b"], n_components=6).num_components == 2
    assert fit_gmm(x[:3], ["a", "b"], n_components=6).num_components == 1
    with pytest.raises(ValueError, match="at least 2"):
        fit_gmm(np.vstack([x[:1], [[np.nan, np.nan]]]), ["a", "b"])
    with pytest.raises(ValueError, match="inconsistent"):
        GmmPrior([1.0], [[0.0, 0.0]], [np.eye(2)], ["only-one-name"])


def test_save_load_round_trip(gmm, tmp_path):
    path = save_prior(gmm, tmp_path / "sub" / "prior.json")
    assert path.exists()
    data = json.loads(path.read_text())
    assert data["format"] == FORMAT == "f2l-gmm-prior/1"
    assert data["corpus"] == {"n": 3000}
    back = load_prior(path)
    for name in ("weights", "means", "covariances", "precisions", "log_norm"):
        np.testing.assert_array_equal(getattr(back, name), getattr(gmm, name))
    assert back.features == gmm.features and back.model == gmm.model and back.corpus == gmm.corpus
    x = _mixture_samples(n=20, seed=5)
    np.testing.assert_array_equal(back.nll(x), gmm.nll(x))


@pytest.mark.parametrize("text, message", [
    pytest.param('{"a": 1}', "not an f2l GMM prior", id="other-object"),
    pytest.param('{"format": "f2l-gmm-prior/2", "weights": [1]}', "not an f2l GMM prior", id="other-format"),
    pytest.param("{not json", "cannot read", id="not-json"),
    pytest.param("", "cannot read", id="empty"),
    pytest.param("[1, 2, 3]", "prior", id="json-array"),
    pytest.param('"a string"', "prior", id="json-string"),
    pytest.param('{"format": "f2l-gmm-prior/1", "features": ["a"]}', "prior", id="missing-keys"),
])
def test_load_prior_rejects_non_priors_naming_the_file(tmp_path, text, message):
    path = tmp_path / "not_a_prior.json"
    path.write_text(text)
    try:
        load_prior(path)
    except ValueError as exc:
        assert str(path) in str(exc) and message in str(exc), str(exc)
    except Exception as exc:  # noqa: BLE001
        raise AssertionError(f"expected ValueError, got {type(exc).__name__}: {exc}") from exc
    else:
        raise AssertionError("no error raised")


def test_load_prior_missing_file(tmp_path):
    with pytest.raises(ValueError, match="missing.json"):
        load_prior(tmp_path / "missing.json")


# -- 7. the sky corpus --------------------------------------------------------------------------------
def test_sky_corpus_is_deterministic(tmp_path):
    a = write_sky_corpus(tmp_path / "a", 3, seed=4, grid=GRID)
    b = write_sky_corpus(tmp_path / "b", 3, seed=4, grid=GRID)
    c = write_sky_corpus(tmp_path / "c", 3, seed=5, grid=GRID)
    assert [p.name for p in a] == ["sky_0000.exr", "sky_0001.exr", "sky_0002.exr"]
    assert sorted(x.name for x in (tmp_path / "a").iterdir()) == [
        "sky_0000.exr", "sky_0000.json", "sky_0001.exr", "sky_0001.json", "sky_0002.exr", "sky_0002.json"]
    for i, (pa, pb, pc) in enumerate(zip(a, b, c)):
        ia, ib, ic = read_exr(pa), read_exr(pb), read_exr(pc)
        assert ia.shape == (16, 32, 3) and ia.dtype == np.float32
        assert np.all(np.isfinite(ia)) and np.all(ia >= 0) and ia.max() > 0
        np.testing.assert_array_equal(ia, ib)
        assert not np.array_equal(ia, ic)
        ja = json.loads(pa.with_suffix(".json").read_text())
        assert ja == json.loads(pb.with_suffix(".json").read_text())
        assert ja != json.loads(pc.with_suffix(".json").read_text())
        assert ja["seed"] == 4 and ja["index"] == i and ja["kind"] in ("clear", "overcast")
        if ja["kind"] == "clear":
            assert np.linalg.norm(ja["sun_direction"]) == pytest.approx(1.0) and ja["sun_direction"][1] > 0
        else:
            assert ja["sun_direction"] is None


def test_sky_corpus_overcast_fraction_and_progress(tmp_path):
    calls = []
    paths = write_sky_corpus(tmp_path, 4, seed=0, grid=GRID, overcast_fraction=1.0, progress=calls.append)
    assert calls == [1, 1, 1, 1]
    assert all(json.loads(p.with_suffix(".json").read_text())["kind"] == "overcast" for p in paths)


def test_list_probes_sorted_recursive_and_files(tmp_path):
    write_sky_corpus(tmp_path / "z", 2, seed=0, grid=GRID)
    write_sky_corpus(tmp_path / "a" / "nested", 2, seed=1, grid=GRID)
    (tmp_path / "a" / "notes.txt").write_text("x")
    found = list_probes([tmp_path])
    assert [p.relative_to(tmp_path).as_posix() for p in found] == [
        "a/nested/sky_0000.exr", "a/nested/sky_0001.exr", "z/sky_0000.exr", "z/sky_0001.exr"]
    # folders are listed sorted each, in the order given; files are passed through as given
    single = tmp_path / "z" / "sky_0001.exr"
    assert list_probes([tmp_path / "z", single]) == [tmp_path / "z" / "sky_0000.exr", single, single]
    assert list_probes([tmp_path / "a" / "notes.txt"]) == [tmp_path / "a" / "notes.txt"]
    empty = tmp_path / "empty"
    empty.mkdir()
    assert list_probes([empty]) == []


# -- 8. fit_probes: a bad file does not stop the others -------------------------------------------------
def _angle_deg(a, b) -> float:
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return math.degrees(math.acos(float(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1, 1))))


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """fit_probes over [a corrupt EXR, 2 clear skies] on 16 x 32 (seed 0: both clear)."""
    folder = tmp_path_factory.mktemp("probes")
    good = write_sky_corpus(folder, 2, seed=0, grid=GRID)
    bad = folder / "bad.exr"
    bad.write_bytes(b"this is not an OpenEXR file\x00\x01\x02" * 20)
    paths = list_probes([folder])
    assert paths == [bad, *good]
    calls = []
    records = fit_probes(paths, SunSky(GRID), progress=calls.append, max_iter=40)
    assert calls == [1, 1, 1]
    return folder, records


def test_fit_probes_reports_the_corrupt_file_and_fits_the_others(fitted):
    folder, records = fitted
    assert [r.status for r in records] == ["error", "ok", "ok"]
    err = records[0]
    assert str(folder / "bad.exr") in err.message and err.path == str(folder / "bad.exr")
    assert err.params is None and err.sun_angle_deg is None and err.kind is None
    for r in records[1:]:
        info = json.loads(Path(r.path).with_suffix(".json").read_text())
        assert r.kind == info["kind"] == "clear"
        assert len(r.params) == 10 and np.all(np.isfinite(r.params))
        assert r.true_sun_direction == pytest.approx(info["sun_direction"])
        assert r.sun_angle_deg == pytest.approx(_angle_deg(r.sun_direction, info["sun_direction"]), abs=1e-9)
        assert r.sun_angle_deg < 15.0  # 16 x 32 texels are 11 degrees wide
        assert np.isfinite(r.loss) and r.runtime_s > 0
        assert r.sun_direction == pytest.approx(SunSky(GRID).sun_direction(np.array(r.params)))


def test_fit_probes_other_failures_and_no_side_file(tmp_path):
    from f2l.io.exr import write_exr

    black = tmp_path / "black.exr"
    write_exr(black, np.zeros((16, 32, 3), np.float32))
    missing = tmp_path / "missing.exr"
    records = fit_probes([missing, black], SunSky(GRID), max_iter=5)
    assert [r.status for r in records] == ["error", "error"]
    assert str(missing) in records[0].message
    assert str(black) in records[1].message and "black" in records[1].message


def test_write_fit_report(fitted, tmp_path):
    folder, records = fitted
    model = SunSky(GRID)
    summary = write_fit_report(records, model, tmp_path / "report")
    assert summary["total"] == 3 and summary["ok"] == 2 and summary["errors"] == 1 and summary["sun_angle_n"] == 2
    angles = [r.sun_angle_deg for r in records[1:]]
    assert summary["sun_angle_deg_median"] == pytest.approx(np.median(angles))
    assert summary["sun_angle_deg_mean"] == pytest.approx(np.mean(angles))
    assert "error: " + str(folder / "bad.exr") in summary["markdown"]
    rows = list(csv.DictReader((tmp_path / "report" / "fit_probe.csv").open()))
    assert [r["status"] for r in rows] == ["error", "ok", "ok"]
    assert float(rows[1]["turbidity"]) == pytest.approx(records[1].params[8])
    assert float(rows[2]["sun_angle_deg"]) == pytest.approx(records[2].sun_angle_deg)


# -- 9. build_prior ----------------------------------------------------------------------------------
def _records_from_params(params):
    return [ProbeRecord(f"p{i}.exr", "ok", params=list(p)) for i, p in enumerate(params)]


def test_build_prior_from_records(fitted):
    _, records = fitted
    model = SunSky(GRID)
    prior = build_prior(model, records, n_components=3, seed=0, corpus={"sources": ["x"]})
    assert prior.features == list(model.prior_feature_names) == sunsky_prior.FEATURE_NAMES
    assert prior.model == "sunsky" and prior.num_components == 1  # 2 fitted probes, 8 features
    assert prior.corpus == {"probes": 3, "fitted": 2, "sources": ["x"]}
    feats = model.prior_features(np.array([r.params for r in records[1:]]))
    np.testing.assert_allclose(prior.means[0], feats.mean(axis=0), rtol=1e-6, atol=1e-8)

    # more records: a richer GMM whose means are a weighted split of the features' mean
    rng = np.random.default_rng(0)
    params = np.column_stack([
        rng.uniform(0.5, 2.0, (300, 3)), rng.uniform(5.0, 50.0, (300, 3)), rng.uniform(0.1, 1.4, 300),
        rng.uniform(-3, 3, 300), rng.uniform(2, 6, 300), rng.choice([1000.0, 8000.0], 300)])
    prior = build_prior(model, _records_from_params(params) + [ProbeRecord("bad.exr", "error", "x")],
                        n_components=2)
    assert prior.num_components == 2 and prior.corpus["probes"] == 301 and prior.corpus["fitted"] == 300
    f = model.prior_features(params)
    # an identity of every EM M-step (sum_k r_nk = 1), so it holds wherever EM stopped, to rounding
    np.testing.assert_allclose(prior.weights @ prior.means, f.mean(axis=0), atol=1e-6)
    # the two kappas are the two clusters
    assert sorted(np.round(np.exp(prior.means[:, 2]))) == pytest.approx([1000.0, 8000.0], rel=1e-3)


def test_build_prior_errors():
    from f2l.models.registry import load_model

    sh9 = load_model("sh9", GRID)
    assert sh9.prior_feature_names is None and sh9.prior_features(np.ones((1, sh9.num_params))) is None
    with pytest.raises(ValueError, match="sh9.*prior_features"):
        build_prior(sh9, _records_from_params(np.ones((5, sh9.num_params))))
    with pytest.raises(ValueError, match="no probe could be fitted"):
        build_prior(SunSky(GRID), [ProbeRecord("a.exr", "error", "a.exr: bad")])


# -- 10. the commands ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def runner():
    return CliRunner()


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory, runner):
    """`f2l sky-corpus --n 3`, then `f2l fit-probe` and `f2l build-prior` on it (16 x 32)."""
    tmp = tmp_path_factory.mktemp("cli")
    corpus, out, prior_path = tmp / "skies", tmp / "out", tmp / "p.json"
    runs = {
        "corpus": runner.invoke(app, ["prior", "sky-corpus", "--out", str(corpus), "--n", "3", "--grid", "16x32", "--json"]),
        "fit": runner.invoke(app, ["eval", "fit-probe", str(corpus), "--model", "sunsky", "--grid", "16x32",
                                   "--out", str(out), "--json"]),
        "prior": runner.invoke(app, ["prior", "build", str(corpus), "--model", "sunsky", "--grid", "16x32",
                                     "--out", str(prior_path), "--components", "1", "--json"]),
    }
    return tmp, corpus, out, prior_path, runs


def test_cli_sky_corpus_and_fit_probe(cli_run):
    _, corpus, out, _, runs = cli_run
    res = runs["corpus"]
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout) == {"written": 3, "out": str(corpus)}
    assert len(list(corpus.glob("*.exr"))) == 3 and len(list(corpus.glob("*.json"))) == 3

    res = runs["fit"]
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["total"] == 3 and summary["ok"] == 3 and summary["model"] == "sunsky"
    assert summary["csv"] == str(out / "fit_probe.csv")
    rows = list(csv.DictReader((out / "fit_probe.csv").open()))
    assert len(rows) == 3 and all(r["status"] == "ok" for r in rows)
    assert [r["path"] for r in rows] == [str(p) for p in sorted(corpus.glob("*.exr"))]
    assert set(SunSky(GRID).param_names) <= set(rows[0])


def test_cli_fit_probe_writes_fitted_probes(cli_run):
    _, _, out, _, runs = cli_run
    assert runs["fit"].exit_code == 0
    assert list(out.rglob("*.exr")), sorted(p.name for p in out.iterdir())


def test_cli_build_prior_and_use_the_prior(cli_run, monkeypatch):
    tmp, corpus, _, prior_path, runs = cli_run
    res = runs["prior"]
    assert res.exit_code == 0, res.output
    info = json.loads(res.stdout)
    assert info["fitted"] == 3 and info["skipped"] == 0 and info["components"] == 1
    assert info["out"] == str(prior_path) and info["features"] == sunsky_prior.FEATURE_NAMES
    prior = load_prior(prior_path)
    assert prior.model == "sunsky" and prior.features == sunsky_prior.FEATURE_NAMES
    assert prior.corpus["fitted"] == 3 and prior.corpus["sources"] == [str(corpus)]

    # the model picks the prior up from $F2L_SUNSKY_PRIOR
    monkeypatch.setenv("F2L_SUNSKY_PRIOR", str(prior_path))
    model = SunSky(GRID)
    assert model.prior is not None and np.array_equal(model.prior.means, prior.means)
    starts = model.initial_points()
    assert starts.shape == (4 * prior.num_components, 10) and np.all(np.isfinite(starts))
    lo, hi = model.bounds()
    assert np.all(starts >= lo) and np.all(starts <= hi)
    # the starts' features are the GMM's means (up to the 1e-6 sun-colour epsilon)
    np.testing.assert_allclose(model.prior_features(starts[:1])[0], prior.means[0], atol=1e-4)
    # prior_nll at the starts and at an overcast vector (w_sun = 0): finite, finite gradients
    params = torch.tensor(np.vstack([starts, starts[:1] * [1, 1, 1, 0, 0, 0, 1, 1, 1, 1]]), requires_grad=True)
    nll = model.prior_nll(params)
    assert nll.shape == (len(starts) + 1,) and torch.all(torch.isfinite(nll))
    # the model widens the file's components by a floor (sunsky_prior.FEATURE_MIN_STD)
    # and scores it marginalised over the sun's elevation (sunsky_prior.SCORED_FEATURES)
    widened = prior.widened(sunsky_prior.FEATURE_MIN_STD).marginal(list(sunsky_prior.SCORED_FEATURES))
    np.testing.assert_allclose(model.prior.covariances,
                               prior.covariances + np.diag(np.square(sunsky_prior.FEATURE_MIN_STD))[None])
    expected = widened.nll(model.prior_features(starts[:1])[:, 1:])[0]
    assert float(nll.detach()[0]) == pytest.approx(float(expected), rel=1e-9)
    nll.sum().backward()
    assert torch.all(torch.isfinite(params.grad))
    # and without the variable's file (and no shipped prior file), no prior: the placeholder starts
    monkeypatch.setenv("F2L_SUNSKY_PRIOR", str(tmp / "nothing_here.json"))
    assert SunSky(GRID).prior is None and SunSky(GRID).initial_points().shape == (8, 10)


def test_cli_fit_probe_without_probes_fails(tmp_path, runner):
    (tmp_path / "notes.txt").write_text("no probes here")
    res = runner.invoke(app, ["eval", "fit-probe", str(tmp_path), "--model", "sunsky", "--grid", "16x32", "--json"])
    assert res.exit_code != 0
    assert "no .exr probes found" in res.stderr and str(tmp_path) in res.stderr
    res = runner.invoke(app, ["prior", "build", str(tmp_path), "--model", "sunsky", "--out", str(tmp_path / "p.json")])
    assert res.exit_code != 0 and "no .exr probes found" in res.stderr
    assert not (tmp_path / "p.json").exists()


def test_cli_fit_probe_all_bad_and_unknown_model(tmp_path, runner):
    (tmp_path / "bad.exr").write_bytes(b"garbage")
    res = runner.invoke(app, ["eval", "fit-probe", str(tmp_path), "--model", "sunsky", "--grid", "16x32", "--json"])
    assert res.exit_code == 1
    summary = json.loads(res.stdout)
    assert summary["ok"] == 0 and summary["errors"] == 1
    res = runner.invoke(app, ["prior", "build", str(tmp_path), "--model", "sunsky", "--grid", "16x32",
                              "--out", str(tmp_path / "p.json"), "--json"])
    assert res.exit_code != 0 and "no probe could be fitted" in res.stderr and "bad.exr" in res.stderr
    res = runner.invoke(app, ["eval", "fit-probe", str(tmp_path), "--model", "no-such-model", "--json"])
    assert res.exit_code != 0 and "no-such-model" in res.stderr


def test_fit_report_breaks_the_sky_errors_down_by_kind():
    from f2l.prior.fit_report import kind_table

    def rec(kind, full, sky, ff=None):
        extra = {"metrics": {"Full-dω MAE (l)": full, "Sky-dω MAE (l)": sky}}
        if ff is not None:
            extra["variants"] = {"m_ff": {"metrics": {"Full-dω MAE (l)": ff, "Sky-dω MAE (l)": ff / 2}}}
        return ProbeRecord(f"{kind}-{full}.exr", "ok", kind=kind, extra=extra)

    records = [rec("clear", 0.1, 0.05, ff=0.2), rec("clear", 0.3, 0.15, ff=0.4), rec("overcast", 0.02, 0.01, ff=0.06),
               ProbeRecord("bad.exr", "error", "unreadable", kind="clear"), ProbeRecord("none.exr", "ok", extra={})]
    table = kind_table(records, "m")
    got = {(r["fit"], r["kind"]): (r["n"], r["Full-dω MAE (l)"], r["Sky-dω MAE (l)"]) for r in table["rows"]}
    assert got == {("m", "clear"): (2, pytest.approx(0.2), pytest.approx(0.1)), ("m", "overcast"): (1, 0.02, 0.01),
                   ("m_ff", "clear"): (2, pytest.approx(0.3), pytest.approx(0.15)),
                   ("m_ff", "overcast"): (1, 0.06, 0.03)}
    assert table["lines"][0] == ("| fit | clear (2): Full-dω (Sky-dω) MAE (l) | "
                                 "overcast (1): Full-dω (Sky-dω) MAE (l) |")
    assert table["lines"][2] == "| m | 0.2 (0.1) | 0.02 (0.01) |"
    assert kind_table([ProbeRecord("x.exr", "ok", extra={"metrics": {}})], "m") == {"rows": [], "lines": []}


def test_cli_build_prior_skips_bad_probes_and_reads_every_hdr_format(tmp_path, runner):
    """build-prior lists probes as fit-probe does (EXR, Radiance, PFM; other files named as
    skipped) and fits them with per-probe errors: a bad probe is skipped with its reason, the prior
    is built from the rest (written), exit 4."""
    import OpenImageIO as oiio

    from f2l.io.exr import write_exr

    corpus = tmp_path / "skies"
    good = write_sky_corpus(corpus, 2, seed=0, grid=GRID)
    sky = read_exr(good[0])
    out = oiio.ImageOutput.create(str(corpus / "radiance.hdr"))  # a third good probe, not an EXR
    out.open(str(corpus / "radiance.hdr"), oiio.ImageSpec(sky.shape[1], sky.shape[0], 3, oiio.FLOAT))
    out.write_image(sky)
    out.close()
    write_exr(corpus / "black.exr", np.zeros((16, 32, 3), np.float32))
    (corpus / "bad.pfm").write_bytes(b"PF\n32 16\n-1.0\n" + b"\x00" * 10)  # truncated
    (corpus / "sky_0001.json").write_text('{"kind": "clear", "sun_direction": [0, 0, 0]}')  # malformed side file
    (corpus / "notes.txt").write_text("not a probe")
    prior_path = tmp_path / "p.json"
    res = runner.invoke(app, ["prior", "build", str(corpus), "--model", "sunsky", "--grid", "16x32",
                              "--out", str(prior_path), "--components", "1", "--json"])
    assert res.exit_code == 4, res.output
    assert "Traceback" not in res.output
    info = json.loads(res.stdout)
    assert info["fitted"] == 2 and info["skipped"] == 3 and prior_path.is_file()
    assert load_prior(prior_path).corpus == {"probes": 5, "fitted": 2, "sources": [str(corpus)]}
    for name, why in (("black.exr", "black"), ("bad.pfm", ""), ("sky_0001.json", "sun_direction")):
        assert any(str(corpus / name) in line and why in line for line in res.stderr.splitlines()
                   if line.startswith("f2l: skipped")), (name, res.stderr)
    assert f"{corpus / 'notes.txt'}: skipped: not an HDR image" in res.stderr
