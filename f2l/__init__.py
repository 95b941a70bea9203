"""f2l — faces to light: HDR outdoor light probes from photographs of faces.

Implements Calian et al., "From Faces to Outdoor Light Probes" (Eurographics 2018).
Conventions (directions, probes, units) are documented in ``docs/conventions.md``.
"""

__version__ = "0.1.0"


def _at_exit() -> None:
    from f2l.io.probe_io import release_openimageio_references

    release_openimageio_references()


import atexit as _atexit  # noqa: E402

_atexit.register(_at_exit)
