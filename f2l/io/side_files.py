"""A shard's side files: ground-truth probes (``probes/<face_id>.exr``, float32 lat-long) and photo
previews (``photos/<face_id>.png``) beside the Parquet records of :mod:`f2l.io.shards`, written
atomically and named by the record's ``face_id`` (checked against the ``face_record`` schema)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from f2l.io.schema import SchemaError
from f2l.io.shards import FaceRecord, _face_id_pattern


def _check_face_id(face_id: str) -> None:
    if not isinstance(face_id, str) or not _face_id_pattern().match(face_id):
        raise SchemaError(f"face id {face_id!r} is not file-name safe "
                          f"(pattern {_face_id_pattern().pattern})")


def _atomic_side_write(out_dir: Path, rel: str, write) -> str:
    final = Path(out_dir) / rel
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(f".{final.stem}.{os.getpid()}.tmp{final.suffix}")
    try:
        write(tmp)
        os.replace(tmp, final)
    finally:
        tmp.unlink(missing_ok=True)
    return rel


def write_side_probe(out_dir: str | os.PathLike, face_id: str, probe: np.ndarray) -> str:
    """Write a float32 (H, W, 3) probe to ``out_dir/probes/<face_id>.exr``; returns the relative path."""
    from f2l.io.exr import write_exr

    _check_face_id(face_id)
    probe = np.asarray(probe, dtype=np.float32)
    if probe.ndim != 3 or probe.shape[2] != 3:
        raise ValueError(f"face {face_id!r}: probe must be (H, W, 3), got {probe.shape}")
    if not np.isfinite(probe).all():
        raise ValueError(f"face {face_id!r}: probe has non-finite values")
    return _atomic_side_write(Path(out_dir), f"probes/{face_id}.exr",
                              lambda p: write_exr(p, probe))


def write_side_photo(out_dir: str | os.PathLike, face_id: str, image: np.ndarray,
                     fmt: str = "png", exif=None) -> str:
    """Write a uint8 (H, W, 3) display image to ``out_dir/photos/<face_id>.<fmt>``; relative path.

    ``exif`` (a ``PIL.Image.Exif``) is embedded when given (PNG eXIf chunk or JPEG APP1)."""
    from PIL import Image

    _check_face_id(face_id)
    fmt = fmt.lower()
    if fmt not in ("png", "jpg", "jpeg"):
        raise ValueError(f"photo format must be png or jpg, got {fmt!r}")
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"face {face_id!r}: photo must be uint8 (H, W, 3), got "
                         f"{image.dtype} {image.shape}")
    pil_fmt = "PNG" if fmt == "png" else "JPEG"
    extra = {} if exif is None else {"exif": exif}
    return _atomic_side_write(Path(out_dir), f"photos/{face_id}.{fmt}",
                              lambda p: Image.fromarray(image).save(p, format=pil_fmt, **extra))


def load_gt_probe(shard_dir: str | os.PathLike, record: FaceRecord) -> np.ndarray | None:
    """The ground-truth probe (H, W, 3) float32 of ``record``, or None when it has none."""
    if record.gt_probe_path is None:
        return None
    from f2l.io.exr import read_exr

    path = Path(shard_dir) / record.gt_probe_path
    if not path.is_file():
        raise FileNotFoundError(f"face {record.face_id!r}: ground-truth probe {path} not found")
    return np.asarray(read_exr(path), dtype=np.float32)
