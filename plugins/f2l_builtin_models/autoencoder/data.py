"""Sky probes for the autoencoder: find, read, sun-centre, encode, and cache them on disk.

``f2l ae train`` streams a folder of HDR sky probes: lat-long ``.exr`` (float, any channel type
OpenEXR reads) or Radiance ``.hdr`` (RGBE, read by OpenCV), full sphere (W = 2H) or sky
hemisphere (W = 4H), any resolution. Each is sun-centred and area-resampled to the 32 x 128 sky
and encoded (:mod:`f2l_builtin_models.autoencoder.encoding`) one file at a time into a memory-mapped cache, so memory
stays bounded for any corpus size (12,000 probes of the Laval HDR sky database: 600 MB on disk).

Cache: ``<dir>/skies.npy`` ((n, 3, 32, 128) float32 encoded skies), ``<dir>/info.json`` (per file:
path, size, mtime, log exposure, sun azimuth, status and message). It is reused when the file
list, sizes and modification times are unchanged. A file that cannot be read or is not a sky
probe is recorded with its reason and skipped; the others go on.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from f2l_builtin_models.autoencoder.encoding import SkyFormatError, centred_sky, encode, full_sphere
from f2l_builtin_models.autoencoder.model import SKY_SHAPE
from f2l.io.atomic import write_text_atomic

SKY_EXTENSIONS = (".exr", ".hdr")
CACHE_VERSION = 2  # 2: cube-root encoding


def list_sky_files(folder: str | Path) -> list[Path]:
    """Sky probe files (``.exr``, ``.hdr``, any case) under ``folder`` (recursively, sorted), or
    ``[folder]`` when it is one such file."""
    p = Path(folder)
    if p.is_file():
        return [p]
    return sorted(f for f in p.rglob("*") if f.is_file() and f.suffix.lower() in SKY_EXTENSIONS)


def read_sky_file(path: str | Path) -> np.ndarray:
    """(H, W, 3) float32 linear RGB of an EXR or Radiance HDR; ValueError naming the file."""
    from f2l.io.probe_io import read_hdr_image

    return read_hdr_image(path)


def prepare_sky(path: str | Path, azimuth: float | None = None) -> tuple[np.ndarray, float, float]:
    """(encoded sky (3, 32, 128) float32, log exposure, sun azimuth rad) of one probe file."""
    name = str(path)
    probe = full_sphere(read_sky_file(path), name)
    sky, az = centred_sky(probe, azimuth)
    e, log_s = encode(sky, name)
    return e, log_s, az


@dataclass
class SkyCache:
    """Encoded skies of a list of files (module docstring); ``ok`` indexes the usable rows."""

    folder: Path
    files: list[dict]
    skies: np.ndarray  # (n, 3, 32, 128) float32 memmap, rows of failed files are zero
    key: dict  # cache version, fingerprint of the files, count

    @property
    def ok(self) -> np.ndarray:
        return np.array([i for i, f in enumerate(self.files) if f["status"] == "ok"], dtype=np.int64)

    @property
    def log_exposure(self) -> np.ndarray:
        return np.array([f.get("log_exposure") or 0.0 for f in self.files])

    @property
    def errors(self) -> list[str]:
        return [f["message"] for f in self.files if f["status"] != "ok"]


def _stat(path: Path) -> dict:
    st = path.stat()
    return {"path": str(path), "size": int(st.st_size), "mtime_ns": int(st.st_mtime_ns)}


def fingerprint(files: list[Path]) -> str:
    """SHA-256 (16 hex) over the files' paths, sizes and modification times."""
    h = hashlib.sha256()
    for f in files:
        s = _stat(f)
        h.update(f"{s['path']}\0{s['size']}\0{s['mtime_ns']}\n".encode())
    return h.hexdigest()[:16]


def build_cache(files: list[Path], folder: str | Path, progress: Callable | None = None) -> SkyCache:
    """Encode ``files`` into ``folder`` (reusing a matching cache); see the module docstring."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    info_path, data_path = folder / "info.json", folder / "skies.npy"
    key = {"version": CACHE_VERSION, "fingerprint": fingerprint(files), "n": len(files)}
    if info_path.exists() and data_path.exists():
        try:
            info = json.loads(info_path.read_text())
            if info.get("key") == key:
                skies = np.load(data_path, mmap_mode="r")
                if skies.shape == (len(files), 3, *SKY_SHAPE):
                    if progress:
                        progress(len(files))
                    return SkyCache(folder, info["files"], skies, key)
        except (OSError, ValueError):
            pass
    tmp = folder / "skies.npy.tmp"
    skies = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float32, shape=(len(files), 3, *SKY_SHAPE))
    records = []
    for i, path in enumerate(files):
        rec = {**_stat(path), "status": "ok", "message": "", "log_exposure": None, "sun_azimuth_rad": None}
        try:
            e, log_s, az = prepare_sky(path)
        except (SkyFormatError, ValueError, OSError) as exc:
            msg = str(exc)
            rec.update(status="error", message=msg if str(path) in msg else f"{path}: {msg}")
        else:
            skies[i] = e
            rec.update(log_exposure=log_s, sun_azimuth_rad=az)
        records.append(rec)
        if progress:
            progress(1)
    skies.flush()
    del skies
    tmp.replace(data_path)
    write_text_atomic(info_path, json.dumps({"key": key, "files": records}) + "\n")
    return SkyCache(folder, records, np.load(data_path, mmap_mode="r"), key)


def holdout_mask(files: list[dict], fraction: float, seed: int) -> np.ndarray:
    """(n,) bool: a deterministic ``fraction`` of the files (by a hash of the file name and the
    seed, so adding files never moves an existing one between the splits) held out."""
    if fraction <= 0:
        return np.zeros(len(files), dtype=bool)
    u = np.array([int(hashlib.sha256(f"{seed}:{Path(f['path']).name}".encode()).hexdigest()[:12], 16) / 16**12
                  for f in files])
    return u < fraction
