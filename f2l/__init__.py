"""f2l — faces to light: HDR outdoor light probes from photographs of faces.

Implements Calian et al., "From Faces to Outdoor Light Probes" (Eurographics 2018).
Conventions (directions, probes, units) are documented in ``docs/conventions.md``.
"""

__version__ = "0.1.0"

def _fit_an_address_space_limit() -> None:
    """Under an address-space limit (``ulimit -v``), reserve address space only for what is used.

    Two allocators reserve far more than they use: Arrow's default (mimalloc) about 1.3 GB at the
    first Parquet read, whatever the data, and glibc's malloc 64 MB per thread arena (up to 8 per
    core). Under ``ulimit -v 2097152`` either alone fails a one-record build. So, only when a limit
    is set: Arrow gets the system allocator (read when pyarrow loads, hence here, before any f2l
    module imports it) and glibc at most two arenas (mallopt M_ARENA_MAX). A user's own
    ``ARROW_DEFAULT_MEMORY_POOL`` or ``MALLOC_ARENA_MAX`` wins."""
    import os
    import resource
    import sys

    if resource.getrlimit(resource.RLIMIT_AS)[0] == resource.RLIM_INFINITY:
        return
    os.environ.setdefault("ARROW_DEFAULT_MEMORY_POOL", "system")
    if sys.platform.startswith("linux") and "MALLOC_ARENA_MAX" not in os.environ:
        import ctypes

        try:
            ctypes.CDLL(None).mallopt(-8, 2)  # M_ARENA_MAX = -8 in glibc's malloc.h
        except (OSError, AttributeError):  # not glibc
            pass


_fit_an_address_space_limit()


_API = ("estimate_photo", "load_probe", "FaceEstimate")


def __getattr__(name: str):
    """The public Python API (:mod:`f2l.api`), loaded on first use so ``import f2l`` stays light."""
    if name in _API:
        import importlib

        # loaded when first asked for: the package root does not depend on f2l.api at import
        return getattr(importlib.import_module("f2l.api"), name)
    raise AttributeError(f"module 'f2l' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + list(_API))


def _at_exit() -> None:
    import sys

    if "colour.io.image" not in sys.modules:  # nothing to release: skip importing probe_io (numpy)
        return
    from f2l.io.probe_io import release_openimageio_references

    release_openimageio_references()


import atexit as _atexit  # noqa: E402

_atexit.register(_at_exit)
