"""The skin's glossy highlight of a whole probe, for ideal photos (``f2l eval geometry``).

The highlight itself (GGX microfacet reflection of sky, sun and ground with the mesh's visibility,
Smith shadowing, Schlick Fresnel, uncoloured by the skin) is :func:`f2l.synth.gloss.glossy_highlight`,
which the synthetic faces use too; its docstring holds the formula and the conventions (F0 = 0.08 ×
specular, α = roughness²). It is an evaluation tool here, not part of the estimator: it adds to an
ideal photo what the renderer's glossy skin adds to a photo, so that its share of the error can be
measured on its own.
"""

from __future__ import annotations

from dataclasses import dataclass

from f2l.synth.gloss import glossy_highlight

__all__ = ["Gloss", "glossy_highlight"]


@dataclass(frozen=True)
class Gloss:
    """A skin's gloss: principled roughness and F0, and its diffuse RGB albedo (which sets the
    photo's exposure relative to the uncoloured highlight)."""

    roughness: float
    f0: float
    albedo_rgb: tuple[float, float, float]
