"""The latent GMM prior of the sky autoencoder (paper §3.4): a Gaussian mixture over z_shape.

The encoder's 63 learned coordinates z_shape of the training skies (eval mode, no input noise)
get a full-covariance GMM (scikit-learn, via :func:`f2l.estimate.model_prior.fit_gmm`); the
exposure z_0 and the sun's azimuth are left out (a photo's exposure and the camera's heading
are arbitrary). psi_l(theta) = -log sum_k pi_k N(z_shape; mu_k, Sigma_k), and the component
means are the multi-start centroids. Stored as ``<weights stem>_prior.json`` (f2l-gmm-prior/1).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import torch

from f2l_builtin_models.autoencoder.model import SHAPE_DIM, SkyAE
from f2l.estimate.model_prior import GmmPrior, fit_gmm

FEATURE_NAMES = [f"z{i:02d}" for i in range(1, SHAPE_DIM + 1)]
DEFAULT_COMPONENTS = 8


@torch.no_grad()
def encode_skies(ae: SkyAE, skies: np.ndarray, index: np.ndarray, batch: int = 64,
                 progress: Callable | None = None) -> np.ndarray:
    """(len(index), 63) z_shape of the encoded skies ``skies[index]`` (eval mode, no noise)."""
    ae.eval()
    out = np.zeros((len(index), SHAPE_DIM), dtype=np.float64)
    for s in range(0, len(index), batch):
        rows = index[s : s + batch]
        out[s : s + len(rows)] = ae.encode(torch.from_numpy(np.asarray(skies[np.sort(rows)]))).numpy()[np.argsort(np.argsort(rows))]
        if progress:
            progress(len(rows))
    return out


def fit_latent_prior(z_shape: np.ndarray, components: int = DEFAULT_COMPONENTS, seed: int = 0,
                     corpus: dict | None = None) -> GmmPrior:
    """Full-covariance GMM over (n, 63) latent codes (reg_covar 1e-3 of the codes' mean variance)."""
    z = np.asarray(z_shape, dtype=np.float64)
    reg = 1e-3 * float(np.mean(np.var(z, axis=0))) if len(z) > 1 else 1e-3
    return fit_gmm(z, FEATURE_NAMES, n_components=components, seed=seed, model="ae", corpus=corpus,
                   reg_covar=max(reg, 1e-6))


def prior_path(weights: str | Path) -> Path:
    p = Path(weights)
    return p.with_name(p.stem + "_prior.json")
