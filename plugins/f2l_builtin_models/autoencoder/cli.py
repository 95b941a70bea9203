"""The sky autoencoder's command group, ``f2l ae corpus`` and ``f2l ae train`` (entry-point group
``f2l.command_groups``, name ``ae``; the names ``ae-corpus`` and ``train-ae`` still work for one release).

Thin: option parsing, progress and exit codes; the work is in ``f2l_builtin_models.autoencoder.corpus`` / ``f2l_builtin_models.autoencoder.train``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional

from typing import Annotated

import typer

JsonOut = Annotated[bool, typer.Option("--json", help="Print one JSON summary on stdout, nothing else (no progress, no table).")]


def _fail(message: str, code: int = 2) -> None:
    typer.echo(f"f2l: error: {message}", err=True)
    raise typer.Exit(code=code)


def ae_corpus_cmd(
    out: Path = typer.Option(..., "--out", help="Output folder: train/ and heldout/ sky EXRs (+ JSON side files) and corpus.json."),
    n_train: int = typer.Option(4000, "--n-train", help="Training skies."),
    n_heldout: int = typer.Option(150, "--n-heldout", help="Held-out skies (never trained on)."),
    seed: int = typer.Option(0, help="Seed (the corpus is deterministic from it)."),
    grid: str = typer.Option("128x256", help="Probe grid HxW (full sphere)."),
    split: list[str] = typer.Option(["train", "heldout"], "--split",
                                    help="Write only these splits (repeatable): 'heldout' alone gives the "
                                         "held-out skies of the same full corpus, for evaluation."),
    json_out: JsonOut = False,
) -> None:
    """Write the autoencoder's sky corpus: Preetham clear skies (all sun elevations and turbidities),
    partly cloudy and overcast skies with procedural clouds (docs/ae.md)."""
    from f2l_builtin_models.autoencoder.corpus import write_ae_corpus
    from f2l.lighting.grid import LatLongGrid

    try:
        h, w = (int(v) for v in grid.lower().split("x"))
        g = LatLongGrid(h, w)
    except Exception as exc:  # noqa: BLE001
        raise typer.BadParameter(f"--grid must look like 128x256: {exc}") from exc
    if n_train < 0 or n_heldout < 0:
        raise typer.BadParameter("counts must be >= 0")
    bar = None
    if not json_out:
        from tqdm import tqdm

        total = (n_train if "train" in split else 0) + (n_heldout if "heldout" in split else 0)
        bar = tqdm(total=total, desc="ae-corpus", unit="sky", file=sys.stderr)
    try:
        paths = write_ae_corpus(out, n_train, n_heldout, seed=seed, grid=g, progress=None if bar is None else bar.update,
                                splits=tuple(dict.fromkeys(split)))
    except ValueError as exc:
        _fail(str(exc))
    finally:
        if bar is not None:
            bar.close()
    typer.echo(json.dumps({"out": str(out), "train": len(paths["train"]), "heldout": len(paths["heldout"])}))


def train_ae_cmd(
    skies_dir: Path = typer.Argument(..., help="Folder of HDR sky probes (lat-long .exr/.hdr, full sphere or sky hemisphere)."),
    out: Path = typer.Option(..., "--out", help="Weights file to write (.npz); the prior, model card and loss curve go beside it."),
    heldout: Optional[Path] = typer.Option(None, "--heldout", help="Separate folder of held-out probes (default: a 5% hash split of SKIES_DIR)."),
    epochs: int = typer.Option(5, help="Epochs."),
    batch_size: int = typer.Option(16, help="Batch size."),
    lr: float = typer.Option(1.5e-3, help="Adam learning rate (cosine decay to 5%)."),
    noise: float = typer.Option(0.01, help="Denoising: Gaussian noise sigma added to the encoded input."),
    l2_weight: float = typer.Option(4.0, "--l2-weight", help="Weight of the solid-angle-weighted squared-error term added to the L1 loss (0: L1 alone, as in the paper; docs/ae.md)."),
    seed: int = typer.Option(0, help="Seed (initialisation, shuffles, noise)."),
    components: int = typer.Option(8, help="Components of the latent GMM prior."),
    threads: int = typer.Option(2, help="Torch threads (at most 2 on the project's machines)."),
    work_dir: Optional[Path] = typer.Option(None, "--work-dir", help="Caches of the encoded skies and the checkpoint (default: <stem>_train/ beside --out)."),
    restart: bool = typer.Option(False, "--restart", help="Ignore an existing checkpoint and train from scratch."),
    json_out: JsonOut = False,
) -> None:
    """Train the sky autoencoder (resumable: rerun continues after the last finished epoch), then fit
    its latent GMM prior and write weights, prior, model card and loss curve."""
    from f2l_builtin_models.autoencoder.train import TrainConfig, TrainError, train_ae
    from f2l_builtin_models.autoencoder.weights import companion

    if not skies_dir.exists():
        _fail(f"{skies_dir}: no such folder")
    cfg = TrainConfig(epochs=epochs, batch_size=batch_size, lr=lr, noise_sigma=noise, l2_weight=l2_weight, seed=seed,
                      gmm_components=components, threads=threads)
    log = (lambda msg: None) if json_out else (lambda msg: typer.echo(msg, err=True))
    try:
        card = train_ae(skies_dir, out, cfg, heldout_dir=heldout, restart=restart, progress=not json_out, log=log,
                        work_dir=work_dir)
    except (TrainError, ValueError) as exc:
        _fail(str(exc))
    if json_out:
        typer.echo(json.dumps(card))
    else:
        typer.echo(companion(out, "_card.md").read_text())
        typer.echo(f"wrote {out}, {companion(out, '_prior.json')}, {companion(out, '_card.json')}, "
                   f"{companion(out, '_card.md')}, {companion(out, '_loss.png')}")


app = typer.Typer(help="The sky autoencoder: its sky corpus and its training (docs/ae.md).", no_args_is_help=True,
                  add_completion=False)
app.command("corpus")(ae_corpus_cmd)
app.command("train")(train_ae_cmd)
