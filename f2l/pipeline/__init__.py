"""``f2l build-dataset``: declarative pipelines (``pipelines/*.toml``) that turn a capture tree into
face-record shards paired with ground-truth probes, reproducibly, incrementally and safely.

- :mod:`f2l.pipeline.spec` — pipeline files, validated against ``schemas/pipeline.schema.json``;
- :mod:`f2l.pipeline.cache` — content-keyed stage outputs in ``WORK/cache``, the build lock;
- :mod:`f2l.pipeline.plan` — what each session needs and what is left out;
- :mod:`f2l.pipeline.probes`, :mod:`f2l.pipeline.faces`, :mod:`f2l.pipeline.assemble` — stages;
- :mod:`f2l.pipeline.publish`, :mod:`f2l.pipeline.card` — the output folder and its card;
- :mod:`f2l.pipeline.build` — :func:`build_dataset`; the command is :mod:`f2l.cli.build`.
"""

from f2l.pipeline.build import BuildSummary, build_dataset
from f2l.pipeline.cache import LockHeld
from f2l.pipeline.spec import Pipeline, PipelineError, load_pipeline

__all__ = ["BuildSummary", "LockHeld", "Pipeline", "PipelineError", "build_dataset",
           "load_pipeline"]
