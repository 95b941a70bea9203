"""Fitting the sky autoencoder to an HDR probe (``f2l eval fit-probe --model ae``, paper Table 1).

- AE_FF (variant ``ae_ff``): the feed-forward code theta_FF = (log s, encoder(e), phi_sun) of the
  probe's sun-centred, encoded sky (``AE.encode_probe``), decoded: no optimisation.
- AE (the fit): theta minimising the probe-fit loss E of :mod:`f2l.prior.probe_fit` (log-
  compressed Charbonnier over the sky hemisphere, dOmega-weighted, + the relative energy per
  channel) from theta_FF, with torch's L-BFGS (strong Wolfe). The exposure z_0 is fitted as
  z_0 - log s* (s* the probe's mean luminance), so the fit is the same for any exposure.

Both are returned as one :class:`~f2l.prior.probe_fit.ProbeFit` (the AE fit) whose
``variants["ae_ff"]`` holds the feed-forward one; ``f2l eval fit-probe`` reports both.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from f2l.prior.probe_fit import REC709_LUMA, ProbeFit, ProbeFitError, minimise_restarted, probe_fit_loss

VARIANT_FF = "ae_ff"


def fit_ae_to_probe(model, probe: np.ndarray, *, max_iter: int = 150, tolerance: float = 1e-10,
                    starts: np.ndarray | None = None, threads: int = 1) -> ProbeFit:
    """Fit ``model`` (an ``AE``) to ``probe`` (H, W, 3) on the model's grid (module docstring)."""
    t0 = time.perf_counter()
    grid = model.grid
    target_np = np.asarray(probe, dtype=np.float64).reshape(-1, 3)
    w = np.where(grid.upper_mask.reshape(-1), grid.solid_angles_flat, 0.0)
    w = w / w.sum()
    scale = float((target_np @ REC709_LUMA) @ w)
    if not scale > 0:
        raise ProbeFitError("probe is black over the model's domain")
    prev_threads = torch.get_num_threads()
    torch.set_num_threads(max(1, int(threads)))
    try:
        ff = model.encode_probe(np.asarray(probe, dtype=np.float64))
        ff_time = time.perf_counter() - t0
        x0 = np.atleast_2d(ff if starts is None else np.asarray(starts, dtype=np.float64)).copy()
        log_scale = math.log(scale)
        x0[:, model.exposure_index] -= log_scale
        target = torch.as_tensor(target_np / scale, dtype=torch.float32)
        weights = torch.as_tensor(w, dtype=torch.float32)

        def losses(params: torch.Tensor) -> torch.Tensor:
            return probe_fit_loss(model.radiance(params), target, weights, 1.0)

        x = torch.as_tensor(x0, dtype=torch.float32)
        with torch.no_grad():
            ff_loss = float(losses(x[:1])[0])
        iterations = 0
        if max_iter > 0:  # each start on its own (probe_fit: batched starts stop CPU-dependently)
            runs = [minimise_restarted(losses, x[i : i + 1], max_iter, tolerance, tolerance_grad=1e-9)
                    for i in range(len(x))]
            x = torch.cat([r[0] for r in runs])
            iterations = max(r[1] for r in runs)
        with torch.no_grad():
            final = losses(x).numpy().astype(np.float64)
    finally:
        torch.set_num_threads(prev_threads)
    if not np.isfinite(final).any():
        raise ProbeFitError("the fit diverged for every start")
    best = int(np.nanargmin(final))
    params = x.detach()[best].double().numpy()
    params[model.exposure_index] += log_scale
    ff_fit = ProbeFit(params=ff, loss=ff_loss, iterations=0, probe=_sky_probe(model, ff),
                      sun_direction=model.sun_direction(ff), runtime_s=ff_time, start_losses=[ff_loss])
    return ProbeFit(params=params, loss=float(final[best]), iterations=iterations, probe=_sky_probe(model, params),
                    sun_direction=model.sun_direction(params), runtime_s=time.perf_counter() - t0,
                    start_losses=[float(v) for v in final], variants={VARIANT_FF: ff_fit})


def _sky_probe(model, params: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 probe of ``params``, 0 below the horizon."""
    return np.where(model.grid.upper_mask[:, :, None], model.probe(params), 0.0).astype(np.float32)
