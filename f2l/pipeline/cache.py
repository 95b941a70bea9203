"""The build cache and the build lock.

Cache layout: ``WORK/cache/<stage>/<key>/`` holds one stage output (files plus ``done``). The key
is the SHA-256 of the canonical JSON of ``{"stage", "stage_version", "f2l", "inputs",
"params"}`` (:func:`stage_key`): inputs are file SHA-256s from ``captures.parquet`` or the keys
of upstream entries, so a key changes exactly when something the output depends on changes.

Writing an entry (:meth:`Cache.write`): the outputs go into ``WORK/cache/<stage>/.tmp-<key>-<pid>``,
then ``done`` (the entry's JSON result) is written and fsynced last, then the folder is renamed to
``<key>``. A reader trusts an entry only when ``<key>/done`` exists, so a build killed at any point
leaves either a complete entry or a temporary folder, which the next build removes
(:meth:`Cache.sweep`, called under the lock).

The lock: ``fcntl.flock`` on ``WORK/.lock`` (non-blocking; the file holds the holder's pid) and on
the output folder itself, so two builds never write one work folder or one output. The kernel
drops both locks when the holder dies, even by SIGKILL.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import f2l
from f2l.pipeline.spec import canonical_json

DONE = "done"
TMP_PREFIX = ".tmp-"


class LockHeld(RuntimeError):
    """Another build holds the work folder's (or the output's) lock."""


def stage_key(stage: str, stage_version: int, inputs, params) -> str:
    """Hex SHA-256 naming one stage output (module docstring)."""
    doc = {"stage": stage, "stage_version": int(stage_version), "f2l": f2l.__version__,
           "inputs": inputs, "params": params}
    return hashlib.sha256(canonical_json(doc).encode("ascii")).hexdigest()


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class Cache:
    """Content-keyed stage outputs under ``WORK/cache``."""

    def __init__(self, work: str | os.PathLike):
        self.root = Path(work) / "cache"

    def entry(self, stage: str, key: str) -> Path:
        return self.root / stage / key

    def lookup(self, stage: str, key: str) -> dict | None:
        """The ``done`` result of a complete entry, or None (missing, unfinished or unreadable)."""
        try:
            return json.loads((self.entry(stage, key) / DONE).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None

    def write(self, stage: str, key: str, produce: Callable[[Path], dict]) -> dict:
        """Run ``produce(tmp_dir)`` (it writes the entry's files and returns its JSON result),
        then publish the entry atomically; returns the result."""
        final = self.entry(stage, key)
        tmp = final.parent / f"{TMP_PREFIX}{key}-{os.getpid()}"
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir(parents=True)
        try:
            result = produce(tmp)
            with open(tmp / DONE, "w", encoding="utf-8") as fh:
                fh.write(canonical_json(result))
                fh.flush()
                os.fsync(fh.fileno())
            if final.exists():  # an entry without `done` (the lookup failed): replace it
                shutil.rmtree(final)
            os.rename(tmp, final)
            _fsync_dir(final.parent)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return result

    def get_or_make(self, stage: str, key: str, produce: Callable[[Path], dict],
                    counts: dict) -> tuple[dict, Path]:
        """(result, entry folder): the cached entry, or a new one; ``counts`` gets ``reused`` or
        ``computed`` incremented."""
        result = self.lookup(stage, key)
        if result is None:
            result = self.write(stage, key, produce)
            counts["computed"] = counts.get("computed", 0) + 1
        else:
            counts["reused"] = counts.get("reused", 0) + 1
        return result, self.entry(stage, key)

    def sweep(self) -> int:
        """Remove temporary entry folders that killed builds left; returns how many."""
        removed = 0
        if not self.root.is_dir():
            return 0
        for stage_dir in sorted(p for p in self.root.iterdir() if p.is_dir()):
            for tmp in sorted(stage_dir.glob(f"{TMP_PREFIX}*")):
                shutil.rmtree(tmp, ignore_errors=True)
                removed += 1
        return removed


class BuildLock:
    """Exclusive, non-blocking locks on ``WORK/.lock`` and on the output folder (module docstring).

    Raises :class:`LockHeld` with ``another build holds WORK/.lock (pid N)`` when taken.
    """

    def __init__(self, work: str | os.PathLike, out: str | os.PathLike | None = None):
        self.path = Path(work) / ".lock"
        self.out = Path(out) if out is not None else None
        self._fds: list[int] = []

    def __enter__(self) -> BuildLock:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            pid = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EACCES):
                raise LockHeld(f"another build holds {self.path} (pid {pid})") from None
            raise
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode("ascii"), 0)
        self._fds.append(fd)
        if self.out is not None:
            self.out.mkdir(parents=True, exist_ok=True)
            out_fd = os.open(self.out, os.O_RDONLY)
            try:
                fcntl.flock(out_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                os.close(out_fd)
                self.__exit__(None, None, None)
                if exc.errno in (errno.EWOULDBLOCK, errno.EACCES):
                    raise LockHeld(f"another build is writing {self.out} (its lock is on the "
                                   f"folder itself)") from None
                raise
            self._fds.append(out_fd)
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        for fd in reversed(self._fds):
            try:
                fcntl.flock(fd, fcntl.LOCK_UN)
            finally:
                os.close(fd)
        self._fds.clear()
