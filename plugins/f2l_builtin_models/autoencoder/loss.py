"""The autoencoder's training loss: solid-angle-weighted L1 / L2 of encoded skies (32 x 128)."""

from __future__ import annotations

import torch

from f2l_builtin_models.autoencoder.encoding import sky_solid_angles


def loss_weights() -> torch.Tensor:
    """(1, 1, 32, 128) dOmega / (3 sum dOmega): the L1 loss's texel weights (sum over c = 1)."""
    sa = sky_solid_angles()
    return torch.as_tensor(sa / (3.0 * sa.sum()), dtype=torch.float32)[None, None]


def weighted_l1(pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """(B,) solid-angle-weighted mean absolute error of encoded skies (B, 3, 32, 128)."""
    return ((pred - target).abs() * weights).sum((1, 2, 3))


def weighted_l2(pred: torch.Tensor, target: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """(B,) solid-angle-weighted mean squared error of encoded skies (B, 3, 32, 128)."""
    d = pred - target
    return (d * d * weights).sum((1, 2, 3))
