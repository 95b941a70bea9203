"""Sky autoencoder lighting model (Calian et al. 2018, §3.3.3): l = R(phi_sun) f_AE(z).

Parameters, in order (65):

    z00_log_exposure     z_0 = log s, the sky's mean luminance (exact, not learned; unbounded)
    z01 ... z63          z_shape, the encoder's learned code (unbounded)
    sun_azimuth_rad      phi_sun: the decoded sky (sun at azimuth 0) is turned so that its sun is
                         at this grid azimuth (0 = -Z, the camera's view; +pi/2 = +X); 2 pi-periodic

Radiance: f_AE(z) = e^{z_0} max(D(z_shape), 0)^3, D the trained decoder (float32, on the
32 x 128 sky hemisphere, ``f2l_builtin_models.autoencoder``), R(phi) a circular column shift, linear between whole
columns (``f2l_builtin_models.autoencoder.encoding.rotate_columns``), then area-resampled to the grid's sky rows when the
grid is not 64 x 128; the rows below the horizon are 0 (domain "sky": the estimator adds the
ground bounce). Computed in float32, returned in the parameters' dtype.

Weights: ``$F2L_AE_WEIGHTS`` or the shipped ``data/ae_sky.npz`` (rebuilt by ``make ae-weights``,
docs/ae.md), with the latent GMM prior ``<stem>_prior.json`` beside it. A missing, truncated or
foreign weights file raises ``f2l_builtin_models.autoencoder.weights.AEWeightsError`` naming the file when the model is
created. The model declares the ``latent-sky`` capability (``f2l.models.capabilities``), so face
estimates go through the generic ``f2l.estimate.latent`` (an azimuth x code search through the
block transport, then all starts batched through the decoder); probe fits
through ``f2l_builtin_models.autoencoder.probe_fit`` (``fit_to_probe``: the feed-forward code ``ae_ff`` and its
optimisation ``ae``).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch

from f2l.lighting.grid import LatLongGrid
from f2l.models.base import LightingModel
from f2l.models.capabilities import LatentLayout, LatentSky, single_thread

DEFAULT_WEIGHTS = Path(__file__).parent / "data" / "ae_sky.npz"
WEIGHTS_ENV = "F2L_AE_WEIGHTS"
START_AZIMUTHS_RAD = (-0.75 * math.pi, -0.25 * math.pi, 0.25 * math.pi, 0.75 * math.pi)
MAX_PRIOR_COMPONENTS = 8
LADDER_ELEVATIONS_DEG = tuple(1.5 + 3.0 * i for i in range(30))
LADDER_TURBIDITIES = (2.5, 6.0)
_LADDER_CACHE: dict[tuple, np.ndarray] = {}
_LOADED: dict = {}


def weights_path() -> Path:
    """The weights file in use: ``$F2L_AE_WEIGHTS`` or the shipped default."""
    return Path(os.environ.get(WEIGHTS_ENV) or DEFAULT_WEIGHTS)


def load_network(path: Path) -> dict:
    """{"ae", "decoder", "meta", "prior"} for ``path``, cached per (path, size, mtime)."""
    from f2l_builtin_models.autoencoder.model import FastDecoder
    from f2l_builtin_models.autoencoder.prior import prior_path
    from f2l_builtin_models.autoencoder.weights import AEWeightsError, load_weights
    from f2l.estimate.model_prior import load_prior

    path = Path(path)
    try:
        st = path.stat()
        key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    except OSError:
        key = (str(path), None, None)
    if key not in _LOADED:
        ae, meta = load_weights(path)
        prior_file = prior_path(path)
        try:
            prior = load_prior(prior_file) if prior_file.exists() else None
        except ValueError as exc:
            raise AEWeightsError(str(exc)) from exc
        _LOADED[key] = {"ae": ae, "decoder": FastDecoder(ae), "meta": meta, "prior": prior, "path": path}
    return _LOADED[key]


class AE(LatentSky, LightingModel):
    """The sky autoencoder model (module docstring); capability ``latent-sky``."""

    name = "ae"
    version = "1"
    description = "Sky autoencoder: R(phi_sun) f_AE(z), z = (log exposure, 63 learned), 65 parameters"
    domain = "sky"

    def __init__(self, grid: LatLongGrid, weights: str | Path | None = None) -> None:
        super().__init__(grid)
        from f2l_builtin_models.autoencoder.encoding import grid_resampler

        self.weights_file = Path(weights) if weights is not None else weights_path()
        net = load_network(self.weights_file)
        self.network, self.decoder, self.prior = net["ae"], net["decoder"], net["prior"]
        res = grid_resampler(grid)
        self._resample = None if res is None else tuple(torch.as_tensor(m, dtype=torch.float32) for m in res)
        self._ladder: np.ndarray | None = None

    # -- layout ------------------------------------------------------------------------------------
    @property
    def param_names(self) -> list[str]:
        return ["z00_log_exposure"] + [f"z{i:02d}" for i in range(1, 64)] + ["sun_azimuth_rad"]

    exposure_index = 0
    shape_slice = slice(1, 64)
    azimuth_index = 64
    latent_layout = LatentLayout(exposure=0, code=slice(1, 64), azimuth=64)

    @property
    def prior_feature_names(self) -> list[str]:
        from f2l_builtin_models.autoencoder.prior import FEATURE_NAMES

        return FEATURE_NAMES

    def prior_features(self, params: np.ndarray) -> np.ndarray:
        """(n, 65) -> (n, 63) z_shape (``f2l prior build --model ae`` fits the GMM on these)."""
        return np.atleast_2d(np.asarray(params, dtype=np.float64))[:, self.shape_slice]

    def prior_nll(self, params: torch.Tensor) -> torch.Tensor:
        """(B, 65) -> (B,) GMM negative log-likelihood of z_shape (0 without a prior)."""
        return self.prior_nll_shape(params[:, self.shape_slice])

    def code_prior_nll(self, codes: torch.Tensor) -> torch.Tensor:
        """``latent-sky``: the GMM NLL of the codes (z_shape)."""
        return self.prior_nll_shape(codes)

    def prior_nll_shape(self, z_shape: torch.Tensor) -> torch.Tensor:
        """(B, 63) -> (B,) GMM negative log-likelihood (0 without a prior)."""
        if self.prior is None:
            return torch.zeros(z_shape.shape[0], dtype=z_shape.dtype)
        return self.prior.nll_torch(z_shape)

    def centroids(self, k: int = MAX_PRIOR_COMPONENTS) -> np.ndarray:
        """(K, 63) z_shape of the heaviest GMM components (the zero code without a prior)."""
        if self.prior is None:
            return np.zeros((1, 63))
        order = np.argsort(-self.prior.weights)[:k]
        return np.array(self.prior.means[order])

    def search_codes(self, k: int = MAX_PRIOR_COMPONENTS, spread: float = 1.5) -> np.ndarray:
        """(3K + L, 63) start codes of the face estimator's search: each of the K heaviest GMM
        components' mean and the two points ``spread`` standard deviations along its first
        principal axis (on the shipped prior, the components are bands of sun elevation ~15 deg
        apart and the axis moves the sun within a band), then the :meth:`ladder_codes`."""
        out = []
        if self.prior is not None:
            for j in np.argsort(-self.prior.weights)[:k]:
                w, v = np.linalg.eigh(self.prior.covariances[j])
                axis = math.sqrt(max(float(w[-1]), 0.0)) * v[:, -1]
                mean = self.prior.means[j]
                out += [mean, mean - spread * axis, mean + spread * axis]
        return np.concatenate([np.asarray(out).reshape(-1, 63), self.ladder_codes()])

    @property
    def cache_key(self) -> tuple:
        """``latent-sky``: decoded search skies are cached per weights file (:attr:`weights_key`)."""
        return self.weights_key

    @property
    def weights_key(self) -> tuple:
        """(resolved path, size, mtime) of the weights file: what per-process caches of derived
        data (search codes, their decoded skies) are keyed by."""
        stat = self.weights_file.stat()
        return str(self.weights_file.resolve()), stat.st_size, stat.st_mtime_ns

    def ladder_codes(self) -> np.ndarray:
        """(L, 63) encoder codes of cloudless corpus skies with the sun every 3 deg of elevation
        (1.5 ... 88.5 deg) at turbidities 2.5 and 6, cached. The latent space moves a sun's
        elevation only in jumps (L-BFGS from a GMM band keeps it within ~10-30 deg of where it
        started), so the search offers every elevation; generated, not stored: ~1 s once."""
        if self._ladder is None:
            key = self.weights_key
            if key not in _LADDER_CACHE:  # per weights file and process: models are made per grid / record
                from f2l_builtin_models.autoencoder.corpus import clear_sky_probe

                grid = LatLongGrid(64, 128)  # sky rows at the network's 32 x 128
                probes = [clear_sky_probe(grid, math.radians(e), 0.0, t) for e in LADDER_ELEVATIONS_DEG
                          for t in LADDER_TURBIDITIES]
                # one intra-op thread: float32 convolutions round differently with 1 or 2 threads,
                # and the codes must not depend on whoever set torch's thread count before
                with single_thread():
                    _LADDER_CACHE[key] = np.stack([self.encode_probe(p)[1:64] for p in probes])
            self._ladder = _LADDER_CACHE[key]
        return self._ladder

    def initial_points(self) -> np.ndarray:
        """(K x 4, 65): each GMM centroid at 4 azimuths (+-45, +-135 deg), unit exposure."""
        starts = [[0.0, *z, az] for z in self.centroids() for az in START_AZIMUTHS_RAD]
        return np.asarray(starts, dtype=np.float64)

    # -- evaluation ----------------------------------------------------------------------------------
    def sky(self, params: torch.Tensor) -> torch.Tensor:
        """(B, 65) -> (B, 3, rows, W) float32 sky on the grid's sky rows (channel-first)."""
        from f2l_builtin_models.autoencoder.encoding import decode_torch, rotate_columns

        p = params.to(torch.float32)
        sky = decode_torch(self.decoder(p[:, self.shape_slice]), p[:, self.exposure_index])
        return self.to_grid(rotate_columns(sky, p[:, self.azimuth_index]))

    def decode_sky(self, codes: torch.Tensor, azimuth: torch.Tensor | None) -> torch.Tensor:
        """``latent-sky``: (B, 63) z_shape, (B,) azimuths -> (B, 3, rows, W) unit-exposure sky,
        R(phi) max(D(z), 0)^3 on the grid's sky rows."""
        from f2l_builtin_models.autoencoder.encoding import decode_unit, rotate_columns

        sky = decode_unit(self.decoder(codes))
        if azimuth is not None:
            sky = rotate_columns(sky, azimuth)
        return self.to_grid(sky)

    def to_grid(self, sky: torch.Tensor) -> torch.Tensor:
        """(B, 3, 32, 128) network sky -> (B, 3, rows, W) on the grid's sky rows (area resampling;
        the identity on 64 x 128)."""
        if self._resample is None:
            return sky
        rows, cols = self._resample
        return torch.einsum("ih,bchw,jw->bcij", rows, sky, cols)

    def radiance(self, params: torch.Tensor) -> torch.Tensor:
        """(B, 65) -> (B, L, 3): the sky on the upper rows, 0 below the horizon."""
        sky = self.sky(params)
        flat = sky.flatten(2).transpose(1, 2)
        out = torch.nn.functional.pad(flat, (0, 0, 0, self.grid.size - flat.shape[1]))
        return out.to(params.dtype)

    def sun_direction(self, params: np.ndarray) -> np.ndarray:
        """The decoded probe's sun: the Y dOmega-weighted mean direction within 5 deg of its
        brightest sky texel (``f2l.metrics.lighting.sun_direction``)."""
        from f2l.metrics.lighting import sun_direction

        return sun_direction(self.probe(np.asarray(params, dtype=np.float64)), self.grid)

    # -- probes (fit-probe, paper Table 1) -------------------------------------------------------------
    def encode_probe(self, probe: np.ndarray) -> np.ndarray:
        """(65,) feed-forward parameters of a full-sphere lat-long probe (H, 2H, 3): its sun
        azimuth, exposure and the encoder's code of its sun-centred sky (AE_FF)."""
        from f2l_builtin_models.autoencoder.encoding import centred_sky, encode, full_sphere

        sky, azimuth = centred_sky(full_sphere(probe, "probe"))
        e, log_s = encode(sky)
        with torch.no_grad():
            z = self.network.eval().encode(torch.from_numpy(e)[None])[0].double().numpy()
        return np.concatenate([[log_s], z, [azimuth]])

    def fit_to_probe(self, probe: np.ndarray, **options):
        """``fit_probe`` for this model: f2l_builtin_models.autoencoder.probe_fit (result ``ae``, variant ``ae_ff``)."""
        from f2l_builtin_models.autoencoder.probe_fit import fit_ae_to_probe

        return fit_ae_to_probe(self, probe, **options)
