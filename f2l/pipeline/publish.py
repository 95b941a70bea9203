"""Publishing cache entries into the output folder OUT, incrementally and safely.

OUT is complete exactly when ``OUT/dataset_card.json`` exists: publishing removes the card
first and writes it last. Files are copied from the cache with a temporary name and renamed
(``.<name>.<random>.tmp``), so OUT never holds a half-written file under a final name.

What OUT holds is recorded outside it, in ``WORK/published/<hash of OUT's path>.json``
(``{relative path: key}``). A file is copied again only when its key changed, it is missing, or
its size differs from its source. Before anything is touched the record drops every file about
to change, so a build killed mid-way never leaves a stale entry trusted. At the end, files that
a build-dataset output may hold (``part-*.parquet``, ``probes/``, ``photos/``, ``overlays/``,
temporary files) but that this build does not list are removed; other files are left alone.
"""

from __future__ import annotations

import hashlib
import json
import re
import shutil
from pathlib import Path

from f2l.io.atomic import atomic_path, write_text_atomic

CARD_NAME = "dataset_card.json"
OWNED_DIRS = ("probes", "photos", "overlays")
_OWNED_TOP = re.compile(r"^(part-\d{5,}\.parquet|\..*\.tmp|.*\.\d+\.tmp)$")


def manifest_path(work: Path, out: Path) -> Path:
    digest = hashlib.sha256(str(Path(out).resolve()).encode("utf-8")).hexdigest()[:16]
    return Path(work) / "published" / f"{digest}.json"


def _read_manifest(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return {str(k): str(v) for k, v in data["files"].items()}
    except (OSError, ValueError, KeyError, AttributeError):
        return {}


def _write_manifest(path: Path, files: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps({"files": dict(sorted(files.items()))}, indent=0))


def _owned(out: Path) -> set[str]:
    """Relative paths of the files in OUT that a build owns (module docstring)."""
    found = set()
    if not out.is_dir():
        return found
    for p in out.iterdir():
        if p.is_file() and (_OWNED_TOP.match(p.name) or p.name == CARD_NAME):
            found.add(p.name)
    for sub in OWNED_DIRS:
        d = out / sub
        if d.is_dir():
            found.update(q.relative_to(out).as_posix() for q in d.rglob("*") if q.is_file())
    return found


def up_to_date(work: Path, out: Path, files: dict, card_text: str) -> bool:
    """Whether OUT already holds exactly ``files`` ({rel: (source, key)}) and this card."""
    card = Path(out) / CARD_NAME
    try:
        if card.read_text(encoding="utf-8") != card_text:
            return False
    except OSError:
        return False
    recorded = _read_manifest(manifest_path(work, out))
    if recorded != {rel: key for rel, (_, key) in files.items()}:
        return False
    for rel, (source, _) in files.items():
        try:
            if (Path(out) / rel).stat().st_size != Path(source).stat().st_size:
                return False
        except OSError:
            return False
    return _owned(Path(out)) == set(files) | {CARD_NAME}


def publish(work: Path, out: Path, files: dict, card_text: str) -> dict:
    """Make OUT hold ``files`` ({relative path: (source file, key)}) and the card; returns
    ``{"written", "kept", "removed"}`` counts."""
    out, work = Path(out), Path(work)
    out.mkdir(parents=True, exist_ok=True)
    (out / CARD_NAME).unlink(missing_ok=True)
    mpath = manifest_path(work, out)
    recorded = _read_manifest(mpath)
    keep = {}
    for rel, key in recorded.items():
        if rel in files and files[rel][1] == key:
            try:
                if (out / rel).stat().st_size == Path(files[rel][0]).stat().st_size:
                    keep[rel] = key
            except OSError:
                pass
    _write_manifest(mpath, keep)
    written = 0
    for rel in sorted(files):
        if rel in keep:
            continue
        source, _ = files[rel]
        target = out / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(target) as tmp:
            shutil.copyfile(source, tmp)
        written += 1
    removed = 0
    for rel in sorted(_owned(out) - set(files)):
        (out / rel).unlink(missing_ok=True)
        removed += 1
    for sub in OWNED_DIRS:
        d = out / sub
        if d.is_dir() and not any(d.iterdir()):
            d.rmdir()
    _write_manifest(mpath, {rel: key for rel, (_, key) in files.items()})
    write_text_atomic(out / CARD_NAME, card_text)
    return {"written": written, "kept": len(keep), "removed": removed}
