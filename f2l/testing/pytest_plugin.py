"""pytest fixtures for plugin authors (loaded through f2l's ``pytest11`` entry point).

- ``f2l_check_model(name, grid=(64, 128))``: load through the registry, capabilities checked;
- ``f2l_round_trip(name_or_model, n=3, seed=0, ...)``: :func:`f2l.testing.round_trip`;
- ``f2l_synthetic_faces(n=3, seed=0, ...)``: :func:`f2l.testing.synthetic_faces`.

Each fixture returns the function, so a test chooses its sizes. Nothing heavy is imported until
a fixture is used.
"""

from __future__ import annotations

import pytest


@pytest.fixture
def f2l_check_model():
    from f2l.testing import check_model

    return check_model


@pytest.fixture
def f2l_round_trip():
    from f2l.testing import round_trip

    return round_trip


@pytest.fixture
def f2l_synthetic_faces():
    from f2l.testing import synthetic_faces

    return synthetic_faces
