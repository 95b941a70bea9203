"""Building a model's GMM prior (``f2l prior sky-corpus|build``): sky corpus → fitted parameters →
GMM prior JSON. The estimator only evaluates a prior (:mod:`f2l.estimate.model_prior`); this
package makes one.

- :mod:`f2l.prior.corpus` — the project's default training corpus of lat-long sky probes;
- :mod:`f2l.prior.probe_fit` — a model fitted directly to one HDR probe (the paper's Table 1 fit; also
  the truth fits of :mod:`f2l.evaluation.truth_fit` and a plugin's own probe fit);
- :mod:`f2l.prior.build` — fit the model to each probe, then a GMM over its prior features;
- :mod:`f2l.prior.fit_report` — the per-probe fit summary and tables (``f2l eval fit-probe``).
"""
