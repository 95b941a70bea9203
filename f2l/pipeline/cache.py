"""The build cache and the build lock.

Cache layout: ``WORK/cache/<stage>/<key>/`` holds one stage output (files plus ``done``). The key
is the SHA-256 of the canonical JSON of ``{"stage", "stage_version", "f2l", "inputs",
"params"}`` (:func:`stage_key`): inputs are file SHA-256s from ``captures.parquet`` or the keys
of upstream entries, so a key changes exactly when something the output depends on changes.

Writing an entry (:meth:`Cache.write`): the outputs go into ``WORK/cache/<stage>/.tmp-<key>-<pid>``,
then ``done`` (the entry's JSON result) is written and fsynced last, then the folder is renamed to
``<key>``. A reader trusts an entry only when ``<key>/done`` exists, so a build killed at any point
leaves either a complete entry or a temporary folder, which the next build removes
(:meth:`Cache.sweep`, called under the lock). Two writers of one key (a Ray task of a killed
build can outlive its driver by a moment) never delete each other's work: the first complete
entry stays, and the later writer returns its result.

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


TOKEN_FILE = ".build-token"


class StaleBuild(RuntimeError):
    """A cache writer of an earlier (killed) build tried to publish after a new build began."""


def new_build_token(work: str | os.PathLike) -> str:
    """Write a fresh ``WORK/.build-token`` (atomically) and return it; called under the lock,
    before the sweep."""
    import uuid

    token = uuid.uuid4().hex
    path = Path(work) / TOKEN_FILE
    tmp = path.with_name(f"{TOKEN_FILE}.{os.getpid()}")
    tmp.write_text(token)
    os.replace(tmp, path)
    return token


def read_build_token(work: str | os.PathLike) -> str | None:
    try:
        return (Path(work) / TOKEN_FILE).read_text().strip()
    except OSError:
        return None


class Cache:
    """Content-keyed stage outputs under ``WORK/cache``."""

    def __init__(self, work: str | os.PathLike, token: str | None = None):
        """``token``: the build this cache writer belongs to (:func:`new_build_token`); an entry
        is then published only while ``WORK/.build-token`` still holds it, so a Ray task that
        outlives its killed build publishes nothing once a new build has begun."""
        self.root = Path(work) / "cache"
        self.token = token

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
            if self.token is not None and read_build_token(self.root.parent) != self.token:
                raise StaleBuild(f"{self.root.parent}: a newer build owns this work folder; "
                                 f"{stage} entry {key[:12]} not published")
            existing = self._publish(stage, key, tmp)
            if existing is not None:
                return existing
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return result

    def _publish(self, stage: str, key: str, tmp: Path) -> dict | None:
        """Rename ``tmp`` to the entry; None when it is published, or the result of a complete
        entry another writer of the same key published first (kept: content-keyed, so the same,
        and someone may be reading it; ``tmp`` is removed). Only an entry without ``done`` is moved
        aside and removed (a complete one never lacks it: ``done`` is written before the rename)."""
        final = self.entry(stage, key)
        for _ in range(5):
            existing = self.lookup(stage, key)
            if existing is not None:
                shutil.rmtree(tmp, ignore_errors=True)
                return existing
            try:
                os.rename(tmp, final)
                _fsync_dir(final.parent)
                return None
            except OSError:  # the entry exists: published meanwhile (next lookup), or stale
                if self.lookup(stage, key) is not None:
                    continue
                stale = final.parent / f"{TMP_PREFIX}stale-{key}-{os.getpid()}"
                try:
                    os.rename(final, stale)
                except OSError:
                    continue
                shutil.rmtree(stale, ignore_errors=True)
        raise OSError(f"{final}: could not publish the cache entry")

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
