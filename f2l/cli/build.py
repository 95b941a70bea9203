"""CLI layer of ``f2l build-dataset`` (registered by :mod:`f2l.cli.app` as
``app.command("build-dataset")(build_dataset_cmd)``; ``python -m f2l.cli.build`` runs it on
its own).

Exit codes (one build collects a status per input, writes what it could, atomically, and the
exit code says whether anything failed): 0 built or up to date and no input failed; 1 the
dataset holds no record (the card says why); 2 bad arguments, pipeline file, capture folder or
face model (nothing written), or a machine that cannot run the build (out of memory, a library
that cannot be loaded; finished cache entries are kept); 3 another build holds the lock; 4 built, but some inputs failed
(status ``error``: an unreadable file, a bracket that could not be merged or placed, a probe
refused as black, uncovered or not finite): each is printed with its session or file and the
reason, listed under ``failed`` in ``--json`` and in the card's ``left_out``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional

import typer

from f2l.cli.common import JsonOut
from f2l.cli.progress import progress_bars


def build_dataset_cmd(
    root: Optional[Path] = typer.Argument(None, help="Capture tree (one folder per session). It is ingested (incrementally) first; leave it out to rebuild from the tree the last build in WORK used."),
    pipeline: Optional[Path] = typer.Option(None, "--pipeline", help="Pipeline TOML (default: pipelines/face2light.toml)."),
    work: Path = typer.Option(Path("work"), "--work", help="Work folder: captures.parquet, the stage cache, the lock and the run log."),
    out: Path = typer.Option(Path("shards"), "--out", help="Output shard folder (face records, probes/, photos/, overlays/, dataset_card.json)."),
    landmarker: Optional[Path] = typer.Option(None, help="face_landmarker.task to use (default: $F2L_FACE_LANDMARKER or the pinned copy)."),
    executor: str = typer.Option("local", "--executor", help="local, or ray: merge, sphere, calibrate and fit-faces (with transport) as Ray tasks; the same output."),
    address: Optional[str] = typer.Option(None, "--address", help="--executor ray: the cluster (HOST:PORT); without it a local Ray with --workers CPUs."),
    workers: int = typer.Option(2, "--workers", min=1, help="--executor ray without --address: CPUs of the local Ray."),
    allow_outside: bool = typer.Option(False, "--allow-outside", help="As f2l ingest --allow-outside: a session.toml may name a flat field outside its session folder, and capture files that are symlinks out of ROOT are read (refused by default). Overrides the pipeline's ingest allow_outside."),
    json_out: JsonOut = False,
) -> None:
    """Capture tree → face-record shards paired with their session's probe: ingest → merge → sphere → calibrate → fit-faces → transport → shards. Only what changed is recomputed ("nothing to do" when nothing did); OUT/dataset_card.json says what was built, from what, how, and what was left out.

    One bad input never stops the build: it is left out with its reason (a probe that is unreadable, black, sees too little sky or holds NaN is never ground truth). Exit code: 0 built (or up to date) and nothing failed; 1 no record built; 2 bad arguments, pipeline, capture folder or face model, or out of memory; 3 another build holds the lock; 4 built, but some inputs failed (printed with file and reason; `failed` in --json)."""
    from f2l.face.landmarker import LandmarkerError
    from f2l.pipeline.build import build_dataset
    from f2l.pipeline.cache import LockHeld
    from f2l.io.executor import ExecutorUnavailable
    from f2l.face.mesh import FaceMeshError

    echo = None if json_out else (lambda line: typer.echo(line, err=True))
    try:
        with progress_bars(not json_out and sys.stderr.isatty()) as progress:
            summary = build_dataset(root, work, out, pipeline, landmarker_path=landmarker, echo=echo,
                                    progress=progress, executor=executor, address=address, workers=workers,
                                    allow_outside=True if allow_outside else None)
    except LockHeld as exc:
        typer.echo(f"f2l: error: {exc}", err=True)
        raise typer.Exit(code=3)
    except (ValueError, FileNotFoundError, LandmarkerError, FaceMeshError, ExecutorUnavailable) as exc:
        typer.echo(f"f2l: error: {exc}", err=True)
        raise typer.Exit(code=2)
    except (MemoryError, ImportError) as exc:  # the machine, not an input: nothing is cached for it
        typer.echo(f"f2l: error: the build cannot run here ({type(exc).__name__}: {exc or 'out of memory'}); "
                   f"what was finished is kept in {work} and a rerun resumes it", err=True)
        raise typer.Exit(code=2)
    if json_out:
        data = summary.to_json()
        data["stage_seconds"] = {k: v for k, v in data["stage_seconds"].items() if k != "items"}
        typer.echo(json.dumps(data))
    else:
        counts = summary.counts
        typer.echo(f"{summary.message}. {counts.get('records', 0)} records from "
                   f"{counts.get('face_photos_used', 0)} of {counts.get('face_photos', 0)} face "
                   f"photos in {counts.get('shards', 0)} shards, {counts.get('left_out', 0)} "
                   f"inputs left out -> {out} ({summary.seconds:.1f} s)")
        for warning in summary.warnings[:20]:
            typer.echo(f"  warning: {warning}")
        if len(summary.warnings) > 20:
            typer.echo(f"  ... and {len(summary.warnings) - 20} more warnings (dataset_card.json)")
        for f in summary.failed[:20]:
            typer.echo(f"  failed: {f['path']} ({f['stage']}): {f['reason']}", err=True)
        if len(summary.failed) > 20:
            typer.echo(f"  ... and {len(summary.failed) - 20} more failed inputs (dataset_card.json "
                       f"left_out, status error)", err=True)
    if not summary.counts.get("records"):
        raise typer.Exit(code=1)
    if summary.failed:
        raise typer.Exit(code=4)


def main() -> None:
    app = typer.Typer(add_completion=False)
    app.command()(build_dataset_cmd)
    app(prog_name="f2l build-dataset")


if __name__ == "__main__":
    sys.exit(main())
