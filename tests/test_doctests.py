"""The doctest examples of f2l.lighting, f2l.metrics, f2l.capture.lens and f2l.capture.view_spec run
(issue 41, item 5).

Every module of those packages must carry at least one example, so this cannot pass vacuously.
"""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import numpy as np
import pytest

import f2l.lighting
import f2l.metrics


def _modules(package) -> list[str]:
    return [package.__name__] + [f"{package.__name__}.{m.name}" for m in pkgutil.iter_modules(package.__path__)]


MODULES = [*_modules(f2l.lighting), *_modules(f2l.metrics), "f2l.capture.lens", "f2l.capture.view_spec"]


@pytest.mark.parametrize("name", MODULES)
def test_doctests(name):
    module = importlib.import_module(name)
    # numpy's own defaults: another library imported earlier in the session (e.g. a renderer) may
    # have changed the global print options (legacy 1.13 pads signs with a space)
    with np.printoptions(legacy=False, sign="-", precision=8, floatmode="maxprec", suppress=False, linewidth=75,
                         threshold=1000, edgeitems=3):
        result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.attempted > 0, f"{name} has no doctest examples"
    assert result.failed == 0, f"{result.failed} of {result.attempted} doctest examples failed in {name}"
