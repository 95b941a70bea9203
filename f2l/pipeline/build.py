"""``build_dataset``: a capture tree → face-record shards with ground-truth probes, incrementally.

Order of work (one build at a time per work folder and per output, :class:`BuildLock`):

1. ingest ROOT into ``WORK/captures.parquet`` (incremental; ROOT is remembered in
   ``WORK/build_root.json`` so a later build may omit it);
2. plan the sessions (:mod:`f2l.pipeline.plan`): what each needs, what is left out and why;
3. per session: its probe (merge + sphere, or the given probe), its charts (calibrate);
4. per face photo: fit-faces with transport;
5. per session the ground-truth probe in the face camera's frame, then the shards
   (:mod:`f2l.pipeline.assemble`);
6. the dataset card; if OUT already holds exactly these files and this card, nothing is written
   ("nothing to do"), else OUT is published (:mod:`f2l.pipeline.publish`).

Every stage output is a cache entry (:mod:`f2l.pipeline.cache`), so a killed build resumes
where it stopped and a re-run recomputes only what changed. Timings and per-stage counts go to
the returned :class:`BuildSummary` and to the run log ``WORK/logs/build-dataset.jsonl`` (one JSON
line per build), never into OUT.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from f2l.io.executor import check_executor
from f2l.io.progress import ProgressCallback
from f2l.pipeline.cache import BuildLock, Cache, new_build_token
from f2l.pipeline.spec import Pipeline, load_pipeline

ROOT_FILE = "build_root.json"
RUN_LOG = Path("logs") / "build-dataset.jsonl"
STAGES = ("merge", "sphere", "calibrate", "fit-faces", "gt-probe", "shards")


@dataclass
class BuildSummary:
    """What one build did: per-stage ``computed`` / ``reused`` entry counts, ingest's ``read`` /
    ``reused`` files, what publishing wrote, the card's counts, its warnings, ``failed`` (the
    inputs that failed: left-out entries with status ``error``, each with path, stage and reason)
    and timings (seconds)."""

    root: str
    work: str
    out: str
    nothing_to_do: bool = False
    ingest: dict = field(default_factory=dict)
    stages: dict = field(default_factory=dict)
    publish: dict = field(default_factory=dict)
    counts: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    failed: list = field(default_factory=list)  # the card's left_out entries with status "error"
    seconds: float = 0.0
    stage_seconds: dict = field(default_factory=dict)
    on_executor: dict = field(default_factory=dict)  # entries made by Ray tasks, per stage (--executor ray)

    @property
    def message(self) -> str:
        if self.nothing_to_do:
            return "nothing to do: the output is up to date"
        done = ", ".join(f"{s} {c['computed']}" for s, c in self.stages.items() if c["computed"])
        return f"built {self.counts.get('records', 0)} records" + (f" (computed: {done})"
                                                                   if done else "")

    def to_json(self) -> dict:
        return {**self.__dict__, "message": self.message}


def with_allow_outside(spec: Pipeline, allow: bool) -> Pipeline:
    """``spec`` with its ingest stage's ``allow_outside`` set to ``allow`` (``--allow-outside``).
    The value is part of the pipeline the card records (and so of its build key); the rows it
    changes carry it into the stage keys: a frame whose flat field lies outside is refused
    without it and records ``allow_outside`` in its ``view_json`` (the merge key) with it, and a
    capture file linked out of the tree is refused without it and read with it."""
    from dataclasses import replace

    ingest = dict(sorted({**spec.stages["ingest"], "allow_outside": bool(allow)}.items()))
    return replace(spec, stages={**spec.stages, "ingest": ingest})


def _resolve_root(root, work: Path) -> Path:
    record = work / ROOT_FILE
    if root is not None:
        return Path(root)
    try:
        return Path(json.loads(record.read_text(encoding="utf-8"))["root"])
    except (OSError, ValueError, KeyError):
        raise FileNotFoundError(f"no capture folder given and {record} does not name one: run "
                                f"`f2l build-dataset ROOT --work {work}` once") from None


def _check_outside(root: Path, work: Path, out: Path) -> None:
    """WORK and OUT must not be scanned as captures: outside ROOT, or in a hidden folder of it."""
    base = root.resolve()
    for name, path in (("--work", work), ("--out", out)):
        try:
            rel = path.resolve().relative_to(base)
        except ValueError:
            continue
        if not any(part.startswith(".") for part in rel.parts):
            raise ValueError(f"{name} {path} is inside the capture folder {root}: ingest would "
                             f"read the build's own files as captures (use a folder outside it)")


def _remember_root(root: Path, work: Path) -> None:
    from f2l.io.atomic import write_text_atomic

    write_text_atomic(work / ROOT_FILE, json.dumps({"root": str(root.resolve())}) + "\n")


def _append_log(work: Path, entry: dict) -> None:
    path = work / RUN_LOG
    path.parent.mkdir(parents=True, exist_ok=True)
    line = (json.dumps(entry, sort_keys=True) + "\n").encode("utf-8")
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    try:
        os.write(fd, line)
    finally:
        os.close(fd)


def build_dataset(root, work, out, pipeline: Pipeline | str | os.PathLike | None = None, *,
                  landmarker_path=None, echo=None, progress: ProgressCallback | None = None, executor: str = "local",
                  address: str | None = None, workers: int = 2,
                  allow_outside: bool | None = None) -> BuildSummary:
    """Build (or bring up to date) the shard folder ``out`` from the capture tree ``root``
    (None: the one a previous build in ``work`` used). ``pipeline``: a :class:`Pipeline`, a
    TOML path, or None for ``pipelines/face2light.toml``. ``echo(str)`` receives one line per
    stage as it finishes; ``progress`` (a callback, :mod:`f2l.io.progress`) is told of each face
    photo fitted. Raises
    :class:`~f2l.pipeline.cache.LockHeld`, :class:`~f2l.pipeline.spec.PipelineError`,
    FileNotFoundError or ValueError (WORK or OUT inside ROOT, an unknown executor) before writing
    anything, :class:`~f2l.io.executor.ExecutorUnavailable` (Ray not installed).
    ``executor`` "ray": the per-item stages run as Ray tasks (:mod:`f2l.pipeline.ray_build`) on
    the cluster at ``address``, or on a local one with ``workers`` CPUs; the output is the same.
    ``allow_outside``: None keeps the pipeline's ingest ``allow_outside``; True or False overrides
    it (:func:`with_allow_outside`), and the card's pipeline records the value used."""
    check_executor(executor)
    spec = pipeline if isinstance(pipeline, Pipeline) else load_pipeline(pipeline)
    if allow_outside is not None:
        spec = with_allow_outside(spec, allow_outside)
    work, out = Path(work), Path(out)
    root = Path(os.path.abspath(_resolve_root(root, work)))
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: not a folder")
    _check_outside(root, work, out)
    work.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    say = echo or (lambda line: None)
    with BuildLock(work, out):
        summary = BuildSummary(root=str(root), work=str(work), out=str(out))
        cache = Cache(work)
        token = new_build_token(work)  # before the sweep: a killed build's Ray tasks stop publishing
        swept = cache.sweep()
        if swept:
            say(f"removed {swept} unfinished cache entr{'y' if swept == 1 else 'ies'} "
                f"of an interrupted build")
        from f2l.pipeline.run import run_stages

        run_stages(spec, root, work, out, cache, summary, landmarker_path, say, progress,
                   {"name": executor, "address": address, "workers": workers, "token": token})
        # a Ray task of a killed build can outlive its driver and begin an entry after the first
        # sweep (it cannot publish it: the token); none of this build's writers runs now
        cache.sweep()
        _remember_root(root, work)
    summary.seconds = round(time.perf_counter() - t_start, 3)
    _append_log(work, {"utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                       "pid": os.getpid(), "root": str(Path(root).resolve()),
                       "out": str(out.resolve()), "pipeline": spec.source,
                       "nothing_to_do": summary.nothing_to_do, "ingest": summary.ingest,
                       "stages": summary.stages, "publish": summary.publish,
                       "counts": summary.counts, "failed": len(summary.failed), "seconds": summary.seconds,
                       "stage_seconds": summary.stage_seconds})
    return summary
