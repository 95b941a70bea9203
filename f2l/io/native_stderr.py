"""Catch what native code writes to file descriptors 1 and 2 (C++ libraries print there directly,
bypassing ``sys.stdout``/``sys.stderr`` and Python's logging) while a block runs, and hand it over
line by line.

Used to keep third-party notices out of the terminal and out of ``--json`` output: LiteRT's
"INFO: Created TensorFlow Lite XNNPACK delegate", Warp's "no CUDA driver", OpenEXR's "Warning:
Exception raised reading pixel data for part 0 - ..." (printed to stdout, without a file name).
The caller routes each line to the debug log (``f2l --debug-log``) or passes it on.

The redirection is process-wide (a file descriptor is), so it is shared and reference-counted:
blocks that overlap, in one thread (nested) or several (a thread pool decoding EXRs), redirect a
descriptor once and restore it when the last of them ends; no block can leave fd 1 or 2 pointing
at another block's temporary file. Each block hands over the complete lines written while it
ran; with overlapping blocks a line may be handed to either of them.

Bindings also print through Python (OpenEXR's pybind11 module calls ``print``, i.e.
``sys.stdout``), which a replaced ``sys.stdout`` (a test runner's capture, an embedding host) would
take past the descriptor: while a block runs, ``sys.stdout``/``sys.stderr`` are swapped for
writers into the same temporary files.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import sys
import tempfile
import threading
from typing import Callable, Iterator

__all__ = ["native_stderr_lines", "native_output_lines", "native_output_to_log"]

_LOCK = threading.Lock()


class _Redirect:
    """One descriptor's shared redirection: the saved original, the sink, the read position."""

    def __init__(self, fd: int):
        self.fd = fd
        self.depth = 0
        self.saved: int | None = None
        self.saved_stream = None
        self.sink = None
        self.read_at = 0
        self.partial = b""

    def enter(self) -> bool:
        if self.depth == 0:
            _flush(self.fd)
            try:
                saved = os.dup(self.fd)
            except OSError:
                return False
            sink = tempfile.TemporaryFile()
            os.dup2(sink.fileno(), self.fd)
            self.saved, self.sink, self.read_at, self.partial = saved, sink, 0, b""
            if self.fd in (1, 2):
                name = "stdout" if self.fd == 1 else "stderr"
                self.saved_stream = getattr(sys, name)
                setattr(sys, name, _StreamSink(sink.fileno(), self.saved_stream))
        self.depth += 1
        return True

    def take(self, final: bool) -> list[str]:
        """Complete lines written since the last take (all of them when ``final``)."""
        size = os.fstat(self.sink.fileno()).st_size
        data = self.partial + (os.pread(self.sink.fileno(), size - self.read_at, self.read_at)
                               if size > self.read_at else b"")
        self.read_at = size
        if final:
            self.partial = b""
        else:
            cut = data.rfind(b"\n") + 1
            data, self.partial = data[:cut], data[cut:]
        return data.decode("utf-8", "replace").splitlines()

    def leave(self) -> list[str]:
        self.depth -= 1
        if self.depth > 0:
            _flush_native()
            return self.take(final=False)
        _flush(self.fd)
        if self.fd in (1, 2):
            setattr(sys, "stdout" if self.fd == 1 else "stderr", self.saved_stream)
            self.saved_stream = None
        try:
            os.dup2(self.saved, self.fd)
        finally:
            os.close(self.saved)
            lines = self.take(final=True)
            self.sink.close()
            self.saved = self.sink = None
        return lines


class _StreamSink:
    """Stands in for ``sys.stdout``/``sys.stderr`` during a block: text goes to the sink file."""

    def __init__(self, fd: int, original):
        self._fd = fd
        self.encoding = getattr(original, "encoding", None) or "utf-8"
        self.errors = "replace"

    def write(self, text: str) -> int:
        os.write(self._fd, str(text).encode("utf-8", "replace"))
        return len(text)

    def writelines(self, lines) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return False

    def fileno(self) -> int:
        return self._fd


_REDIRECTS = {1: _Redirect(1), 2: _Redirect(2)}


def _flush_native() -> None:
    """Flush C stdio buffers (a C++ library's ``std::cout``/``printf`` output to a file or pipe is
    buffered: unflushed, it would reach the real descriptor after the block ends)."""
    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError, TypeError):  # no C library handle on this platform
        pass


def _flush(fd: int) -> None:
    stream = sys.stdout if fd == 1 else sys.stderr
    try:
        if stream is not None:
            stream.flush()
    except (OSError, ValueError):
        pass
    _flush_native()


@contextlib.contextmanager
def native_output_lines(handle: Callable[[str, bool], None], fds: tuple[int, ...] = (1, 2)) -> Iterator[None]:
    """Run the block with the descriptors ``fds`` (1: stdout, 2: stderr) redirected to temporary
    files; afterwards call ``handle(line, failed)`` for each non-empty line written meanwhile
    (``failed``: the block raised). A descriptor that cannot be duplicated (embedded
    interpreters) is left as it is."""
    entered: list[_Redirect] = []
    with _LOCK:
        for fd in fds:
            red = _REDIRECTS.get(fd) or _REDIRECTS.setdefault(fd, _Redirect(fd))
            if red.enter():
                entered.append(red)
    failed = False
    try:
        yield
    except BaseException:
        failed = True
        raise
    finally:
        lines: list[str] = []
        with _LOCK:
            for red in entered:
                lines += red.leave()
        for line in lines:
            if line.strip():
                handle(line, failed)


def native_stderr_lines(handle: Callable[[str, bool], None]) -> Iterator[None]:
    """:func:`native_output_lines` for fd 2 only (stderr)."""
    return native_output_lines(handle, fds=(2,))


def native_output_to_log(logger: logging.Logger, context: str = ""):
    """:func:`native_output_lines` for fd 1 and 2, each line logged at DEBUG level on ``logger``
    (``f2l --debug-log``), prefixed with ``context`` (e.g. the file being read)."""
    prefix = f"{context}: " if context else ""

    def handle(line: str, failed: bool) -> None:
        logger.debug("%snative output%s: %s", prefix, " (failed)" if failed else "", line)

    return native_output_lines(handle)
