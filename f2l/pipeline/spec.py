"""Pipeline files: a TOML list of stages with parameters, validated against
``schemas/pipeline.schema.json``, with every parameter left out filled from that schema's
``default`` values (the schema is the one place defaults live).

Rules beyond the schema: each stage appears at most once and in the order of :data:`STAGE_ORDER`;
``ingest``, ``fit-faces``, ``transport`` and ``shards`` are required; ``merge`` and ``sphere``
come together (a pipeline without them uses only the probes given in the capture tree); without
``calibrate`` every face keeps its camera RGB (identity correction).
"""

from __future__ import annotations

import hashlib
import json
import os
from importlib import resources
from dataclasses import dataclass, replace
from pathlib import Path

STAGE_ORDER = ("ingest", "merge", "sphere", "calibrate", "fit-faces", "transport", "shards")
REQUIRED_STAGES = ("ingest", "fit-faces", "transport", "shards")
DEFAULT_PIPELINE = "face2light.toml"
SCHEMA_NAME = "pipeline"


class PipelineError(ValueError):
    """A pipeline file that cannot be used; the message names the file and the problem."""


@dataclass(frozen=True)
class Pipeline:
    """A validated pipeline: ``stages`` maps stage name → parameters (defaults filled in, no
    ``name`` key), in :data:`STAGE_ORDER`; ``grid_height`` × ``grid_width`` texels."""

    name: str
    version: int
    grid_height: int
    grid_width: int
    stages: dict
    source: str  # the file name (no folder: the dataset card holds no machine paths)
    file_sha256: str

    def has(self, stage: str) -> bool:
        return stage in self.stages

    def params(self, stage: str) -> dict:
        """Parameters of ``stage`` ({} when the pipeline leaves it out)."""
        return dict(self.stages.get(stage, {}))

    def to_json(self) -> dict:
        """JSON-able description (for the dataset card and cache keys); no paths."""
        return {"name": self.name, "version": self.version,
                "grid": [self.grid_height, self.grid_width],
                "stages": [{"name": s, **self.stages[s]} for s in self.stages],
                "file": self.source, "file_sha256": self.file_sha256}


def pipelines_dir() -> Path:
    """The package ``f2l.pipelines``, whose single source is the repository's top-level
    ``pipelines/`` (pyproject maps it in; a wheel carries a copy)."""
    try:
        # a data folder without __init__.py is a namespace package: files() gives a
        # MultiplexedPath, whose joinpath of an existing file is a real path
        folder = Path(str(resources.files("f2l.pipelines").joinpath(DEFAULT_PIPELINE))).parent
    except ModuleNotFoundError:
        folder = Path(__file__).resolve().parents[2] / "pipelines"  # a source tree on sys.path
    if not (folder / DEFAULT_PIPELINE).is_file():
        raise FileNotFoundError(f"default pipeline {DEFAULT_PIPELINE} not found in {folder} "
                                "(is f2l installed with its package data?)")
    return folder


def default_pipeline_path() -> Path:
    return pipelines_dir() / DEFAULT_PIPELINE


def _defaults(schema: dict, stage: str) -> dict:
    props = schema["$defs"][stage]["properties"]
    return {k: v["default"] for k, v in props.items() if "default" in v}


def _schema_errors(config: dict, schema: dict) -> list[str]:
    import jsonschema

    validator = jsonschema.Draft202012Validator(schema)
    out = []
    for err in sorted(validator.iter_errors(config), key=lambda e: list(map(str, e.absolute_path))):
        where = "/".join(str(p) for p in err.absolute_path) or "(top level)"
        out.append(f"{where}: {err.message}")
    return out


def parse_pipeline(config: dict, source: str = "pipeline", file_sha256: str = "") -> Pipeline:
    """Validate a parsed pipeline document and fill in defaults (PipelineError naming ``source``)."""
    from f2l.io.schema import load_schema

    schema = load_schema(SCHEMA_NAME)
    errors = _schema_errors(config, schema)
    if errors:
        raise PipelineError(f"{source}: " + "; ".join(errors[:10]))
    names = [s["name"] for s in config["stages"]]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise PipelineError(f"{source}: stage(s) {', '.join(duplicates)} appear more than once")
    if names != sorted(names, key=STAGE_ORDER.index):
        raise PipelineError(f"{source}: stages must run in the order {' → '.join(STAGE_ORDER)} "
                            f"(got {' → '.join(names)})")
    missing = [s for s in REQUIRED_STAGES if s not in names]
    if missing:
        raise PipelineError(f"{source}: required stage(s) missing: {', '.join(missing)}")
    if ("merge" in names) != ("sphere" in names):
        raise PipelineError(f"{source}: merge and sphere go together (one without the other "
                            f"leaves brackets unmerged or nothing to assemble)")
    stages = {}
    for stage in config["stages"]:
        params = _defaults(schema, stage["name"])
        params.update({k: v for k, v in stage.items() if k != "name"})
        stages[stage["name"]] = dict(sorted(params.items()))
    grid_defaults = {k: v["default"] for k, v in schema["properties"]["grid"]["properties"].items()}
    grid = {**grid_defaults, **config.get("grid", {})}
    return Pipeline(name=config["name"], version=int(config["version"]),
                    grid_height=int(grid["height"]), grid_width=int(grid["width"]), stages=stages,
                    source=source, file_sha256=file_sha256)


def load_pipeline(path: str | os.PathLike | None = None) -> Pipeline:
    """Read and validate a pipeline TOML (the default ``pipelines/face2light.toml`` when None)."""
    path = Path(path) if path is not None else default_pipeline_path()
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise PipelineError(f"{path}: cannot read pipeline file ({exc.strerror or exc})") from None
    from f2l.io.bounded import InputError, load_toml

    try:
        config = load_toml(data, str(path))
    except InputError as exc:
        raise PipelineError(str(exc)) from None
    spec = parse_pipeline(config, source=str(path), file_sha256=hashlib.sha256(data).hexdigest())
    return replace(spec, source=path.name)


def canonical_json(value) -> str:
    """Compact, key-sorted JSON: the byte form that cache keys and the dataset card hash."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=True,
                      allow_nan=False)
