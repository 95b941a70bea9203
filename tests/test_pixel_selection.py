"""Which pixels the estimator reads: highlight-aware selection, and clipped channels as bounds."""

import numpy as np

from f2l.estimate.observation import highlight_pixels


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


def _sunny_face_with_clipping(face, grid, exposure):
    """The fixture face's exact shading (noise-free) exposed so its brightest pixels clip at 1."""
    from f2l.estimate import FaceObservation
    from f2l.synth.skies import clear_sky
    from f2l.transport import Transport

    probe = clear_sky(grid, np.radians(40.0), np.radians(60.0))
    albedo = np.array([0.55, 0.38, 0.30])
    shading = albedo * Transport(face.visibility_bits, face.normals.astype(np.float64), grid).matmul(
        probe.reshape(-1, 3).astype(np.float64))
    shading = shading / np.percentile(shading.max(1), 100.0 - exposure)
    clipped = shading.max(1) >= 1.0
    observed = np.minimum(shading, 1.0)
    return FaceObservation(face.normals, observed, ~clipped, face.visibility_bits, grid), clipped


def test_clipped_channels_are_censored_and_the_others_kept(face_geometry, small_grid):
    """Sun models read clipped pixels: a clipped channel only as a lower bound (no cost when the
    prediction is above it), an unclipped channel of the same pixel as an ordinary observation."""
    import torch

    from f2l.estimate import EstimatorConfig
    from f2l.estimate.problem import FaceProblem
    from f2l.models import load_model

    obs, clipped = _sunny_face_with_clipping(face_geometry, small_grid, exposure=15.0)
    assert 0 < clipped.sum() < len(clipped)
    model = load_model("sunsky", small_grid)
    prob = FaceProblem(obs, model, EstimatorConfig())
    assert prob.clip_hybrid is not None and prob.clip_bound.any() and not prob.clip_bound.all()
    assert not FaceProblem(obs, model, EstimatorConfig(clipped_bounds=False)).clip_hybrid
    n = prob.clip_target.shape[0]
    dtype = prob.clip_target.dtype
    zero_sky = (torch.zeros(1, prob.L_sky, 3, dtype=dtype), None, torch.zeros(1, 3, dtype=dtype))
    # no light: every censored channel is short by its recorded value, every other one too
    cost_dark = float(prob.clipped_term(zero_sky, torch.ones(1, 3, dtype=dtype), torch.zeros(1, dtype=dtype)))
    np.testing.assert_allclose(cost_dark, float(prob.clip_target.sum()), rtol=1e-4)
    # a bright uniform sky: censored channels cost nothing, the others cost |prediction - observed|
    bright = (torch.full((1, prob.L_sky, 3), 50.0, dtype=dtype), None, torch.zeros(1, 3, dtype=dtype))
    cost = float(prob.clipped_term(bright, torch.ones(1, 3, dtype=dtype), torch.zeros(1, dtype=dtype)))
    tl = prob.clip_hybrid.apply(bright[0], None)[0]
    seen = prob.apparent(torch.ones(3, dtype=dtype))  # albedo 1 plus the skin's gloss (skin_gloss)
    expected = float(((seen * tl - prob.clip_target).abs() * ~prob.clip_bound).sum())
    np.testing.assert_allclose(cost, expected, rtol=1e-4)
    assert n <= len(clipped)
