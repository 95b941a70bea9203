"""The CLI's progress bars: the library reports :class:`f2l.io.progress.ProgressEvent`\\ s to a
callback, and only the CLI draws them (tqdm on stderr, one bar per stage, lines in between)."""

from __future__ import annotations

import sys
from contextlib import contextmanager

from f2l.io.progress import ProgressEvent


class Bars:
    """A progress callback drawing one tqdm bar per task (a new task, or stage, closes the last bar)."""

    def __init__(self, file=None) -> None:
        self.file = file if file is not None else sys.stderr
        self.bar, self.stage = None, None

    def __call__(self, event: ProgressEvent) -> None:
        from tqdm import tqdm

        starts = event.done == 0 and not event.advance and event.message is None  # Progress's first event
        if self.bar is None or event.stage != self.stage or starts:
            self.close()
            self.bar = tqdm(total=event.total, unit=event.unit, desc=event.stage or None,
                            dynamic_ncols=True, file=self.file, initial=event.done - event.advance)
            self.stage = event.stage
        if event.message:
            self.bar.write(event.message, file=self.file)
        if event.advance:
            self.bar.update(event.advance)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        self.bar, self.stage = None, None


@contextmanager
def progress_bars(enabled: bool = True):
    """A :class:`Bars` callback closed at the end, or None (no progress) when not ``enabled``:
    ``with progress_bars(not json_out) as progress: run(..., progress=progress)``."""
    if not enabled:
        yield None
        return
    bars = Bars()
    try:
        yield bars
    finally:
        bars.close()
