"""Progress as a callback: the library reports, only the CLI draws (a tqdm bar, f2l.cli.progress).

A long-running function takes ``progress: Callable[[ProgressEvent], None] | None``; None (or
False, as older callers pass) reports nothing. It reports through a :class:`Progress`: one event
when it starts (``advance`` 0, the ``total`` known then), one per item finished, and one per
line worth showing (``message``, e.g. an input that failed), in the order they happen.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class ProgressEvent:
    """One step of a task: ``advance`` items just finished (``done`` so far of ``total``, None when
    unknown) of the task ``stage``, counted in ``unit``; ``message`` a line to show (or None)."""

    stage: str
    unit: str
    done: int
    total: int | None
    advance: int = 0
    message: str | None = None


ProgressCallback = Callable[[ProgressEvent], None]


class Progress:
    """Reports one task's progress to ``callback`` (nothing when it is None or False)."""

    def __init__(self, callback: ProgressCallback | None, stage: str, unit: str = "item",
                 total: int | None = None) -> None:
        if callback is not None and callback is not False and not callable(callback):
            raise TypeError(f"progress must be a callable taking a ProgressEvent, or None, got {callback!r}")
        self.callback = callback if callable(callback) else None
        self.stage, self.unit, self.total, self.done = stage, unit, total, 0
        self._emit(0, None)

    def _emit(self, advance: int, message: str | None) -> None:
        if self.callback is not None:
            self.callback(ProgressEvent(self.stage, self.unit, self.done, self.total, advance, message))

    def advance(self, n: int = 1) -> None:
        """``n`` more items finished."""
        self.done += n
        self._emit(n, None)

    def note(self, message: str) -> None:
        """A line to show beside the progress (e.g. an input that failed, with its reason)."""
        self._emit(0, message)
