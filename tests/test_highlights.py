"""Highlight-aware pixel selection (EstimatorConfig.highlight_mad): the dichromatic rule."""

import numpy as np

from f2l.estimate.estimator import highlight_pixels


def test_desaturated_bright_pixels_are_flagged_and_diffuse_ones_kept():
    rng = np.random.default_rng(0)
    skin = np.array([0.55, 0.38, 0.30])
    shading = rng.uniform(0.2, 1.0, 500)[:, None]
    rgb = skin * shading * rng.normal(1.0, 0.02, (500, 3))  # diffuse: one chromaticity, any brightness
    highlight = np.arange(40)
    rgb[highlight] = skin * 0.9 + 0.25  # a grey specular lobe on top of bright skin
    flagged = highlight_pixels(rgb, 1.0)
    assert flagged[highlight].all()
    assert flagged[40:].mean() < 0.1  # diffuse pixels keep their place
    assert highlight_pixels(rgb[40:], 3.0).mean() < 0.01  # a strict threshold flags (almost) none


def test_dark_desaturated_pixels_are_not_highlights():
    """A shadow lit by the blue sky is desaturated too, but darker than the median: kept."""
    skin = np.array([0.55, 0.38, 0.30])
    rgb = np.vstack([np.tile(skin, (300, 1)) * np.linspace(0.5, 1.0, 300)[:, None],
                     np.tile([0.05, 0.05, 0.06], (50, 1))])
    assert not highlight_pixels(rgb, 1.0)[300:].any()
