"""The sky autoencoder network (Calian et al. 2018, Fig. 2), float32 torch.

Input and output: the HDR-encoded sky hemisphere e (B, 3, 32, 128) of :mod:`f2l_builtin_models.autoencoder.encoding`
(rows from the zenith to the horizon, the sun's azimuth at the centre: between columns 63 and 64).

Encoder (each stage: conv -> BatchNorm -> ReLU -> 2 x 2 max-pool)::

    3 -> 64 (5x5) @ 32x128 -> pool 16x64
      -> 96 (3x3) -> pool 8x32 -> 96 (3x3) -> pool 4x16 -> 64 (3x3) -> pool 2x8
      -> flatten (1024) -> linear -> z_shape (63)

Decoder, the mirror (each stage: nearest 2x upsampling -> conv -> BatchNorm -> ReLU)::

    z_shape -> linear 1024 -> BN -> ReLU -> (64, 2, 8)
      -> up 4x16, 96 (3x3) -> up 8x32, 96 (3x3) -> up 16x64, 64 (3x3) -> up 32x128, 64 (5x5)
      -> 1x1 conv -> 3 channels (linear output: the encoded sky)

The paper's latent z in R^64 is (log exposure, z_shape): the first coordinate is computed exactly
from the input (``encoding.exposure``: the sky's mean luminance), not learned, so a photo's
unknown exposure is one exact, linear latent direction and the 63 learned coordinates describe
the sky's shape, colour and sun-to-sky ratio (docs/ae.md). z_shape is linear (no BN / ReLU): a
GMM prior over it and a quasi-Newton search in it need an unbounded, unclipped space.

Padding: circular in azimuth (the panorama wraps around; the seam lies behind the sun) and zero
in elevation, for every conv of both halves.

Speed: a conv after nearest 2x upsampling is evaluated exactly as a 3 x 3 conv with 4 x C_out
outputs on the low-resolution input followed by a pixel shuffle (:class:`UpConv`; each output
phase sees a 2 x 2 (3 x 3 kernel) or 3 x 3 (5 x 5 kernel) window of the input), so the costly
last stage needs 9 x 4 instead of 25 x 4 multiply-adds per low-res pixel. :class:`FastDecoder`
additionally folds BatchNorm into the conv weights and runs channels-last (inference only).
"""

from __future__ import annotations

import functools

import torch
import torch.nn as nn
import torch.nn.functional as F

SKY_SHAPE = (32, 128)  # rows (zenith -> horizon) x columns of the network's sky hemisphere
ENCODER_STAGES = ((3, 64, 5), (64, 96, 3), (96, 96, 3), (96, 64, 3))  # (in, out, kernel)
DECODER_STAGES = ((64, 96, 3), (96, 96, 3), (96, 64, 3), (64, 64, 5))
BOTTLENECK = (64, 2, 8)  # channels, rows, columns after the last pool
LATENT_DIM = 64  # z = (log exposure, z_shape)
SHAPE_DIM = LATENT_DIM - 1

ARCHITECTURE = {
    "name": "f2l-sky-ae",
    "input": [3, *SKY_SHAPE],
    "encoder": [list(s) for s in ENCODER_STAGES],
    "decoder": [list(s) for s in DECODER_STAGES],
    "bottleneck": list(BOTTLENECK),
    "latent_dim": LATENT_DIM,
    "shape_dim": SHAPE_DIM,
    "padding": "circular azimuth, zero elevation",
    "upsampling": "nearest",
}


def pad_sky(x: torch.Tensor, rows: int, cols: int) -> torch.Tensor:
    """Pad (B, C, H, W) by ``cols`` circularly in azimuth and ``rows`` zeros in elevation."""
    if cols:
        x = torch.cat([x[..., -cols:], x, x[..., :cols]], dim=-1)
    if rows:
        x = F.pad(x, (0, 0, rows, rows))
    return x


class SkyConv(nn.Conv2d):
    """A k x k conv with circular azimuth / zero elevation padding that keeps the size."""

    def __init__(self, cin: int, cout: int, k: int) -> None:
        super().__init__(cin, cout, k, padding=0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        r = self.kernel_size[0] // 2
        return F.conv2d(pad_sky(x, r, r), self.weight, self.bias)


@functools.cache
def _phase_map(k: int) -> torch.Tensor:
    """(2, 2, 3, 3, k, k) 0/1 map M: the conv of kernel w after nearest 2x upsampling equals, for
    output phase (a, b), the 3 x 3 conv of the low-res input with sum_{dy,dx} M[a,b,:,:,dy,dx] w.

    Full-res row 2i + a + dy (dy in -r..r) is low-res row i + floor((a + dy) / 2), an offset in
    -1..1 for k <= 5 (same for columns)."""
    r = k // 2
    m = torch.zeros(2, 2, 3, 3, k, k)
    for a in range(2):
        for b in range(2):
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    m[a, b, (a + dy) // 2 + 1, (b + dx) // 2 + 1, dy + r, dx + r] = 1.0
    return m


def subpixel_weight(weight: torch.Tensor) -> torch.Tensor:
    """(C_out, C_in, k, k) -> (4 C_out, C_in, 3, 3) low-res kernels, output channel c * 4 + 2a + b
    (the order ``pixel_shuffle`` expects). Differentiable (a fixed linear map of ``weight``)."""
    k = weight.shape[-1]
    m = _phase_map(k).to(dtype=weight.dtype, device=weight.device)
    w = torch.einsum("abpqyx,oiyx->oabipq", m, weight)
    return w.reshape(weight.shape[0] * 4, weight.shape[1], 3, 3)


def upconv(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """conv(upsample_nearest_2x(x), weight) with sky padding, computed at low resolution."""
    b = None if bias is None else bias.repeat_interleave(4)
    return F.pixel_shuffle(F.conv2d(pad_sky(x, 1, 1), subpixel_weight(weight), b), 2)


class UpConv(nn.Conv2d):
    """Nearest 2x upsampling followed by a k x k :class:`SkyConv` (k = 3 or 5), evaluated exactly
    at low resolution (module docstring). The parameters are the plain k x k conv's."""

    def __init__(self, cin: int, cout: int, k: int) -> None:
        if k not in (3, 5):
            raise ValueError(f"UpConv supports 3x3 and 5x5 kernels, got {k}")
        super().__init__(cin, cout, k, padding=0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return upconv(x, self.weight, self.bias)


class SkyAE(nn.Module):
    """The autoencoder (module docstring). ``encode`` / ``decode`` work on encoded skies and z_shape."""

    def __init__(self) -> None:
        super().__init__()
        enc: list[nn.Module] = []
        for cin, cout, k in ENCODER_STAGES:
            enc += [SkyConv(cin, cout, k), nn.BatchNorm2d(cout), nn.ReLU(inplace=True), nn.MaxPool2d(2)]
        self.encoder = nn.Sequential(*enc)
        flat = BOTTLENECK[0] * BOTTLENECK[1] * BOTTLENECK[2]
        self.to_latent = nn.Linear(flat, SHAPE_DIM)
        self.from_latent = nn.Sequential(nn.Linear(SHAPE_DIM, flat), nn.BatchNorm1d(flat), nn.ReLU(inplace=True))
        dec: list[nn.Module] = []
        for cin, cout, k in DECODER_STAGES:
            dec += [UpConv(cin, cout, k), nn.BatchNorm2d(cout), nn.ReLU(inplace=True)]
        self.decoder = nn.Sequential(*dec)
        self.to_sky = nn.Conv2d(DECODER_STAGES[-1][1], 3, 1)

    def encode(self, e: torch.Tensor) -> torch.Tensor:
        """(B, 3, 32, 128) encoded sky -> (B, 63) z_shape."""
        return self.to_latent(self.encoder(e).flatten(1))

    def decode(self, z_shape: torch.Tensor) -> torch.Tensor:
        """(B, 63) z_shape -> (B, 3, 32, 128) encoded sky."""
        h = self.from_latent(z_shape).view(-1, *BOTTLENECK)
        return self.to_sky(self.decoder(h))

    def forward(self, e: torch.Tensor) -> torch.Tensor:
        return self.decode(self.encode(e))


def _fold_bn(weight: torch.Tensor, bias: torch.Tensor | None, bn: nn.BatchNorm2d | nn.BatchNorm1d):
    """(weight, bias) of a layer followed by an eval-mode BatchNorm, folded into one affine layer."""
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    shape = (-1,) + (1,) * (weight.dim() - 1)
    b = bias if bias is not None else torch.zeros_like(bn.running_mean)
    return weight * scale.view(shape), (b - bn.running_mean) * scale + bn.bias


class FastDecoder(nn.Module):
    """The trained decoder for inference: BatchNorm folded into the convs, sub-pixel kernels
    precomputed, float32, no parameter gradients (gradients flow to z only)."""

    def __init__(self, ae: SkyAE) -> None:
        super().__init__()
        ae = ae.eval()
        with torch.no_grad():
            lin, bn = ae.from_latent[0], ae.from_latent[1]
            w, b = _fold_bn(lin.weight, lin.bias, bn)
            self.register_buffer("fc_w", w.float().contiguous())
            self.register_buffer("fc_b", b.float().contiguous())
            self.stages = []
            mods = list(ae.decoder)
            for i in range(0, len(mods), 3):
                conv, bn2 = mods[i], mods[i + 1]
                w, b = _fold_bn(conv.weight, conv.bias, bn2)
                ws = subpixel_weight(w).float().contiguous(memory_format=torch.channels_last)
                bs = b.float().repeat_interleave(4).contiguous()
                self.register_buffer(f"w{i // 3}", ws)
                self.register_buffer(f"b{i // 3}", bs)
                self.stages.append(i // 3)
            self.register_buffer("out_w", ae.to_sky.weight.detach().float().clone())
            self.register_buffer("out_b", ae.to_sky.bias.detach().float().clone())

    def forward(self, z_shape: torch.Tensor) -> torch.Tensor:
        """(B, 63) -> (B, 3, 32, 128) encoded sky (float32)."""
        h = torch.relu(torch.addmm(self.fc_b, z_shape.float(), self.fc_w.T)).view(-1, *BOTTLENECK)
        h = h.contiguous(memory_format=torch.channels_last)  # oneDNN's preferred layout: ~25% faster
        for i in self.stages:
            h = torch.relu(F.pixel_shuffle(F.conv2d(pad_sky(h, 1, 1), getattr(self, f"w{i}"), getattr(self, f"b{i}")), 2))
        return F.conv2d(h, self.out_w, self.out_b)
