"""pyarrow without pandas, for a short process that never uses pandas.

pyarrow imports pandas (0.25–0.4 s on 2 cores) on its first ``pa.array`` and its first
``Array.to_numpy(zero_copy_only=False)``, whatever they convert, only to ask whether the values
are pandas objects or to look up pandas' types. f2l itself never imports pandas to fit faces, so
in the forked face fit of ``f2l estimate`` (:mod:`f2l.io.forked`) :func:`hide_pandas` makes
``import pandas`` fail for the rest of the process: pyarrow then converts lists and arrays
without it, to the same values (pyarrow's own fallback when pandas is not installed). For that
child process only, never for a library call: a later ``import pandas`` in the same process
raises ImportError.
"""

from __future__ import annotations

import importlib.abc
import sys


class _HidePandas(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "pandas" or name.startswith("pandas."):
            raise ImportError(f"{name} is hidden in this process (f2l.io.pyarrow_pandas.hide_pandas)")
        return None


def hide_pandas() -> bool:
    """Make ``import pandas`` fail in this process from now on; False (and nothing done) when
    pandas is already imported, True otherwise."""
    if "pandas" in sys.modules:
        return False
    if not any(isinstance(f, _HidePandas) for f in sys.meta_path):
        sys.meta_path.insert(0, _HidePandas())
    return True
