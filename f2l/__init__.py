"""f2l — faces to light: HDR outdoor light probes from photographs of faces.

Implements Calian et al., "From Faces to Outdoor Light Probes" (Eurographics 2018).
Conventions (directions, probes, units) are documented in ``docs/conventions.md``.
"""

__version__ = "0.1.0"
