"""Training the sky autoencoder (``f2l ae train``): denoising AE with a solid-angle-weighted L1 loss.

    loss = mean_batch [ sum_{c,h,w} w_h |f(e + n) - e|  +  lambda sum_{c,h,w} w_h (f(e + n) - e)^2 ],
    w_h = dOmega_h / (3 sum_{h,w} dOmega_h),   n ~ N(0, sigma^2), sigma = 0.01

(in the cube-root encoding sigma is 3% of the mean sky): the paper's denoising, solid-angle-
weighted L1, plus (``l2_weight`` lambda = 4; 0 gives the paper's L1 alone) the same weights on
squared errors. Under L1 every texel's gradient is +-w_h whatever its error, so the sun's two
texels get 2 of ~4,000 equal votes: networks trained on L1 alone (4,000 skies, two epochs; or 8
clear skies, 300 steps) reproduced the sky and never the sun (decoded peak ~1 x the mean sky where
the truth is ~750 x, docs/ae.md). The squared term's gradient grows with the error (16 x L1's at
a missing sun) and hardly touches the sky's small residuals (0.4 x L1's at an error of 0.05)
on encoded (cube-root), sun-centred skies (:mod:`f2l_builtin_models.autoencoder.encoding`, :mod:`f2l_builtin_models.autoencoder.data`). Adam, batch 32, the
learning rate on a cosine from ``lr`` to ``lr * lr_final`` over all steps. Seeded: the weights'
initialisation from ``seed``, epoch k's shuffle and noise from (seed, k), so a resumed run
equals an uninterrupted one. A checkpoint (model, optimiser, history) is written atomically
after every epoch to the work folder (default ``<stem>_train/`` beside the weights; it also holds
the encoded-sky caches); a rerun with the same settings and data continues after the last
finished epoch (other settings: an error naming the checkpoint, or ``restart``).

After the last epoch: the weights (``<stem>.npz``, :mod:`f2l_builtin_models.autoencoder.weights`), the latent GMM prior
(:mod:`f2l_builtin_models.autoencoder.prior`), the held-out evaluation and the model card (:mod:`f2l_builtin_models.autoencoder.card`).
"""

from __future__ import annotations

import dataclasses
import io
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from f2l_builtin_models.autoencoder import card as card_mod
from f2l_builtin_models.autoencoder.data import SkyCache, build_cache, holdout_mask, list_sky_files
from f2l_builtin_models.autoencoder.loss import loss_weights, weighted_l1, weighted_l2  # noqa: F401  (re-exported)
from f2l_builtin_models.autoencoder.model import SkyAE
from f2l_builtin_models.autoencoder.prior import encode_skies, fit_latent_prior, prior_path
from f2l_builtin_models.autoencoder.weights import companion, save_weights
from f2l.io.atomic import atomic_path


class TrainError(ValueError):
    """Training cannot start or continue; the message says why (and names the file)."""


@dataclass
class TrainConfig:
    epochs: int = 5
    batch_size: int = 16
    lr: float = 1.5e-3
    lr_final: float = 0.05  # final learning rate as a fraction of lr (cosine)
    noise_sigma: float = 0.01
    l2_weight: float = 4.0  # lambda of the squared-error term (0: the paper's L1 alone)
    seed: int = 0
    holdout_fraction: float = 0.05  # used when no separate held-out folder is given
    gmm_components: int = 8
    threads: int = 2

    def key(self) -> dict:
        """The settings a checkpoint must share to be continued (threads may differ)."""
        d = dataclasses.asdict(self)
        d.pop("threads")
        return d


def _lr(cfg: TrainConfig, step: int, total: int) -> float:
    t = min(step / max(total, 1), 1.0)
    return cfg.lr * (cfg.lr_final + (1.0 - cfg.lr_final) * 0.5 * (1.0 + math.cos(math.pi * t)))


@torch.no_grad()
def evaluate_loss(ae: SkyAE, skies: np.ndarray, index: np.ndarray, batch: int = 64, l2: bool = False):
    """Mean weighted L1 of the noise-free reconstructions of ``skies[index]`` (eval mode), and
    with ``l2`` the mean weighted squared error too (a pair)."""
    if len(index) == 0:
        return (float("nan"), float("nan")) if l2 else float("nan")
    ae.eval()
    w = loss_weights()
    total, total2 = 0.0, 0.0
    for s in range(0, len(index), batch):
        x = torch.from_numpy(np.array(skies[np.sort(index[s : s + batch])]))
        y = ae(x)
        total += float(weighted_l1(y, x, w).sum())
        total2 += float(weighted_l2(y, x, w).sum())
    return (total / len(index), total2 / len(index)) if l2 else total / len(index)


def _save_checkpoint(path: Path, payload: dict) -> None:
    buf = io.BytesIO()
    torch.save(payload, buf)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(buf.getvalue())


def _load_checkpoint(path: Path) -> dict:
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable checkpoint is reported the same way
        raise TrainError(f"{path}: unreadable checkpoint ({type(exc).__name__}: {exc}); delete it or use --restart") from exc


def work_folder(out: str | Path, work_dir: str | Path | None = None) -> Path:
    """The folder of the caches and the checkpoint: ``work_dir`` or ``<stem>_train/`` beside ``out``."""
    return Path(work_dir) if work_dir is not None else companion(out, "_train")


def train_ae(skies_dir: str | Path, out: str | Path, cfg: TrainConfig | None = None,
             heldout_dir: str | Path | None = None, restart: bool = False, progress: bool = True,
             log: Callable[[str], None] | None = None, work_dir: str | Path | None = None) -> dict:
    """Train on the sky probes under ``skies_dir`` and write ``out`` (.npz) and its companions.

    ``heldout_dir``: a separate folder of probes for the held-out error (else a deterministic
    ``holdout_fraction`` of ``skies_dir`` is held out, never trained on). ``work_dir``: caches and
    checkpoint (:func:`work_folder`). Returns the model card.
    """
    cfg = cfg or TrainConfig()
    out = Path(out)
    if out.suffix != ".npz":
        raise TrainError(f"{out}: the weights file must end in .npz")
    out.parent.mkdir(parents=True, exist_ok=True)
    log = log or (lambda msg: None)
    torch.set_num_threads(max(1, min(int(cfg.threads), 2)))
    files = list_sky_files(skies_dir)
    if not files:
        raise TrainError(f"{skies_dir}: no .exr or .hdr sky probes found")
    work = work_folder(out, work_dir)
    cache = _cached(files, work / "cache", "encode skies", progress)
    usable = cache.ok
    if heldout_dir is not None:
        held_files = list_sky_files(heldout_dir)
        if not held_files:
            raise TrainError(f"{heldout_dir}: no .exr or .hdr sky probes found")
        held_cache = _cached(held_files, work / "cache_heldout", "encode held-out", progress)
        train_idx, held_idx = usable, held_cache.ok
    else:
        mask = holdout_mask(cache.files, cfg.holdout_fraction, cfg.seed)
        held_cache = cache
        train_idx, held_idx = usable[~mask[usable]], usable[mask[usable]]
    for msg in cache.errors[:10]:
        log(f"skipped {msg}")
    if len(train_idx) < 2:
        raise TrainError(f"{skies_dir}: only {len(train_idx)} usable training skies (need at least 2)")

    torch.manual_seed(cfg.seed)
    ae = SkyAE()
    opt = torch.optim.Adam(ae.parameters(), lr=cfg.lr)
    history: list[dict] = []
    ckpt_path = work / "checkpoint.ckpt"
    data_key = {"fingerprint": cache.key["fingerprint"], "n_train": int(len(train_idx)),
                "n_heldout": int(len(held_idx))}
    start_epoch = 0
    if ckpt_path.exists() and not restart:
        ck = _load_checkpoint(ckpt_path)
        if ck.get("config") != cfg.key() or ck.get("data") != data_key:
            raise TrainError(f"{ckpt_path}: checkpoint of other settings or data ({ck.get('config')}); "
                             "rerun with the same options, or --restart")
        ae.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        history, start_epoch = list(ck["history"]), int(ck["epoch"])
        log(f"resuming from {ckpt_path} after epoch {start_epoch}")

    weights = loss_weights()
    steps_per_epoch = math.ceil(len(train_idx) / cfg.batch_size)
    total_steps = steps_per_epoch * cfg.epochs
    for epoch in range(start_epoch, cfg.epochs):
        t0 = time.perf_counter()
        ae.train()
        order = np.random.default_rng([cfg.seed, epoch]).permutation(train_idx)
        gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + epoch)
        bar = _bar(steps_per_epoch, f"epoch {epoch + 1}/{cfg.epochs}", progress)
        running, seen = 0.0, 0
        for step in range(steps_per_epoch):
            rows = np.sort(order[step * cfg.batch_size : (step + 1) * cfg.batch_size])
            if len(rows) < 2:  # BatchNorm needs two samples
                continue
            x = torch.from_numpy(np.array(cache.skies[rows]))
            noisy = x + cfg.noise_sigma * torch.randn(x.shape, generator=gen)
            for group in opt.param_groups:
                group["lr"] = _lr(cfg, epoch * steps_per_epoch + step, total_steps)
            opt.zero_grad(set_to_none=True)
            pred = ae(noisy)
            loss = weighted_l1(pred, x, weights).mean()
            if cfg.l2_weight > 0:
                loss = loss + cfg.l2_weight * weighted_l2(pred, x, weights).mean()
            loss.backward()
            opt.step()
            running += float(loss.detach()) * len(rows)
            seen += len(rows)
            bar(1, loss=float(loss.detach()))
        bar(0, close=True)
        held, held2 = evaluate_loss(ae, held_cache.skies, held_idx, l2=True)
        history.append({"epoch": epoch + 1, "train_loss": running / max(seen, 1), "heldout_loss": held,
                        "heldout_l2": held2, "seconds": time.perf_counter() - t0})
        _save_checkpoint(ckpt_path, {"config": cfg.key(), "data": data_key, "epoch": epoch + 1,
                                     "model": ae.state_dict(), "optimizer": opt.state_dict(), "history": history})
        log(f"epoch {epoch + 1}: train {history[-1]['train_loss']:.4f}, held-out L1 {held:.4f}, L2 {held2:.4f}, "
            f"{history[-1]['seconds']:.0f} s")

    ae.eval()
    summary = {"epochs": cfg.epochs, "train_skies": int(len(train_idx)), "heldout_skies": int(len(held_idx)),
               "train_seconds": float(sum(h["seconds"] for h in history))}
    save_weights(out, ae, training={**summary, "config": dataclasses.asdict(cfg)})
    bar = _bar(len(train_idx), "latent prior", progress)
    z = encode_skies(ae, cache.skies, train_idx, progress=bar)
    bar(0, close=True)
    from f2l.estimate.model_prior import save_prior

    prior = fit_latent_prior(z, cfg.gmm_components, cfg.seed, corpus={"source": str(skies_dir), "skies": int(len(z))})
    save_prior(prior, prior_path(out))
    heldout = card_mod.heldout_report(ae, held_cache, held_idx)
    return card_mod.write_card(out, cfg, history, cache, train_idx, held_idx, heldout, prior,
                               skies_dir=skies_dir, heldout_dir=heldout_dir)


def _cached(files: list[Path], folder: Path, desc: str, progress: bool) -> SkyCache:
    bar = _bar(len(files), desc, progress)
    cache = build_cache(files, folder, bar)
    bar(0, close=True)
    return cache


def _bar(total: int, desc: str, enabled: bool):
    """A progress callback ``step(n, close=False, **postfix)`` over tqdm on stderr, or a no-op."""
    if not enabled:
        return lambda n=1, close=False, **kw: None
    from tqdm import tqdm

    bar = tqdm(total=total, desc=desc, unit="sky" if "epoch" not in desc else "batch", leave=True)

    def step(n=1, close=False, **postfix):
        if postfix:
            bar.set_postfix({k: f"{v:.4f}" for k, v in postfix.items()}, refresh=False)
        if n:
            bar.update(n)
        if close:
            bar.close()

    return step
