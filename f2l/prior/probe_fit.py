"""Fit a lighting model directly to an HDR probe (the paper's Table 1 setting; no face involved).

Loss, over the model's domain (upper hemisphere for ``domain == "sky"``, the sphere otherwise),
weighted by texel solid angle dω and averaged over channels:

    E(θ) = Σ_ω w_ω ρ(log(1 + l_θ(ω)/s) − log(1 + l*(ω)/s))  +  mean_c (Σ_ω w_ω (l_θ − l*)_c / Σ_ω w_ω l*_c)²,

w_ω = dω / Σ dω over the domain, ρ(r) = sqrt(r² + ε²) − ε, s the probe's solid-angle-weighted
mean luminance. The log term compresses the sun (10⁴–10⁷ × the sky) so that the sky's ~4,000
texels shape the fit; it hardly sees the sun's intensity (a few texels of tiny dω), which the
second term — the squared relative error of each channel's energy, smooth — pins. Both terms are scale invariant, and
intensity parameters (``model.intensity_params``) are optimised as log(value / s): a probe and
a 10⁶ × brighter copy give the same parameters up to the intensity scale. Multi-start quasi-Newton (torch L-BFGS, all starts batched) from the
model's ``probe_starts(probe_flat)`` when it has them (data-driven starts, e.g. the sun at the
brightest texel: 2 such starts fit a compact-sun probe to 0.01° of its sun in ~4 s, where the 8
generic starts took ~10 s and landed 0.3° off, because one L-BFGS over the batch's summed loss
lets the worst start slow the others), otherwise from ``initial_points()``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from f2l.estimate.params import BoxTransform
from f2l.lighting.grid import LatLongGrid

__all__ = ["ProbeFit", "ProbeFitError", "fit_probe", "probe_fit_loss", "MAX_PROBE_RADIANCE", "list_probe_files",
           "read_side_file", "fit_probe_file", "fit_probe_files"]

START_MARGIN = 1e-3  # starts sit at least this fraction of a bounded range inside it (a sigmoid
#                     at its 1e-6 clip has no gradient left: a kappa start at 8192 could never move)
LOG_INTENSITY_LIMIT = 80.0  # intensities are fitted as log(value / s); |log| is clamped here (e^80 ≈ 6e34 × the
#                             probe's mean luminance, far past any HDR range) so that exp() cannot overflow
RESTARTS = 3  # fresh L-BFGS memories after a run stops early (a flat line-search step)

EPS = 1e-6
REC709_LUMA = np.array([0.2126, 0.7152, 0.0722])


class ProbeFitError(ValueError):
    """The probe cannot be fitted (wrong shape, non-finite or negative values, no light)."""


@dataclass
class ProbeFit:
    """params (P,), loss, L-BFGS iterations, fitted radiance (H, W, 3) float32, the model's sun
    direction (or None), wall time, the loss of every start, and named variant fits of the same
    probe that a model's own routine may add (e.g. a latent model's feed-forward encoding)."""

    params: np.ndarray
    loss: float
    iterations: int
    probe: np.ndarray
    sun_direction: np.ndarray | None
    runtime_s: float
    start_losses: list = field(default_factory=list)
    variants: dict = field(default_factory=dict)


def probe_fit_loss(radiance: torch.Tensor, target: torch.Tensor, weights: torch.Tensor,
                   scale: float) -> torch.Tensor:
    """(B, L, 3) model radiance vs (L, 3) target with (L,) weights (zero outside the domain,
    summing to 1) -> (B,) loss E of the module docstring."""
    # negative model radiance (e.g. SH lobes) is penalised through a leaky branch, so that a start
    # with l <= 0 still has a gradient
    leaky = torch.clamp(torch.where(radiance > 0, radiance, 0.01 * radiance), min=-0.5 * scale)
    r = torch.log1p(leaky / scale) - torch.log1p(target / scale)
    rho = torch.sqrt(r * r + EPS * EPS) - EPS
    shape_term = (rho.mean(dim=2) * weights).sum(dim=1)
    # energy term: the sun's few texels barely weigh in the log term, so its intensity is pinned
    # by the linear L1 error relative to the probe's energy (also scale invariant)
    energy = ((radiance - target).transpose(1, 2) @ weights) / (target.T @ weights).clamp_min(1e-300)
    return shape_term + (energy * energy).mean(dim=1)


def _check_probe(probe: np.ndarray, grid: LatLongGrid) -> np.ndarray:
    probe = np.asarray(probe, dtype=np.float64)
    if probe.shape != (grid.height, grid.width, 3):
        if (probe.ndim == 3 and probe.shape[2] == 3 and probe.shape[0] > 0
                and probe.shape[1] == 2 * probe.shape[0]):
            from f2l.lighting.resample import resample

            probe = resample(probe, grid.height, grid.width)
        else:
            raise ProbeFitError(f"probe must be a lat-long (H, 2H, 3) image, got {probe.shape}")
    if not np.isfinite(probe).all():
        raise ProbeFitError("probe holds NaN or inf")
    if (probe < 0).any():
        raise ProbeFitError("probe holds negative radiance")
    return probe


def fit_probe(probe: np.ndarray, model, *, max_iter: int = 150, tolerance: float = 1e-10,
              starts: np.ndarray | None = None, threads: int = 1) -> ProbeFit:
    """Fit ``model`` (a LightingModel on its own grid) to ``probe`` (H, W, 3) linear radiance.

    A probe on another lat-long grid is resampled (energy-preserving) to the model's grid.
    ``starts`` (S, P) replaces the model's starting points. A model with its own fit-to-probe
    routine (``model.fit_to_probe(probe, **options)`` not None, e.g. an encoder) gets the checked,
    resampled probe and these options and returns the ProbeFit itself.
    """
    t0 = time.perf_counter()
    grid = model.grid
    probe = _check_probe(probe, grid)
    own = model.fit_to_probe(probe, max_iter=max_iter, tolerance=tolerance, starts=starts, threads=threads)
    if own is not None:
        return own
    target_np = probe.reshape(-1, 3)
    domain = grid.upper_mask.reshape(-1) if model.domain == "sky" else np.ones(grid.size, bool)
    w = np.where(domain, grid.solid_angles_flat, 0.0)
    w = w / w.sum()
    scale = float((target_np @ REC709_LUMA) @ w)
    if not scale > 0:
        raise ProbeFitError("probe is black over the model's domain")

    if starts is None:
        starts = model.probe_starts(target_np)
        starts = model.initial_points() if starts is None else starts
    starts = np.atleast_2d(np.asarray(starts, dtype=np.float64))
    lo, hi = model.bounds()
    starts = np.clip(starts, lo, hi)
    # Intensity parameters (radiance ~ linear in them, e.g. w_sky, w_sun) are fitted as the log
    # of their value over the probe's scale s, so the fit is the same for any exposure.
    log_idx = np.asarray(model.intensity_params, dtype=np.int64)
    lo_x, hi_x = lo.copy(), hi.copy()
    lo_x[log_idx], hi_x[log_idx] = -np.inf, np.inf
    box = BoxTransform(lo_x, hi_x)
    x0 = box.to_unconstrained(starts, margin=START_MARGIN)
    x0[:, log_idx] = np.log(np.maximum(starts[:, log_idx] / scale, 1e-12))
    dtype = torch.float64
    target = torch.as_tensor(target_np / scale, dtype=dtype)
    weights = torch.as_tensor(w, dtype=dtype)
    log_mask = torch.zeros(model.num_params, dtype=torch.bool)
    log_mask[torch.as_tensor(log_idx)] = True

    def to_params(x_: torch.Tensor, factor: float = 1.0) -> torch.Tensor:
        """Parameters for the normalised probe (factor 1) or the original one (factor s)."""
        safe = torch.where(log_mask, x_, torch.zeros_like(x_)).clamp(-LOG_INTENSITY_LIMIT, LOG_INTENSITY_LIMIT)
        return torch.where(log_mask, torch.exp(safe) * factor, box.to_params(x_))

    def objective(x_: torch.Tensor) -> torch.Tensor:
        # A line search can step to where a parameter is not finite (a NaN direction after an
        # overflow): the loss there is +inf, and the model never sees such parameters.
        finite = torch.isfinite(x_)
        loss = probe_fit_loss(model.radiance(to_params(torch.where(finite, x_, torch.zeros_like(x_)))),
                              target, weights, 1.0)
        ok = finite.all(dim=-1) & torch.isfinite(loss)
        return torch.where(ok, loss, torch.full_like(loss, math.inf))

    prev_threads = torch.get_num_threads()
    torch.set_num_threads(max(1, int(threads)))
    try:
        # Every start is its own L-BFGS run: one L-BFGS over the batch's summed loss shares a line
        # search and a curvature memory, so a poor start stalls the good one and where it stops
        # depends on the CPU's rounding (issue 18: 2e-5 to 1.1e-4 loss across OpenBLAS/ATen paths).
        runs = [minimise_restarted(objective, torch.tensor(row[None], dtype=dtype), max_iter, tolerance)
                for row in x0]
        x = torch.cat([r[0] for r in runs])
        iterations = max(r[1] for r in runs)
        with torch.no_grad():
            losses = objective(x).numpy()
            params = to_params(x, scale)
    finally:
        torch.set_num_threads(prev_threads)
    if not np.isfinite(losses).any():
        raise ProbeFitError("the fit diverged for every start")
    best = int(np.nanargmin(losses))
    best_params = params[best].numpy().astype(np.float64)
    fitted = model.probe(best_params)
    if model.domain == "sky":
        fitted = np.where(grid.upper_mask[:, :, None], fitted, 0.0).astype(np.float32)
    return ProbeFit(
        params=best_params, loss=float(losses[best]), iterations=iterations, probe=fitted,
        sun_direction=model.sun_direction(best_params), runtime_s=time.perf_counter() - t0,
        start_losses=[float(v) for v in losses],
    )


def minimise_restarted(objective, x0: torch.Tensor, max_iter: int, tolerance: float,
                       tolerance_grad: float = 1e-12) -> tuple[torch.Tensor, int]:
    """L-BFGS (strong Wolfe) on one start (1, P) minimising ``objective(x).sum()``; returns
    (x, iterations).

    The loss is scale-normalised (the probe is divided by its mean luminance), so ``tolerance``
    is relative to a loss of order 1. torch's L-BFGS also stops when a line search returns a tiny
    step (a flat step, or a curvature memory gone stale); such an early stop is rounding-dependent,
    so the run restarts with a fresh memory, up to ``RESTARTS`` times, until a restart no longer
    lowers the loss by more than ``tolerance`` or the ``max_iter`` budget is spent. A run that
    ends at a non-finite loss (it diverged) is undone: the last finite point is returned.
    """
    x = x0.detach().clone().requires_grad_(True)
    used = 0
    with torch.no_grad():
        previous = float(objective(x).sum())
    kept = x.detach().clone()  # the last point with a finite loss: a run that diverges returns to it
    for _ in range(1 + RESTARTS):
        if used >= max_iter:
            break
        optimiser = torch.optim.LBFGS([x], lr=1.0, max_iter=max_iter - used, tolerance_grad=tolerance_grad,
                                      tolerance_change=tolerance, history_size=20,
                                      line_search_fn="strong_wolfe")

        def closure():
            optimiser.zero_grad()
            loss = objective(x).sum()
            loss.backward()
            return loss

        optimiser.step(closure)
        used += max(1, int(optimiser.state[optimiser._params[0]].get("n_iter", 0)))
        with torch.no_grad():
            loss = float(objective(x).sum())
        if not math.isfinite(loss):
            break  # the run diverged (e.g. a line search into an overflow): keep the last finite point
        kept = x.detach().clone()
        if not loss < previous - tolerance * max(1.0, abs(previous)):
            break  # this run made no progress: a stationary point, not a stale memory
        previous = loss
    return kept, used


# -- fit-probe over files: listing, side files, per-probe errors ----------------------------------------

MAX_PROBE_RADIANCE = 1e30
"""Brightest texel (linear radiance, the file's own units) a probe may hold to be fitted. The sun
is ~1e9 cd/m² and an HDR capture spans ~1e7 between sun and shadow, so 1e30 leaves 20 orders of
magnitude for any exposure scale; a file beyond it (float32 ends at 3.4e38) is refused as
implausible, because a fit's sums and products of such values overflow float32 when the fitted
probe is written."""

SIDE_FILE_SUFFIX = ".json"
"""A probe's side file is ``<probe>.json`` beside it (``sky_0001.exr`` → ``sky_0001.json``): keys
``kind`` (a short string) and ``sun_direction`` (3 finite numbers, not all zero, or null) are
used; other keys are ignored."""


def list_probe_files(inputs) -> tuple[list, list[str]]:
    """(probe paths, messages about the files left out) for ``fit-probe``'s arguments: a file
    named directly is taken as it is (it gets a per-probe error if unreadable); a folder gives its
    HDR images of every format :func:`f2l.io.probe_io.read_hdr_image` reads
    (:data:`~f2l.io.probe_io.HDR_IMAGE_EXTENSIONS`), sorted, recursively; any other file in it,
    apart from the probes' side files, is left out with a message."""
    from pathlib import Path

    from f2l.io.probe_io import HDR_IMAGE_EXTENSIONS

    found, skipped = [], []
    for item in inputs:
        p = Path(item)
        if not p.is_dir():
            found.append(p)
            continue
        files = sorted(f for f in p.rglob("*") if f.is_file())
        probes = [f for f in files if f.suffix.lower() in HDR_IMAGE_EXTENSIONS]
        sides = {f.with_suffix(SIDE_FILE_SUFFIX) for f in probes}
        found.extend(probes)
        skipped.extend(f"{f}: skipped: not an HDR image ({', '.join(HDR_IMAGE_EXTENSIONS)})"
                       for f in files if f.suffix.lower() not in HDR_IMAGE_EXTENSIONS and f not in sides)
    return found, skipped


def read_side_file(path) -> dict:
    """The validated side file of probe ``path`` (:data:`SIDE_FILE_SUFFIX`), {} when there is
    none; ValueError naming the side file and the key for anything malformed (bounded JSON
    through :func:`f2l.io.bounded.load_json`: depth, string length, NaN/inf)."""
    from pathlib import Path

    from f2l.io.bounded import load_json

    side = Path(path).with_suffix(SIDE_FILE_SUFFIX)
    if not side.is_file():
        return {}
    try:
        data = side.read_bytes()
    except OSError as exc:
        raise ValueError(f"{side}: unreadable side file ({exc.strerror or exc})") from exc
    info = load_json(data, str(side))
    if not isinstance(info, dict):
        raise ValueError(f"{side}: a side file must hold a JSON object, got {type(info).__name__}")
    kind = info.get("kind")
    if kind is not None and not (isinstance(kind, str) and 0 < len(kind) <= 64):
        raise ValueError(f"{side}: kind must be a string of 1 to 64 characters, got {str(kind)[:80]!r}")
    sun = info.get("sun_direction")
    if sun is not None:
        ok = (isinstance(sun, list) and len(sun) == 3
              and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in sun))
        vec = np.asarray(sun, dtype=np.float64) if ok else None
        if not ok or not np.isfinite(vec).all() or not np.linalg.norm(vec) > 1e-12:
            raise ValueError(f"{side}: sun_direction must be 3 finite numbers, not all zero, got {str(sun)[:80]!r}")
    return info


def _finite_float32(name: str, values) -> None:
    arr = np.asarray(values, dtype=np.float64)
    if not np.isfinite(arr).all() or (arr.size and float(np.abs(arr).max()) > float(np.finfo(np.float32).max)):
        raise ProbeFitError(f"the fitted {name} overflows float32")


def fit_probe_file(path, model, out_dir=None, **fit_options):
    """``fit_probe`` on one probe file → a :class:`ProbeRecord`; every
    failure (unreadable or oversized file, malformed side file, black, uncovered or implausibly
    bright probe, a fit or a fitted probe that overflows float32) is a record with status
    "error" and a message naming the file, never an exception. The file is read at most at the
    model's grid size (a larger image is decoded in bands, :func:`f2l.io.probe_io.read_hdr_image`);
    with ``out_dir`` the fitted probe is written there as ``<stem>_<model>.exr`` (atomically)."""
    from pathlib import Path

    from f2l.io.exr import write_exr
    from f2l.io.probe_io import hdr_image_size, read_hdr_image
    from f2l.lighting.plausibility import probe_problem

    path = Path(path)
    grid = model.grid
    kind = None
    try:
        info = read_side_file(path)
        kind = info.get("kind")
        height, width = hdr_image_size(path)
        if (height, width) != (grid.height, grid.width) and width != 2 * height:
            raise ProbeFitError(f"probe must be a lat-long (H, 2H, 3) image, got {width}x{height}")
        probe = read_hdr_image(path, (grid.height, grid.width))
        if probe.shape[1] == 2 * probe.shape[0] and probe.shape[0] % 2 == 0:
            problem = probe_problem(probe)
            if problem:
                raise ProbeFitError(problem)
        brightest = float(probe.max()) if probe.size else 0.0
        if brightest > MAX_PROBE_RADIANCE:
            raise ProbeFitError(f"brightest texel {brightest:.3g} exceeds the plausible radiance bound "
                                f"{MAX_PROBE_RADIANCE:g} (MAX_PROBE_RADIANCE)")
        fit = fit_probe(probe, model, **fit_options)
        _finite_float32("parameters", fit.params)
        _finite_float32("probe", fit.probe)
        rec = ProbeRecord(str(path), "ok", params=fit.params.tolist(), loss=fit.loss,
                          runtime_s=fit.runtime_s, kind=kind,
                          sun_direction=None if fit.sun_direction is None else
                          [float(v) for v in fit.sun_direction])
        rec.extra["metrics"] = probe_fit_metrics(fit, probe, grid)
        rec.extra["variants"] = {name: {"metrics": probe_fit_metrics(v, probe, grid),
                                        "runtime_s": v.runtime_s, "params": v.params.tolist()}
                                 for name, v in fit.variants.items()}
        if out_dir is not None:
            fitted_path = Path(out_dir) / f"{path.stem}_{model.name}.exr"
            write_exr(fitted_path, fit.probe)
            rec.extra["fitted_probe"] = str(fitted_path)
            for name, v in fit.variants.items():
                write_exr(Path(out_dir) / f"{path.stem}_{name}.exr", v.probe)
        true_sun = info.get("sun_direction")
        if true_sun is not None and fit.sun_direction is not None:
            t = np.asarray(true_sun, dtype=np.float64)
            c = float(np.clip(np.dot(t / np.linalg.norm(t), fit.sun_direction), -1.0, 1.0))
            rec.true_sun_direction = [float(v) for v in t]
            rec.sun_angle_deg = math.degrees(math.acos(c))
        return rec
    except (ProbeFitError, OSError, ValueError, ArithmeticError, RuntimeError, MemoryError) as exc:
        # (a MemoryError or a torch RuntimeError is this probe's failure: the others go on)
        message = str(exc) if str(path) in str(exc) or str(path.with_suffix(SIDE_FILE_SUFFIX)) in str(exc) \
            else f"{path}: {exc}"
        return ProbeRecord(str(path), "error", message, kind=kind)


def fit_probe_files(paths, model, progress=None, out_dir=None, **fit_options) -> list:
    """:func:`fit_probe_file` on every path, in order (one bad probe never stops the others)."""
    from pathlib import Path

    if out_dir is not None:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
    records = []
    for path in paths:
        records.append(fit_probe_file(path, model, out_dir, **fit_options))
        if progress:
            progress(1)
    return records


@dataclass
class ProbeRecord:
    """One probe's fit: path, status ('ok' or 'error'), message, params, sun direction, its
    known sun direction (side file) and the angle between them (degrees), loss, time."""

    path: str
    status: str
    message: str = ""
    params: list | None = None
    sun_direction: list | None = None
    true_sun_direction: list | None = None
    sun_angle_deg: float | None = None
    kind: str | None = None
    loss: float | None = None
    runtime_s: float | None = None
    extra: dict = field(default_factory=dict)


def probe_fit_metrics(fit, probe: np.ndarray, grid) -> dict:
    """The §5.1 lighting metrics (``f2l.metrics.lighting.probe_metrics``: Full/Sky/Sun-dω MAE and
    Sun-ang, sun metrics NaN where the overcast heuristic calls the probe overcast) of a fit
    against the probe it fitted, on the model's grid. The estimated sun is the model's own
    (``fit.sun_direction``) where it has one, else the fitted probe's brightest region."""
    from f2l.metrics.lighting import probe_metrics

    gt = _check_probe(probe, grid)
    return probe_metrics(fit.probe, gt, grid, est_sun_dir=fit.sun_direction)
