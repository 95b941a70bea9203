"""Sky-autoencoder weight files: a NumPy ``.npz`` (no pickle) of the state dict plus metadata.

Layout: one array per ``SkyAE.state_dict()`` entry (float32; BatchNorm's batch counters int64)
and ``__meta__``, a JSON string::

    {"format": "f2l-ae-weights/1", "architecture": model.ARCHITECTURE,
     "encoding": {"power": 3.0, "sky_shape": [32, 128]}, "training": {...}}

Loading checks the format, the architecture and every tensor's name and shape, so a missing,
truncated or foreign file (another network, another f2l version's layout) raises
:class:`AEWeightsError` whose message starts with the file's path and says what is wrong.

Companion files next to ``<name>.npz``: ``<name>_prior.json`` (the latent GMM prior, format
``f2l-gmm-prior/1``), ``<name>_card.json`` / ``<name>_card.md`` (the model card) and
``<name>_loss.png`` (the loss curve), written by ``f2l ae train``.
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import torch

from f2l_builtin_models.autoencoder.encoding import POWER
from f2l_builtin_models.autoencoder.model import ARCHITECTURE, SKY_SHAPE, SkyAE
from f2l.io.atomic import atomic_path

FORMAT = "f2l-ae-weights/1"


class AEWeightsError(ValueError):
    """A weights file that cannot be used; the message names the file."""


def companion(weights: str | Path, suffix: str) -> Path:
    """``<stem><suffix>`` next to the weights file (e.g. suffix ``_prior.json``)."""
    p = Path(weights)
    return p.with_name(p.stem + suffix)


def save_weights(path: str | Path, ae: SkyAE, training: dict | None = None) -> Path:
    """Write ``ae``'s state dict and metadata to ``path`` (.npz) atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {k: v.detach().cpu().numpy() for k, v in ae.state_dict().items()}
    meta = {"format": FORMAT, "architecture": ARCHITECTURE,
            "encoding": {"power": POWER, "sky_shape": list(SKY_SHAPE)}, "training": training or {}}
    arrays["__meta__"] = np.array(json.dumps(meta))
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(buf.getvalue())
    return path


def load_weights(path: str | Path) -> tuple[SkyAE, dict]:
    """(SkyAE in eval mode, metadata) from ``path``; AEWeightsError naming the file otherwise."""
    path = Path(path)
    if not path.is_file():
        raise AEWeightsError(f"{path}: weights file not found" if not path.exists() else f"{path}: not a regular file")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: np.array(data[k]) for k in data.files}
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        raise AEWeightsError(f"{path}: not a readable f2l autoencoder weights file (truncated or corrupt?): "
                             f"{type(exc).__name__}: {exc}") from exc
    if "__meta__" not in arrays:
        raise AEWeightsError(f"{path}: no f2l metadata (__meta__): not an f2l autoencoder weights file")
    try:
        meta = json.loads(str(arrays.pop("__meta__")))
    except ValueError as exc:
        raise AEWeightsError(f"{path}: unreadable metadata: {exc}") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        found = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise AEWeightsError(f"{path}: format {found!r}, expected {FORMAT!r}")
    if meta.get("architecture") != ARCHITECTURE:
        raise AEWeightsError(f"{path}: weights of another architecture ({json.dumps(meta.get('architecture'))}); "
                             f"this f2l expects {json.dumps(ARCHITECTURE)}")
    enc = meta.get("encoding", {})
    if enc.get("power") != POWER or list(enc.get("sky_shape", [])) != list(SKY_SHAPE):
        raise AEWeightsError(f"{path}: HDR encoding {enc} differs from this f2l's (power {POWER}, sky {list(SKY_SHAPE)})")
    ae = SkyAE()
    expected = ae.state_dict()
    missing = sorted(set(expected) - set(arrays))
    extra = sorted(set(arrays) - set(expected))
    wrong = sorted(k for k in set(expected) & set(arrays) if tuple(arrays[k].shape) != tuple(expected[k].shape))
    if missing or extra or wrong:
        detail = "; ".join(f"{what}: {', '.join(names[:5])}{' ...' if len(names) > 5 else ''}"
                           for what, names in (("missing", missing), ("unexpected", extra), ("wrong shape", wrong)) if names)
        raise AEWeightsError(f"{path}: tensors do not match the architecture ({detail})")
    state = {k: torch.as_tensor(v).to(expected[k].dtype) for k, v in arrays.items()}
    if not all(torch.isfinite(v).all() for v in state.values() if v.is_floating_point()):
        raise AEWeightsError(f"{path}: holds NaN or infinite weights")
    ae.load_state_dict(state)
    return ae.eval(), meta
