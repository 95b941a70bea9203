"""GMM priors over lighting-model parameters, built from probes fitted with ``fit_probe``.

A model that supports a prior maps its parameter vectors to a *feature* vector (its
``prior_features(params)``, numpy (n, P) -> (n, D), and the torch twin
``prior_features_torch``), e.g. for a sun-plus-sky model: sun elevation, turbidity, log κ, the sun-to-sky
intensity ratio and colours; never the azimuth (the camera's heading is arbitrary) nor the
absolute exposure. A Gaussian mixture (scikit-learn, full covariances) over those features of a
corpus of fitted probes is the prior: ψ_l(θ) = −log Σ_k π_k N(f(θ); μ_k, Σ_k), and its means give
the multi-start centroids (``model.params_from_features``).

Stored as JSON: ``{"format": "f2l-gmm-prior/1", "model", "features", "weights", "means",
"covariances", "corpus": {...provenance...}}``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from f2l.io.atomic import write_text_atomic

__all__ = ["GmmPrior", "fit_gmm", "load_prior", "save_prior"]

FORMAT = "f2l-gmm-prior/1"


class GmmPrior:
    """A Gaussian mixture over D features with its negative log-likelihood in numpy and torch."""

    def __init__(self, weights, means, covariances, features: list[str], model: str = "",
                 corpus: dict | None = None) -> None:
        self.weights = np.asarray(weights, dtype=np.float64)
        self.means = np.asarray(means, dtype=np.float64)
        self.covariances = np.asarray(covariances, dtype=np.float64)
        k, d = self.means.shape
        if self.weights.shape != (k,) or self.covariances.shape != (k, d, d) or len(features) != d:
            raise ValueError("inconsistent GMM shapes")
        self.features = list(features)
        self.model = model
        self.corpus = dict(corpus or {})
        self.precisions = np.linalg.inv(self.covariances)
        _, logdet = np.linalg.slogdet(self.covariances)
        self.log_norm = np.log(self.weights) - 0.5 * (d * math.log(2 * math.pi) + logdet)
        self._torch: dict = {}

    @property
    def num_components(self) -> int:
        return len(self.weights)

    def nll(self, features: np.ndarray) -> np.ndarray:
        """(n, D) -> (n,) negative log-likelihood."""
        d = np.asarray(features, dtype=np.float64)[:, None, :] - self.means[None]  # (n, K, D)
        maha = np.einsum("nki,kij,nkj->nk", d, self.precisions, d)
        logp = self.log_norm[None] - 0.5 * maha
        m = logp.max(axis=1, keepdims=True)
        return -(m[:, 0] + np.log(np.exp(logp - m).sum(axis=1)))

    def nll_torch(self, features: torch.Tensor) -> torch.Tensor:
        """(B, D) -> (B,) negative log-likelihood, differentiable."""
        key = (features.dtype, features.device)
        if key not in self._torch:
            # whitening: precision_k = L_k L_k^T, maha_k = |f L_k - mu_k L_k|^2 -- one matmul for all
            # components (a few ops: this runs in every evaluation of the estimator's objective)
            chol = np.linalg.cholesky(self.precisions)  # (K, D, D)
            k, d = self.means.shape
            whiten = chol.transpose(1, 0, 2).reshape(d, k * d)
            shift = np.einsum("ki,kij->kj", self.means, chol).reshape(-1)
            self._torch[key] = tuple(torch.as_tensor(a, dtype=features.dtype, device=features.device)
                                     for a in (whiten, shift, self.log_norm))
        whiten, shift, log_norm = self._torch[key]
        z = (features @ whiten - shift).reshape(features.shape[0], len(log_norm), -1)
        maha = (z * z).sum(-1)
        return -torch.logsumexp(log_norm[None] - 0.5 * maha, dim=1)

    def marginal(self, features: list[str]) -> "GmmPrior":
        """The mixture's marginal over ``features`` (names of this prior's, in the order given): each
        component's mean and covariance restricted to them, its weight unchanged. Exact: the
        marginal of a Gaussian mixture is the mixture of its components' marginals."""
        index = [self.features.index(name) for name in features]
        return GmmPrior(self.weights, self.means[:, index], self.covariances[:, index][:, :, index], list(features),
                        model=self.model, corpus=self.corpus)

    def widened(self, min_std: np.ndarray) -> "GmmPrior":
        """A copy with each component's covariance + diag(min_std^2): a corpus that is narrower
        than the world (e.g. synthetic skies) must not make the prior overrule the data."""
        floor = np.diag(np.asarray(min_std, dtype=np.float64) ** 2)
        return GmmPrior(self.weights, self.means, self.covariances + floor[None], self.features,
                        model=self.model, corpus=self.corpus)

    def to_json(self) -> dict:
        return {"format": FORMAT, "model": self.model, "features": self.features,
                "weights": self.weights.tolist(), "means": self.means.tolist(),
                "covariances": self.covariances.tolist(), "corpus": self.corpus}


def fit_gmm(features: np.ndarray, names: list[str], n_components: int = 6, seed: int = 0,
            model: str = "", corpus: dict | None = None, reg_covar: float = 1e-4) -> GmmPrior:
    """Fit a full-covariance GMM (scikit-learn EM, k-means init, 5 restarts) to (n, D) features."""
    from sklearn.mixture import GaussianMixture

    x = np.asarray(features, dtype=np.float64)
    x = x[np.isfinite(x).all(axis=1)]
    k = max(1, min(int(n_components), len(x) // max(2 * x.shape[1], 1)))
    if len(x) < 2:
        raise ValueError(f"need at least 2 finite feature vectors to fit a prior, got {len(x)}")
    gmm = GaussianMixture(n_components=k, covariance_type="full", reg_covar=reg_covar,
                          n_init=5, random_state=int(seed)).fit(x)
    return GmmPrior(gmm.weights_, gmm.means_, gmm.covariances_, names, model=model, corpus=corpus)


def save_prior(prior: GmmPrior, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps(prior.to_json(), indent=1) + "\n")
    return path


def load_prior(path: str | Path) -> GmmPrior:
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read the prior: {exc}") from exc
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        found = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise ValueError(f"{path}: not an f2l GMM prior (format {found!r})")
    try:
        return GmmPrior(data["weights"], data["means"], data["covariances"], data["features"],
                        model=data.get("model", ""), corpus=data.get("corpus"))
    except (KeyError, TypeError, ValueError, np.linalg.LinAlgError) as exc:
        raise ValueError(f"{path}: malformed GMM prior: {exc!r}") from exc
