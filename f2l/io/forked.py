"""One call in a forked child process, so that this process can do other work meanwhile.

``f2l estimate photo.jpg`` fits the photo's faces (numpy, OpenCV, scipy, Embree: no torch) while
this process imports torch and the estimator (about a second that otherwise comes first). A
thread cannot overlap them: both hold the GIL most of the time. :func:`start` forks, the child
runs ``fn()`` and sends back its result (or its exception) pickled through a pipe, then exits
without running the parent's exit handlers; :meth:`Forked.result` waits for it.

Fork is only safe before a library starts threads of its own that a fork would leave half-held
(torch's and OpenMP's pools: :mod:`f2l.io.executor` spawns for that reason). :func:`start` forks
only on Linux, while torch is not imported, this process runs no other Python thread, standard
output and error are file descriptors (a child's progress lines reach the terminal) and
``F2L_NO_FORK`` is not set; otherwise ``fn()`` runs here, at once, and the result is the same.
"""

from __future__ import annotations

import os
import pickle
import signal
import sys
import threading
import traceback
from collections.abc import Callable
from typing import Any

NO_FORK_ENV = "F2L_NO_FORK"
"""Set (to anything but empty) to run :func:`start`'s calls in this process."""


def _streams_are_files() -> bool:
    """Standard output and error write to file descriptors, so a child's lines reach the same place
    (not, e.g., a test runner's in-memory capture)."""
    try:
        return all(isinstance(stream.fileno(), int) for stream in (sys.stdout, sys.stderr))
    except (AttributeError, OSError, ValueError):  # io.UnsupportedOperation is an OSError
        return False


def can_fork() -> bool:
    """True where :func:`start` forks (module docstring)."""
    return (sys.platform.startswith("linux") and hasattr(os, "fork") and not os.environ.get(NO_FORK_ENV)
            and "torch" not in sys.modules and threading.active_count() == 1 and _streams_are_files())


class Forked:
    """A call started by :func:`start`: :meth:`result` returns its value or raises its exception."""

    def __init__(self, pid: int | None, read_fd: int | None, outcome: tuple | None = None) -> None:
        self.pid, self._fd, self._outcome = pid, read_fd, outcome

    @property
    def forked(self) -> bool:
        return self.pid is not None

    def result(self) -> Any:
        """Wait for the call; its return value, or its exception raised here (an exception from
        the child carries the child's traceback as a note)."""
        if self._outcome is None:
            self._outcome = self._collect()
        ok, value = self._outcome
        if ok:
            return value
        raise value

    def cancel(self) -> None:
        """Stop a child still running (SIGTERM) and reap it; nothing when done or not forked."""
        if self.pid is not None and self._outcome is None:
            try:
                os.kill(self.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
            self._outcome = (False, RuntimeError("cancelled"))
            self._reap()

    def _collect(self) -> tuple:
        chunks = []
        with os.fdopen(self._fd, "rb") as pipe:
            while chunk := pipe.read(1 << 20):
                chunks.append(chunk)
        self._fd = None
        status = self._reap()
        if not chunks:
            return False, RuntimeError(f"the forked child {self.pid} ended without a result "
                                       f"(wait status {status})")
        return pickle.loads(b"".join(chunks))

    def _reap(self) -> int:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        _, status = os.waitpid(self.pid, 0)
        return status


def _portable(exc: BaseException) -> BaseException:
    """``exc`` if it pickles and unpickles, else a RuntimeError with its type and message; the
    traceback rides along as a note either way."""
    note = "in the forked child:\n" + "".join(traceback.format_exception(exc)).rstrip()
    try:
        out = pickle.loads(pickle.dumps(exc))
    except Exception:  # noqa: BLE001 - any exception type may refuse to pickle
        out = RuntimeError(f"{type(exc).__name__}: {exc}")
    out.add_note(note)
    return out


def start(fn: Callable[[], Any], *, child_setup: Callable[[], Any] | None = None) -> Forked:
    """Run ``fn()`` in a forked child (or here, where :func:`can_fork` says no) and return its
    :class:`Forked`; ``fn``'s result must pickle. ``child_setup()`` runs first in a child only
    (e.g. :func:`f2l.io.hidden_modules.hide`). Standard output and error are flushed first
    so that nothing buffered is written twice."""
    if not can_fork():
        try:
            return Forked(None, None, (True, fn()))
        except Exception as exc:  # noqa: BLE001 - raised by result(), as from a child
            return Forked(None, None, (False, exc))
    sys.stdout.flush()
    sys.stderr.flush()
    read_fd, write_fd = os.pipe()
    pid = os.fork()
    if pid:
        os.close(write_fd)
        return Forked(pid, read_fd)
    code = 0
    try:  # the child: never returns into the parent's code
        os.close(read_fd)
        try:
            if child_setup is not None:
                child_setup()
            payload = pickle.dumps((True, fn()))
        except BaseException as exc:  # noqa: BLE001 - KeyboardInterrupt too: the parent re-raises it
            payload = pickle.dumps((False, _portable(exc)))
        with os.fdopen(write_fd, "wb") as pipe:
            pipe.write(payload)
        sys.stdout.flush()
        sys.stderr.flush()
    except BaseException:  # noqa: BLE001 - e.g. the parent went away: the pipe is broken
        code = 1
    finally:
        os._exit(code)
