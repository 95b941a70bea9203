"""Sky-autoencoder corpus, training (tiny: a few dozen skies, one epoch), resume, weights files and the
plugin built from them (f2l_builtin_models.autoencoder.corpus / train / weights, plugins/f2l_builtin_models/ae.py)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from f2l_builtin_models.autoencoder.corpus import random_ae_sky, write_ae_corpus
from f2l_builtin_models.autoencoder.model import SkyAE
from f2l_builtin_models.autoencoder.train import TrainConfig, TrainError, evaluate_loss, loss_weights, train_ae, weighted_l1
from f2l_builtin_models.autoencoder.weights import AEWeightsError, load_weights, save_weights
from f2l.io.exr import read_exr
from f2l.lighting.grid import LatLongGrid

GRID = LatLongGrid(16, 32)
TINY = TrainConfig(epochs=1, batch_size=4, threads=1, gmm_components=2, seed=3)
N_TRAIN, N_HELDOUT = 24, 4


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    out = tmp_path_factory.mktemp("ae_corpus")
    paths = write_ae_corpus(out, N_TRAIN, N_HELDOUT, seed=5, grid=GRID)
    return out, paths


@pytest.fixture(scope="module")
def trained(corpus, tmp_path_factory):
    out, _ = corpus
    weights = tmp_path_factory.mktemp("ae_weights") / "tiny.npz"
    logs: list[str] = []
    card = train_ae(out / "train", weights, TINY, heldout_dir=out / "heldout", progress=False, log=logs.append)
    return weights, card, logs


# -- corpus ----------------------------------------------------------------------------------------------
def test_corpus_layout_side_files_and_kinds(corpus):
    out, paths = corpus
    assert len(paths["train"]) == N_TRAIN and len(paths["heldout"]) == N_HELDOUT
    assert json.loads((out / "corpus.json").read_text())["n_train"] == N_TRAIN
    infos = [json.loads(p.with_suffix(".json").read_text()) for p in paths["train"] + paths["heldout"]]
    kinds = {i["kind"] for i in infos}
    assert kinds == {"clear", "partly", "overcast"}
    for info, path in zip(infos, paths["train"] + paths["heldout"]):
        probe = read_exr(path)
        assert probe.shape == (16, 32, 3) and np.isfinite(probe).all() and probe.min() >= 0
        assert 0.0 <= info["sun_transmittance"] <= 1.0
        if info["kind"] == "overcast":
            assert info["sun_direction"] is None and info["sun_transmittance"] == 0.0
        else:
            assert math.isclose(np.linalg.norm(info["sun_direction"]), 1.0, rel_tol=1e-9)
        if info["kind"] == "clear":
            assert info["sun_transmittance"] == 1.0
    assert {i["split"] for i in infos} == {"train", "heldout"}


def test_corpus_is_deterministic_and_a_cloud_can_hide_the_sun():
    a, ia = random_ae_sky(GRID, np.random.default_rng(11))
    b, ib = random_ae_sky(GRID, np.random.default_rng(11))
    assert np.array_equal(a, b) and ia == ib
    partly = [random_ae_sky(GRID, np.random.default_rng(s))[1] for s in range(60)]
    trans = [i["sun_transmittance"] for i in partly if i["kind"] == "partly"]
    assert trans and min(trans) < 0.5 and max(trans) > 0.5  # clouds occlude the sun partly or fully


# -- training -------------------------------------------------------------------------------------------
def test_tiny_training_reduces_the_loss_and_writes_everything(trained, corpus):
    weights, card, logs = trained
    for suffix in ("_prior.json", "_card.json", "_card.md", "_loss.png"):
        assert weights.with_name(weights.stem + suffix).is_file(), suffix
    assert (weights.parent / (weights.stem + "_train") / "checkpoint.ckpt").is_file()
    hist = card["training"]["history"]
    assert len(hist) == 1 and card["data"]["train_skies"] == N_TRAIN and card["data"]["heldout_skies"] == N_HELDOUT
    assert card["heldout"]["skies"] == N_HELDOUT and np.isfinite(card["heldout"]["l1_encoded"])
    # the trained network reconstructs the held-out skies better than its own initialisation
    from f2l_builtin_models.autoencoder.train import _cached  # the same cache train_ae built

    held = _cached(sorted((corpus[0] / "heldout").glob("*.exr")), weights.parent / (weights.stem + "_train") / "cache_heldout",
                   "", False)
    trained_ae, meta = load_weights(weights)
    # the same float32 weights' loss; the whole float32 forward pass is ~1e-7 from float64's, so any order agrees
    assert math.isclose(evaluate_loss(trained_ae, held.skies, held.ok), hist[0]["heldout_loss"], rel_tol=1e-5)
    torch.manual_seed(TINY.seed)
    initial_ae = SkyAE()
    x = torch.from_numpy(np.asarray(held.skies[held.ok]))
    w = loss_weights()
    with torch.no_grad():  # batch statistics: six Adam steps are too few to settle BatchNorm's running ones
        before = float(weighted_l1(initial_ae.train()(x), x, w).mean())
        after = float(weighted_l1(trained_ae.train()(x), x, w).mean())
    assert after < 0.8 * before, (after, before)
    assert meta["training"]["epochs"] == 1
    assert "## Losses" in weights.with_name(weights.stem + "_card.md").read_text()


def test_rerun_resumes_from_the_checkpoint_and_other_settings_are_refused(trained, corpus):
    weights, card, _ = trained
    logs: list[str] = []
    again = train_ae(corpus[0] / "train", weights, TINY, heldout_dir=corpus[0] / "heldout", progress=False,
                     log=logs.append)
    assert any("resuming" in m and "after epoch 1" in m for m in logs)
    assert not any(m.startswith("epoch") for m in logs)  # nothing retrained
    assert again["training"]["history"] == card["training"]["history"]
    other = TrainConfig(**{**TINY.__dict__, "lr": 1e-4})
    with pytest.raises(TrainError, match=str(weights.parent / (weights.stem + "_train") / "checkpoint.ckpt")):
        train_ae(corpus[0] / "train", weights, other, heldout_dir=corpus[0] / "heldout", progress=False)


def test_interrupted_training_continues_to_the_same_weights(corpus, tmp_path):
    cfg = TrainConfig(epochs=2, batch_size=4, threads=1, gmm_components=1, seed=4)
    train_dir, held = tmp_path / "few", corpus[0] / "heldout"
    train_dir.mkdir()
    for path in corpus[1]["train"][:8]:
        (train_dir / path.name).symlink_to(path)
    whole = tmp_path / "whole.npz"
    train_ae(train_dir, whole, cfg, heldout_dir=held, progress=False)

    class Stop(Exception):
        pass

    def stop_after_first(msg):
        if msg.startswith("epoch 1:"):
            raise Stop

    parts = tmp_path / "parts.npz"
    with pytest.raises(Stop):
        train_ae(train_dir, parts, cfg, heldout_dir=held, progress=False, log=stop_after_first)
    assert not parts.exists() and (tmp_path / "parts_train" / "checkpoint.ckpt").exists()
    logs: list[str] = []
    train_ae(train_dir, parts, cfg, heldout_dir=held, progress=False, log=logs.append)
    assert any("after epoch 1" in m for m in logs) and any(m.startswith("epoch 2:") for m in logs)
    a, _ = load_weights(whole)
    b, _ = load_weights(parts)
    # same process, kernels, threads: resuming replays the arithmetic bit for bit (Adam grows any 1-ulp change to ~lr)
    for (ka, va), (kb, vb) in zip(a.state_dict().items(), b.state_dict().items()):
        assert ka == kb and torch.equal(va, vb), ka


def test_no_skies_is_an_error_naming_the_folder(tmp_path):
    with pytest.raises(TrainError, match=str(tmp_path)):
        train_ae(tmp_path, tmp_path / "w.npz", TINY, progress=False)


# -- weights files ---------------------------------------------------------------------------------------
def test_missing_truncated_and_foreign_weights_name_the_file(trained, tmp_path):
    weights = trained[0]
    missing = tmp_path / "missing.npz"
    with pytest.raises(AEWeightsError, match=str(missing)):
        load_weights(missing)
    truncated = tmp_path / "truncated.npz"
    blob = weights.read_bytes()
    truncated.write_bytes(blob[: len(blob) // 2])
    with pytest.raises(AEWeightsError, match=str(truncated)):
        load_weights(truncated)
    foreign = tmp_path / "foreign.npz"
    np.savez(foreign, weight=np.zeros((3, 3)))
    with pytest.raises(AEWeightsError, match=str(foreign)):
        load_weights(foreign)
    # another architecture: right format, but different layers
    other = tmp_path / "other.npz"
    ae = SkyAE()
    save_weights(other, ae)
    with np.load(other) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(str(arrays["__meta__"]))
    meta["architecture"]["encoder"][0][1] = 32
    arrays["__meta__"] = np.array(json.dumps(meta))
    np.savez(other, **arrays)
    with pytest.raises(AEWeightsError, match=f"{other}.*another architecture"):
        load_weights(other)
    # right metadata, wrong tensors
    meta["architecture"]["encoder"][0][1] = 64
    arrays["__meta__"] = np.array(json.dumps(meta))
    arrays["to_latent.weight"] = np.zeros((5, 5), np.float32)
    np.savez(other, **arrays)
    with pytest.raises(AEWeightsError, match=f"{other}.*wrong shape"):
        load_weights(other)


def test_plugin_from_the_tiny_weights(trained, monkeypatch, tmp_path):
    from f2l_builtin_models.ae import AE

    weights = trained[0]
    model = AE(GRID, weights=weights)
    assert model.num_params == 65 and model.domain == "sky"
    starts = model.initial_points()
    assert starts.shape[1] == 65 and np.isfinite(starts).all()
    p = torch.as_tensor(starts)
    rad = model.radiance(p)
    assert rad.shape == (len(starts), GRID.size, 3)
    assert torch.isfinite(rad).all() and float(rad.min()) >= 0.0
    assert float(rad[:, GRID.sky_rows * GRID.width:].abs().max()) == 0.0  # no ground: the estimator adds it
    assert float(rad[:, : GRID.sky_rows * GRID.width].sum()) > 0
    nll = model.prior_nll(p)
    assert nll.shape == (len(starts),) and torch.isfinite(nll).all()
    # the exposure is exact: z_0 + log 10 multiplies the radiance by 10
    q = p[:1].clone()
    q[0, 0] += math.log(10.0)
    assert torch.allclose(model.radiance(q), 10.0 * rad[:1], rtol=1e-4, atol=1e-6)
    # a truncated weights file named through the environment: the error names it
    bad = tmp_path / "bad.npz"
    bad.write_bytes(weights.read_bytes()[:1000])
    monkeypatch.setenv("F2L_AE_WEIGHTS", str(bad))
    with pytest.raises(AEWeightsError, match=str(bad)):
        AE(GRID)


def test_cli_commands(tmp_path):
    import typer

    from f2l_builtin_models.autoencoder.cli import ae_corpus_cmd, train_ae_cmd

    app = typer.Typer()
    app.command("ae-corpus")(ae_corpus_cmd)
    app.command("train-ae")(train_ae_cmd)
    runner = CliRunner()
    res = runner.invoke(app, ["ae-corpus", "--out", str(tmp_path / "c"), "--n-train", "6", "--n-heldout", "2",
                              "--grid", "16x32", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout) == {"out": str(tmp_path / "c"), "train": 6, "heldout": 2}
    res = runner.invoke(app, ["ae-corpus", "--out", str(tmp_path / "h"), "--n-train", "6", "--n-heldout", "2",
                              "--grid", "16x32", "--split", "heldout", "--json"])
    assert res.exit_code == 0 and json.loads(res.stdout)["train"] == 0 and not (tmp_path / "h" / "train").exists()
    for i in range(2):  # the held-out skies of the full corpus, byte for byte
        name = f"heldout/sky_{i:05d}.exr"
        assert (tmp_path / "h" / name).read_bytes() == (tmp_path / "c" / name).read_bytes()
    res = runner.invoke(app, ["train-ae", str(tmp_path / "c" / "train"), "--out", str(tmp_path / "w.npz"),
                              "--epochs", "1", "--batch-size", "4", "--components", "1", "--threads", "1", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["training"]["epochs"] == 1
    res = runner.invoke(app, ["train-ae", str(tmp_path / "nothing"), "--out", str(tmp_path / "x.npz")])
    assert res.exit_code == 2 and "nothing" in res.output
