"""``f2l fit-faces``: photos → face-record shards, crops, overlays and a per-photo status table.

Output directory layout (a shard directory that ``f2l estimate`` reads)::

    OUT/part-00000.parquet        face records (schema face_record), one row group per face
    OUT/photos/<face_id>.png      the working-resolution crop that pixel_rc refers to
    OUT/overlays/<face_id>.png    debug overlay (landmarks + mesh, normals, mask, sky visibility)
    OUT/overlays/<photo>.png      the whole photo, every detected face framed: kept or refused (why)
    OUT/probes/<face_id>.exr      ground-truth probe, when --gt-probes holds <photo stem>.exr
    OUT/status/fit_faces.parquet  one row per photo (schema photo_status)

Face ids are ``<photo stem>-<first 10 hex of the file's SHA-256>-f<index>`` (file-name safe),
so the same bytes give the same ids wherever the file lives. One bad photo never stops the
batch: it gets status ``error`` with a message naming it; ``no_face`` and ``rejected`` photos
are counted. Every file is written atomically.

A photo whose file name is not valid UTF-8 (bytes a Linux file system allows, which Parquet
strings cannot hold) is fitted like any other, recorded under its name with each undecodable byte
escaped as ``\\xNN`` (:func:`printable_path`); its status message says so.
"""

from __future__ import annotations

import json
import os
import re
import time
from pathlib import Path

import numpy as np

from f2l.face.fit import FaceFit, FitOptions, face_record, fit_photo_faces, sky_visibility
from f2l.io.hashing import file_sha256
from f2l.io.progress import Progress, ProgressCallback

PHOTO_EXTENSIONS = {".jpg", ".jpeg", ".png", ".tif", ".tiff"}
RAW_EXTENSIONS = {".cr2", ".cr3", ".crw", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".dng", ".raf",
                  ".orf", ".rw2", ".pef", ".srw", ".x3f", ".3fr", ".iiq", ".rwl", ".mrw", ".kdc",
                  ".dcr", ".erf", ".mef", ".mos"}
STATUS_TABLE = Path("status") / "fit_faces.parquet"


def expand_photos(paths) -> list[Path]:
    """Files as given, folders expanded recursively to photo/RAW files (sorted)."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out.extend(sorted(q for q in p.rglob("*") if q.is_file()
                              and q.suffix.lower() in PHOTO_EXTENSIONS | RAW_EXTENSIONS))
        else:
            out.append(p)
    return out


def printable(text: str) -> str:
    """``text`` as valid UTF-8: the undecodable bytes of a file name (``surrogateescape``) as
    ``\\xNN``, any other lone surrogate as ``\\uNNNN``."""
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        pass
    try:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    except UnicodeEncodeError:
        return text.encode("utf-8", "backslashreplace").decode("utf-8")


def printable_path(path) -> str:
    """The path as tables and messages can hold it: ``str(path)``, or where its name is not valid
    UTF-8, that name with each undecodable byte escaped as ``\\xNN``."""
    return printable(os.fspath(path))


def face_id(path: Path, sha256: str, index: int) -> str:
    stem = re.sub(r"[^A-Za-z0-9._+=@#-]", "_", path.stem).lstrip("._-+=@#") or "photo"
    return f"{stem[:160]}-{sha256[:10]}-f{index}"


def _overlay(out: Path, fid: str, fit: FaceFit, options: FitOptions) -> str:
    from f2l.face.overlay import write_overlay
    from f2l.face.mesh import canonical_face_mesh

    rel = f"overlays/{fid}.png"
    (out / "overlays").mkdir(parents=True, exist_ok=True)
    counts = fit.counts()
    title = (f"{fid}  yaw {fit.head.yaw_deg:+.0f}° pitch {fit.head.pitch_deg:+.0f}°  "
             f"{counts['num_masked']}/{counts['num_pixels']} px usable")
    write_overlay(out / rel, crop=fit.crop_display, landmarks_xy=fit.view.to_working(fit.landmarks),
                  triangles=np.asarray(canonical_face_mesh()[1]), pixel_rc=fit.pixel_rc,
                  normals=fit.normals, mask=fit.mask, excluded=fit.excluded,
                  sky_visibility=sky_visibility(fit.visibility_bits, options.grid), title=title,
                  traced=fit.traced)
    return rel


OVERLAY_MAX_SIDE = 1600


def _photo_overlay(out: Path, path: Path, sha: str, photo, fits, records) -> str:
    """``overlays/<photo stem>-<sha10>.png``: the photo (reduced to ``OVERLAY_MAX_SIDE``) with every
    detected face framed, kept (green, its index) or refused (red, the reason)."""
    from f2l.face.fit import landmark_box
    from f2l.face.overlay import write_photo_overlay

    display, scale, offset = photo.detection_image(OVERLAY_MAX_SIDE)
    ids = {r.face_index: r.face_id for r, _ in records}
    faces = []
    for fit in fits:
        if isinstance(fit, FaceFit):
            faces.append((landmark_box(fit.landmarks), f"f{fit.face_index}", fit.face_index in ids))
        elif fit.box is not None:
            faces.append((fit.box, f"f{fit.face_index} {fit.reason}", False))
    faces = [((np.asarray(b) - np.tile(offset, 2)), label, kept) for b, label, kept in faces]
    rel = f"overlays/{face_id(path, sha, 0).rsplit('-f', 1)[0]}.png"
    (out / "overlays").mkdir(parents=True, exist_ok=True)
    kept = sum(k for _, _, k in faces)
    write_photo_overlay(out / rel, display, scale, faces,
                        title=f"{printable(path.name)}: {len(fits)} face(s) detected, {kept} kept, {len(fits) - kept} refused")
    return rel


def _gt_probe(out: Path, fid: str, photo_path: Path, gt_dir: Path | None, grid) -> str | None:
    """Attach ``gt_dir/<photo stem>.exr``, area-resampled to the record's lighting grid."""
    if gt_dir is None:
        return None
    src = gt_dir / f"{photo_path.stem}.exr"
    if not src.is_file():
        return None
    from f2l.io.exr import read_exr
    from f2l.io.side_files import write_side_probe

    probe = np.asarray(read_exr(src), dtype=np.float32)
    if probe.shape[:2] != grid.shape:  # e.g. a renderer's 128 x 256 truth for a 64 x 128 fit
        from f2l.lighting.resample import resample

        probe = resample(probe, grid.height, grid.width)
    return write_side_probe(out, fid, probe)


def fit_faces(photos, out, options: FitOptions = FitOptions(), *, overlays: bool = True,
              landmarker_path=None, gt_probes=None, progress: ProgressCallback | None = None,
              records_per_shard: int = 64) -> dict:
    """Fit every face of every photo into the shard directory ``out``; returns a summary.
    ``progress``: a callback told of each photo, and of each one not ok (:mod:`f2l.io.progress`)."""
    from f2l.face.landmarker import FaceLandmarker
    from f2l.io.photo import PhotoError, load_photo
    from f2l.io.shards import ShardWriter
    from f2l.io.side_files import write_side_photo
    from f2l.io.tables import ParquetAppender

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / STATUS_TABLE).parent.mkdir(parents=True, exist_ok=True)
    files = expand_photos(photos)
    gt_dir = Path(gt_probes) if gt_probes is not None else None
    landmarker = FaceLandmarker(landmarker_path, threads=1)
    counts = {"ok": 0, "no_face": 0, "rejected": 0, "error": 0}
    n_records, per_face_s, t_start = 0, [], time.perf_counter()
    bar = Progress(progress, "fit-faces", "photo", len(files))
    with ShardWriter(out, records_per_shard=records_per_shard, overwrite=True) as writer, \
            ParquetAppender(out / STATUS_TABLE, "photo_status", rows_per_group=256) as status:
        for path in files:
            t0 = time.perf_counter()
            shown = printable_path(path)  # what the tables and messages hold
            row = {"source_path": shown, "sha256": "", "num_detected": 0, "face_ids": [],
                   "rejected_json": "[]", "overlay_path": None}
            try:
                if not path.is_file():
                    raise PhotoError(path, "no such file")
                row["sha256"] = sha = file_sha256(path)
                photo = load_photo(path)
                fits = fit_photo_faces(photo, landmarker, options)
                row["num_detected"] = len(fits)
                rejected, records = [], []
                for fit in fits:
                    if not isinstance(fit, FaceFit):
                        rejected.append({"face_index": fit.face_index, "reason": fit.reason,
                                         "message": f"{shown}: {printable(fit.message)}",
                                         "box": None if fit.box is None else [round(v, 2) for v in fit.box]})
                        continue
                    fid = face_id(path, sha, fit.face_index)
                    crop_rel = write_side_photo(out, fid, fit.crop_display)
                    record = face_record(fit, photo, fid, options, source_path=shown,
                                         photo_rel=crop_rel,
                                         gt_probe_rel=_gt_probe(out, fid, path, gt_dir, options.grid))
                    if overlays:
                        record.meta["overlay_path"] = _overlay(out, fid, fit, options)
                    records.append((record, sum(fit.timings.values())))
                if overlays and fits:
                    row["overlay_path"] = _photo_overlay(out, path, sha, photo, fits, records)
                # a photo's records are written together, after all its faces succeeded
                for record, seconds in records:
                    writer.write(record)
                    row["face_ids"].append(record.face_id)
                    per_face_s.append(seconds)
                row["rejected_json"] = json.dumps(rejected)
                if row["face_ids"]:
                    row["status"], row["message"] = "ok", f"{shown}: {len(row['face_ids'])} face(s)"
                    if rejected:
                        row["message"] += f", {len(rejected)} refused"
                    if any(r.meta.get("greyscale") for r, _ in records):
                        row["message"] += "; greyscale: it says nothing about the light's colour"
                elif fits:
                    row["status"] = "rejected"
                    row["message"] = "; ".join(r["message"] for r in rejected)
                else:
                    row["status"], row["message"] = "no_face", f"{shown}: no face detected"
            except PhotoError as exc:
                row["status"], row["message"] = "error", printable(str(exc))
            except Exception as exc:  # noqa: BLE001 - one bad photo must not stop the batch
                row["status"] = "error"
                row["message"] = printable(f"{shown}: {type(exc).__name__}: {exc}")
            if shown != str(path):
                row["message"] += ("; the file name is not valid UTF-8: recorded with its "
                                   "undecodable bytes as \\xNN")
            row["seconds"] = round(time.perf_counter() - t0, 4)
            status.append(row)
            counts[row["status"]] += 1
            n_records += len(row["face_ids"])
            if row["status"] != "ok":
                bar.note(f"{row['status']}: {row['message']}")
            bar.advance(1)
    return {
        "out": str(out),
        "photos": len(files),
        "records": n_records,
        "status": counts,
        "status_table": str(out / STATUS_TABLE),
        "seconds": round(time.perf_counter() - t_start, 3),
        "fit_seconds_per_face_median": round(float(np.median(per_face_s)), 3) if per_face_s else None,
        "options": options.to_meta(),
    }
