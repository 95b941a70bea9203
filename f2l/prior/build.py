"""Build a model's GMM prior from a folder of lat-long sky probes (``f2l prior build``): fit the
model to every probe (:mod:`f2l.prior.probe_fit`), then a GMM over ``model.prior_features`` of
the fitted parameters (:func:`f2l.estimate.model_prior.fit_gmm`). The default corpus is
:mod:`f2l.prior.corpus`; any other folder of lat-long sky EXRs works the same."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from f2l.estimate.model_prior import GmmPrior, fit_gmm
from f2l.prior.probe_fit import ProbeRecord, fit_probe_files, list_probe_files

__all__ = ["ProbeRecord", "list_probes", "fit_probes", "build_prior"]


def list_probes(inputs: Iterable[str | Path]) -> list[Path]:
    """The probes :func:`f2l.prior.probe_fit.list_probe_files` finds: files named directly, and
    the HDR images (EXR, Radiance, PFM, float TIFF) found, sorted, recursively, in the given
    folders (use ``list_probe_files`` to get the other files of those folders named as skipped)."""
    return list_probe_files(inputs)[0]


def fit_probes(paths: list[Path], model, progress: Callable | None = None,
               out_dir: str | Path | None = None, **fit_options) -> list[ProbeRecord]:
    """:func:`f2l.prior.probe_fit.fit_probe_files`: fit_probe on every path; a bad probe
    (unreadable or oversized file, malformed side file, black, uncovered or implausibly bright
    probe, a fit that overflows) gets status 'error' and a message naming it, the rest go on.
    With ``out_dir``, each fitted probe is written there as ``<stem>_<model>.exr``. Each record's
    ``extra["metrics"]`` holds :func:`f2l.prior.probe_fit.probe_fit_metrics`, and
    ``extra["variants"]`` the same for the fit's named variants (e.g. ``ae_ff``)."""
    return fit_probe_files(paths, model, progress=progress, out_dir=out_dir, **fit_options)


def build_prior(model, records: list[ProbeRecord], n_components: int = 6, seed: int = 0,
                corpus: dict | None = None) -> GmmPrior:
    """A GMM over ``model.prior_features`` of the successfully fitted probes."""
    if model.prior_feature_names is None:
        raise ValueError(f"model {model.name!r} has no prior_features(): it does not support a GMM prior")
    ok = [r for r in records if r.status == "ok"]
    if not ok:
        raise ValueError("no probe could be fitted; see the per-probe messages")
    params = np.asarray([r.params for r in ok], dtype=np.float64)
    features = np.asarray(model.prior_features(params), dtype=np.float64)
    provenance = {"probes": len(records), "fitted": len(ok), **(corpus or {})}
    return fit_gmm(features, list(model.prior_feature_names), n_components=n_components, seed=seed,
                   model=model.name, corpus=provenance)
