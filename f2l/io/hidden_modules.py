"""Modules a short process hides from itself: libraries import them eagerly for nothing it uses.

In the forked face fit of ``f2l estimate`` (:mod:`f2l.io.forked`), :data:`UNUSED_BY_THE_FIT`:

* pandas (0.25–0.4 s on 2 cores): pyarrow imports it on its first ``pa.array`` and its first
  ``Array.to_numpy(zero_copy_only=False)``, whatever they convert, only to ask whether the
  values are pandas objects or to look up pandas' types; f2l never imports it to fit faces.
* networkx (~0.1 s, half of trimesh's import): ``trimesh.graph`` imports it at import time,
  but prefers scipy for every graph routine and f2l's fit calls none of networkx's.

A hidden module raises ImportError from then on; pyarrow and trimesh then take the path they
take when it is not installed, to the same values (tests/test_cold_start.py compares Parquet
bytes; ``f2l estimate`` writes the same shards, estimates and probes). For such a process only,
never for a library call: a later ``import pandas`` in the same process fails.
"""

from __future__ import annotations

import importlib.abc
import sys

UNUSED_BY_THE_FIT = ("pandas", "networkx")
"""What the face fit's process hides (module docstring)."""


class _Hide(importlib.abc.MetaPathFinder):
    def __init__(self, names: tuple[str, ...]) -> None:
        self.names = names

    def find_spec(self, name, path=None, target=None):
        if name.split(".", 1)[0] in self.names:
            raise ImportError(f"{name} is hidden in this process (f2l.io.hidden_modules)")
        return None


def hide(names=UNUSED_BY_THE_FIT) -> tuple[str, ...]:
    """Make importing each of ``names`` (top-level packages) fail in this process from now on;
    returns those hidden (one already imported is left alone)."""
    names = tuple(n for n in names if n not in sys.modules)
    if names:
        sys.meta_path.insert(0, _Hide(names))
    return names
