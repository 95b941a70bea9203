"""The autoencoder's model card (JSON + Markdown), its loss curve (PNG) and held-out evaluation.

Held-out error: the weighted L1 of the training loss (encoded sky, noise-free input), and the
lighting metrics of ``f2l.metrics.lighting`` (probes normalised to unit upper energy; Full/Sky/
Sun-dω MAE, Sun-ang from each probe's brightest region, sun metrics on the skies the overcast
heuristic calls sunny) between each held-out sky and its feed-forward reconstruction
decode(encode(sky)) with the sky's own exposure, on the sun-centred 32 x 128 sky.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import platform
from pathlib import Path

import numpy as np
import torch

from f2l_builtin_models.autoencoder.encoding import decode_numpy, sky_grid
from f2l_builtin_models.autoencoder.model import ARCHITECTURE, SkyAE
from f2l_builtin_models.autoencoder.weights import companion
from f2l.io.atomic import write_text_atomic

ENCODING_NOTE = ("e = (l / s)^(1/3), s = the sky's mean Rec.709 luminance (z_0 = log s); sun-centred, "
                 "area-resampled 32 x 128 sky hemisphere")


@torch.no_grad()
def heldout_report(ae, cache, index: np.ndarray, batch: int = 64) -> dict:
    """Held-out errors of the feed-forward reconstructions (module docstring)."""
    from f2l_builtin_models.autoencoder.loss import loss_weights, weighted_l1
    from f2l.metrics.lighting import PROBE_METRIC_NAMES, is_overcast, probe_metrics

    if len(index) == 0:
        return {"skies": 0}
    ae.eval()
    grid = sky_grid()
    w = loss_weights()
    l1, rows = [], []
    index = np.sort(index)
    log_s = cache.log_exposure
    for s in range(0, len(index), batch):
        idx = index[s : s + batch]
        x = torch.from_numpy(np.asarray(cache.skies[idx]))
        y = ae(x)
        l1.extend(weighted_l1(y, x, w).tolist())
        for j, i in enumerate(idx):
            gt = np.zeros((grid.height, grid.width, 3))
            est = np.zeros_like(gt)
            gt[: grid.sky_rows] = decode_numpy(x[j].numpy(), log_s[i])
            est[: grid.sky_rows] = decode_numpy(y[j].numpy(), log_s[i])
            rows.append(probe_metrics(est, gt, grid, overcast=is_overcast(gt, grid)))
    out = {"skies": int(len(index)), "l1_encoded": float(np.mean(l1))}
    for name in PROBE_METRIC_NAMES:
        vals = np.array([r[name] for r in rows], dtype=np.float64)
        vals = vals[np.isfinite(vals)]
        out[name] = {"mean": float(vals.mean()) if vals.size else None,
                     "median": float(np.median(vals)) if vals.size else None, "n": int(vals.size)}
    return out


def _corpus_recipe(skies_dir) -> dict | None:
    """The ``corpus.json`` of an ``f2l ae corpus`` folder (the folder or its parent), if any."""
    for d in (Path(skies_dir), Path(skies_dir).parent):
        f = d / "corpus.json"
        if f.is_file():
            try:
                return json.loads(f.read_text())
            except ValueError:
                return None
    return None


def write_card(out: Path, cfg, history: list[dict], cache, train_idx, held_idx, heldout: dict, prior,
               skies_dir, heldout_dir) -> dict:
    """Write ``<stem>_card.json``, ``<stem>_card.md`` and ``<stem>_loss.png``; returns the card."""
    out = Path(out)
    blob = out.read_bytes()
    card = {
        "model": "ae",
        "weights": {"file": out.name, "sha256": hashlib.sha256(blob).hexdigest(), "bytes": len(blob),
                    "parameters": int(sum(p.numel() for p in SkyAE().parameters()))},
        "architecture": ARCHITECTURE,
        "encoding": ENCODING_NOTE,
        "data": {
            "source": str(skies_dir), "files": len(cache.files), "usable": int(len(cache.ok)),
            "errors": cache.errors[:20], "train_skies": int(len(train_idx)), "heldout_skies": int(len(held_idx)),
            "heldout_source": str(heldout_dir) if heldout_dir is not None
            else f"{cfg.holdout_fraction:.0%} of the source by file-name hash (never trained on)",
            "corpus_recipe": _corpus_recipe(skies_dir),
        },
        "training": {**dataclasses.asdict(cfg), "loss": "solid-angle-weighted L1 + l2_weight x solid-angle-weighted squared error, on the encoded sky",
                     "optimizer": "Adam, cosine learning rate", "history": history,
                     "train_seconds": float(sum(h["seconds"] for h in history)),
                     "torch": torch.__version__, "machine": f"{platform.machine()}, {torch.get_num_threads()} torch threads"},
        "heldout": heldout,
        "prior": {"file": companion(out, "_prior.json").name, "components": prior.num_components,
                  "features": len(prior.features), "fitted_on": prior.corpus.get("skies")},
    }
    write_text_atomic(companion(out, "_card.json"), json.dumps(card, indent=1) + "\n")
    write_text_atomic(companion(out, "_card.md"), card_markdown(card))
    plot_losses(history, companion(out, "_loss.png"))
    return card


def card_markdown(card: dict) -> str:
    t, d, h = card["training"], card["data"], card["heldout"]
    fmt = lambda v: "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.4g}"  # noqa: E731
    lines = [
        f"# Model card: f2l sky autoencoder (`{card['weights']['file']}`)", "",
        f"- weights: {card['weights']['bytes'] / 1e6:.2f} MB, {card['weights']['parameters']:,} parameters, "
        f"sha256 `{card['weights']['sha256'][:16]}…`",
        "- architecture: conv 64 (5×5) → 96 → 96 → 64 (3×3), each BN + ReLU + max-pool 2, FC → z_shape ∈ ℝ⁶³ "
        "(+ z₀ = log exposure: z ∈ ℝ⁶⁴), mirrored decoder (nearest upsampling), 1×1 conv → 3 channels",
        f"- HDR encoding: {card['encoding']}",
        f"- data: {d['train_skies']} training skies from `{d['source']}` ({d['files']} files, {d['usable']} usable); "
        f"held out: {d['heldout_skies']} ({d['heldout_source']})",
    ]
    if d.get("corpus_recipe"):
        lines.append(f"- corpus recipe: `{json.dumps(d['corpus_recipe'])}`")
    lines += [
        f"- training: {t['epochs']} epochs, batch {t['batch_size']}, Adam lr {t['lr']:g} (cosine to ×{t['lr_final']:g}), "
        f"input noise σ = {t['noise_sigma']:g}, loss L1 + {t['l2_weight']:g} × L2, seed {t['seed']}, {t['train_seconds'] / 60:.1f} min ({t['machine']}, torch {t['torch']})",
        f"- prior: {card['prior']['components']}-component GMM over z_shape, fitted on {card['prior']['fitted_on']} training skies",
        "", "## Losses (solid-angle-weighted, on the encoded sky)", "",
        "| epoch | train (L1 + λ L2, noisy input) | held-out L1 | held-out L2 | seconds |", "|---|---|---|---|---|",
    ]
    lines += [f"| {r['epoch']} | {fmt(r['train_loss'])} | {fmt(r['heldout_loss'])} | {fmt(r.get('heldout_l2'))} | "
              f"{r['seconds']:.0f} |" for r in t["history"]]
    lines += ["", f"## Held-out error of decode(encode(sky)) ({h.get('skies', 0)} skies)", ""]
    if h.get("skies"):
        lines += ["| metric | mean | median | n |", "|---|---|---|---|",
                  f"| L1 (encoded sky) | {fmt(h['l1_encoded'])} | | {h['skies']} |"]
        for name, v in h.items():
            if isinstance(v, dict):
                lines.append(f"| {name} | {fmt(v['mean'])} | {fmt(v['median'])} | {v['n']} |")
    return "\n".join(lines) + "\n"


def plot_losses(history: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    ep = [r["epoch"] for r in history]
    ax.plot(ep, [r["train_loss"] for r in history], "o-", label="train: L1 + λ L2 (noisy input)")
    ax.plot(ep, [r["heldout_loss"] for r in history], "s-", label="held-out L1")
    ax.plot(ep, [r.get("heldout_l2", float("nan")) for r in history], "^-", label="held-out L2")
    ax.set_xlabel("epoch")
    ax.set_ylabel("solid-angle-weighted loss")
    ax.set_yscale("log")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    tmp.replace(path)
