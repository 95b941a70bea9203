"""Catch what native code writes to file descriptor 2 (C++ libraries print there directly,
bypassing ``sys.stderr`` and Python's logging) while a block runs, and hand it over line by line.

Used to keep third-party start-up notices (LiteRT's "INFO: Created TensorFlow Lite XNNPACK
delegate", Warp's "no CUDA driver") out of the terminal: the caller routes each line to the debug
log (``f2l --debug-log``) or passes it on.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from typing import Callable, Iterator

__all__ = ["native_stderr_lines"]


@contextlib.contextmanager
def native_stderr_lines(handle: Callable[[str, bool], None]) -> Iterator[None]:
    """Run the block with fd 2 redirected to a temporary file; afterwards call
    ``handle(line, failed)`` for each non-empty line written meanwhile (``failed``: the block
    raised). Without a usable fd 2 (embedded interpreters) the block runs unchanged."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):
        yield
        return
    failed = False
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield
        except BaseException:
            failed = True
            raise
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            for line in sink.read().decode("utf-8", "replace").splitlines():
                if line.strip():
                    handle(line, failed)
