"""The lighting-model plugin interface (entry-point group ``f2l.lighting_models``).

A model turns a parameter vector into radiance on a lat-long grid, differentiably (torch).
Everything else — transport, loss, albedo, ground bounce, multi-start, optimisation — lives in
``f2l.estimate``, so a plugin is small. See ``plugins/example_directional`` for a template.

Contract
--------
- ``name``, ``version``, ``description``: identification (shown by ``f2l models``).
- ``domain``: ``"sky"`` — the model describes the upper hemisphere only and the estimator adds the
  Lambertian ground bounce below the horizon (l_gnd = rho_gnd / pi * E_horizontal(sky));
  ``"sphere"`` — the model describes the whole sphere itself (e.g. spherical harmonics).
- ``param_names`` and ``bounds()``: the parameter vector layout and box bounds (``±inf`` allowed).
- ``initial_points()``: starting points (S, P) for the multi-start optimiser (e.g. GMM centroids).
- ``radiance(params)``: torch (B, P) -> (B, L, 3) radiance on the flattened grid (row-major texels),
  non-negative for sky models. For ``domain == "sky"`` only the upper rows are used.
- optional ``prior_nll(params)``: (B,) negative log-likelihood of the parameters (the psi_l term).
- optional ``sun_direction(params)``: (3,) unit direction of the sun, when the model has one.
- optional ``intensity_params``: indices of parameters radiance is linear in (fit-probe fits
  their logarithm); ``probe_starts(probe_flat)``: starts for fitting a probe (None: the
  ``initial_points()``); ``prior_features(params)`` / ``prior_feature_names``: what
  ``f2l prior build`` fits its GMM on (None: the model has no GMM prior).

Capabilities (``f2l.models.capabilities``) are typed mixins a model inherits to get the
estimator's fast paths: ``LinearRadiance`` (linear in its parameters), ``SunAngles`` (the sun's
angles are parameters: capture-time prior), ``CompactSun`` (sky + vMF sun: exact-core transport
and the global sun search), ``LatentSky`` (a decoded latent sky: batched start search). List them
before ``LightingModel`` in the bases. The registry checks them; ``docs/plugins.md`` has examples.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np
import torch

from f2l.lighting.grid import LatLongGrid


class LightingModel(ABC):
    """Base class for lighting models; subclass and register under ``f2l.lighting_models``.

    ``param_names``, ``initial_points`` and ``radiance`` are abstract: a subclass that leaves one
    out cannot be instantiated, and the registry reports it by name with what is missing.
    """

    name: ClassVar[str] = ""
    version: ClassVar[str] = "1"
    description: ClassVar[str] = ""
    domain: ClassVar[str] = "sky"

    def __init__(self, grid: LatLongGrid) -> None:
        self.grid = grid

    # -- layout ------------------------------------------------------------------------------
    @property
    @abstractmethod
    def param_names(self) -> list[str]:
        """Names of the P parameters, in vector order."""

    @property
    def num_params(self) -> int:
        return len(self.param_names)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) bounds, each (P,) float64; default unbounded."""
        p = self.num_params
        return np.full(p, -np.inf), np.full(p, np.inf)

    @abstractmethod
    def initial_points(self) -> np.ndarray:
        """(S, P) starting points of the multi-start optimiser (e.g. prior centroids)."""

    # -- evaluation ------------------------------------------------------------------------------
    @abstractmethod
    def radiance(self, params: torch.Tensor) -> torch.Tensor:
        """(B, P) parameters -> (B, L, 3) radiance on the flattened grid, differentiable."""

    def prior_nll(self, params: torch.Tensor) -> torch.Tensor:
        return torch.zeros(params.shape[0], dtype=params.dtype, device=params.device)

    def sun_direction(self, params: np.ndarray) -> np.ndarray | None:
        return None

    intensity_params: ClassVar[tuple[int, ...]] = ()
    prior_feature_names: ClassVar[list[str] | None] = None

    def prior_features(self, params: np.ndarray) -> np.ndarray | None:
        """(n, P) -> (n, F) features a GMM prior is fitted on (``f2l prior build``); None: no prior."""
        return None

    def probe_starts(self, probe_flat: np.ndarray) -> np.ndarray | None:
        """(S, P) starts for fitting this model to a probe (L, 3); None: ``initial_points()``."""
        return None

    def fit_to_probe(self, probe: np.ndarray, **options):
        """The model's own probe fit (a ``f2l.prior.probe_fit.ProbeFit``), or None: the generic one."""
        return None

    # -- helpers ---------------------------------------------------------------------------------
    def probe(self, params: np.ndarray) -> np.ndarray:
        """Radiance (H, W, 3) float32 for one parameter vector (no ground bounce)."""
        with torch.no_grad():
            rad = self.radiance(torch.as_tensor(np.asarray(params, dtype=np.float64))[None])[0]
        return rad.reshape(self.grid.height, self.grid.width, 3).cpu().numpy().astype(np.float32)
