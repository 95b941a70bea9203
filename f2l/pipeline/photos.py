"""Photos straight into ``f2l estimate``: every face of each photo fitted on the way, cached by content.

``f2l estimate photo.jpg …`` (or a folder of photos) fits each photo with the default pipeline's
``fit-faces`` and ``transport`` parameters (:mod:`f2l.pipeline.faces`, the same stage as
``build-dataset``) into ``OUT/faces/cache/fit-faces/<key>/``: the photo's face-record shard,
crops, per-face overlays and the whole-photo overlay. The key is the photo's file name and
SHA-256, the pinned models' SHA-256 and the parameters, so a rerun, or the same bytes under the
same name in another folder, reuses the entry and fits nothing. A photo that cannot be read or
holds no usable face gets its status and reason (cached too: an unchanged bad photo is not
retried) and never stops the others. A photo whose file name is not valid UTF-8 is refused
with a status naming it (its undecodable bytes as ``\\xNN``): the cache and the records keep
names as UTF-8 text; renamed, it is fitted.
"""

from __future__ import annotations

import os
from pathlib import Path

from f2l.face.run import PHOTO_EXTENSIONS, RAW_EXTENSIONS, expand_photos, printable, printable_path
from f2l.io.progress import Progress, ProgressCallback

FACES_DIR = "faces"


def is_photo_input(path: str | os.PathLike) -> bool:
    """A photo or RAW file, or a folder with photos and no Parquet shard of its own."""
    p = Path(path)
    if p.is_file():
        return p.suffix.lower() in PHOTO_EXTENSIONS | RAW_EXTENSIONS
    if p.is_dir():
        return not any(p.glob("*.parquet")) and bool(expand_photos([p]))
    return False


def fit_photos(inputs, out: str | os.PathLike, *, min_face_px: float | None = None,
               progress: ProgressCallback | None = None) -> dict:
    """Fit every face of the photos under ``inputs`` (files or folders) into the cache under
    ``OUT/faces``; returns ``{"shards": [entry folders with records], "photos": [per-photo status
    rows], "counts": {status: n, "reused": n, "computed": n}}``. ``progress``: a callback told of
    each photo and of each photo that is not ok, with its reason (:mod:`f2l.io.progress`)."""
    from f2l.io.hashing import file_sha256
    from f2l.pipeline.cache import Cache
    from f2l.pipeline.faces import FaceFitter
    from f2l.pipeline.spec import load_pipeline

    spec = load_pipeline()
    fit = dict(spec.params("fit-faces"))
    if min_face_px is not None:
        fit["min_face_px"] = float(min_face_px)
    cache = Cache(Path(out) / FACES_DIR)
    cache.sweep()
    fitter = None
    files = expand_photos(inputs)
    counts: dict = {}
    rows, shards = [], []
    bar = Progress(progress, "fit faces", "photo", len(files))
    for path in files:
        shown = printable_path(path)
        if shown != str(path):
            row = {"source_path": shown, "status": "error", "face_ids": [], "rejected": [],
                   "message": f"{shown}: the file name is not valid UTF-8 (its undecodable bytes "
                              f"shown as \\xNN); rename the file to estimate it"}
            counts["error"] = counts.get("error", 0) + 1
            rows.append(row)
            bar.note(f"error: {row['message']}")
            bar.advance(1)
            continue
        try:
            sha = file_sha256(path)
        except OSError as exc:
            row = {"source_path": shown, "status": "error", "face_ids": [], "rejected": [],
                   "message": printable(f"{path}: cannot read: {exc.strerror or exc}")}
        else:
            if fitter is None:
                fitter = FaceFitter(cache, path.parent, fit, spec.params("transport"),
                                    (spec.grid_height, spec.grid_width))
            fitter.root = path.parent
            result = fitter({"path": path.name, "sha256": sha, "camera": ""}, counts, {})
            row = {"source_path": str(path), "status": result["status"], "face_ids": result["face_ids"],
                   "rejected": result["rejected"], "entry": result["entry"],
                   "message": result["message"].replace(path.name, str(path), 1)}
            if result["face_ids"] and Path(result["entry"]) not in shards:  # same bytes, same name: one entry
                shards.append(Path(result["entry"]))
        counts[row["status"]] = counts.get(row["status"], 0) + 1
        rows.append(row)
        if row["status"] != "ok":
            bar.note(f"{row['status']}: {row['message']}")
        bar.advance(1)
    return {"shards": shards, "photos": rows, "counts": counts}
