"""The sky autoencoder's network, HDR encoding, sun-centring and rotation (f2l_builtin_models.autoencoder.model / encoding)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from f2l_builtin_models.autoencoder.encoding import (SkyFormatError, centred_sky, decode_numpy, decode_torch, encode, exposure,
                             full_sphere, rotate_columns, sky_solid_angles)
from f2l_builtin_models.autoencoder.model import FastDecoder, SHAPE_DIM, SkyAE, SkyConv, UpConv
from f2l.lighting.grid import LatLongGrid, direction_from_angles, rotate_y
from f2l.synth.skies import clear_sky


@pytest.fixture(scope="module")
def ae():
    torch.manual_seed(0)
    net = SkyAE()
    # non-trivial BatchNorm statistics, so folding them into the convs is really tested
    for m in net.modules():
        if isinstance(m, (torch.nn.BatchNorm1d, torch.nn.BatchNorm2d)):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.2, 0.2)
    return net.eval()


def test_encoder_decoder_shapes(ae):
    x = torch.randn(2, 3, 32, 128)
    with torch.no_grad():
        z = ae.encode(x)
        y = ae.decode(z)
    assert z.shape == (2, SHAPE_DIM) == (2, 63)
    assert y.shape == (2, 3, 32, 128)
    # the mirrored decoder's stages: 2x8 -> 4x16 -> 8x32 -> 16x64 -> 32x128, 1x1 conv to 3 channels
    assert [m.out_channels for m in ae.decoder if isinstance(m, UpConv)] == [96, 96, 64, 64]
    assert [m.out_channels for m in ae.encoder if isinstance(m, SkyConv)] == [64, 96, 96, 64]
    assert ae.to_sky.kernel_size == (1, 1) and ae.to_sky.out_channels == 3


@pytest.mark.parametrize("k", [3, 5])
def test_upconv_equals_upsampling_then_conv(k):
    torch.manual_seed(k)
    up = UpConv(6, 5, k)
    ref = SkyConv(6, 5, k)
    ref.load_state_dict(up.state_dict())
    x = torch.randn(2, 6, 4, 16)
    expected = ref(F.interpolate(x, scale_factor=2, mode="nearest"))
    # float32 sums of <= 150 terms, |y| ~ 2: each side ~1e-6 from float64 in any order (6e-7 measured)
    assert torch.allclose(up(x), expected, atol=1e-5)


def test_sky_padding_is_circular_in_azimuth():
    torch.manual_seed(1)
    conv = SkyConv(3, 4, 3)
    x = torch.randn(1, 3, 8, 32)
    # rolling the input in azimuth rolls the output: no seam at the panorama's edge
    # each output is the same 27-term float32 sum, at most reordered at vector tails: ~1e-6 (measured: equal)
    assert torch.allclose(conv(torch.roll(x, 5, -1)), torch.roll(conv(x), 5, -1), atol=1e-5)


def test_fast_decoder_matches_the_network(ae):
    fast = FastDecoder(ae)
    z = torch.randn(3, SHAPE_DIM)
    with torch.no_grad():
        assert torch.allclose(fast(z), ae.decode(z), atol=1e-4)  # float32, |y| < 0.3: both ~1e-7 from float64's
    z.requires_grad_(True)
    fast(z).sum().backward()
    assert z.grad is not None and torch.isfinite(z.grad).all()
    assert not any(p.requires_grad for p in fast.parameters())


def test_rotation_by_whole_columns_is_a_roll():
    x = torch.rand(2, 3, 4, 16)
    step = 2 * math.pi / 16
    y = rotate_columns(x, torch.tensor([3 * step, -2 * step]))
    assert torch.allclose(y[0], torch.roll(x[0], 3, -1), atol=1e-6)
    assert torch.allclose(y[1], torch.roll(x[1], -2, -1), atol=1e-6)


def test_fractional_rotation_matches_rotate_y_and_keeps_energy():
    x = torch.rand(1, 3, 4, 16, dtype=torch.float64)
    phi = 0.3
    y = rotate_columns(x, torch.tensor([phi], dtype=torch.float64))
    ref = rotate_y(x[0].permute(1, 2, 0).numpy(), -phi)
    assert np.allclose(y[0].permute(1, 2, 0).numpy(), ref, atol=1e-12)
    assert torch.allclose(y.sum(-1), x.sum(-1))
    # differentiable in the angle: d/dphi of the texel sum-weighted by column index is finite, non-zero
    a = torch.tensor([phi], dtype=torch.float64, requires_grad=True)
    (rotate_columns(x, a) * torch.arange(16.0, dtype=torch.float64)).sum().backward()
    assert a.grad is not None and float(a.grad.abs()) > 0


def test_encoding_round_trip_and_exposure():
    rng = np.random.default_rng(0)
    sky = rng.uniform(0.0, 5.0, (32, 128, 3)) ** 3
    e, log_s = encode(sky)
    assert e.shape == (3, 32, 128) and e.dtype == np.float32
    assert math.isclose(math.exp(log_s), exposure(sky), rel_tol=1e-12)
    back = decode_numpy(e, log_s)
    assert np.allclose(back, sky, rtol=1e-5, atol=1e-5 * exposure(sky))
    # exposure invariance: a brighter copy has the same code and log s shifted by log(1000)
    e2, log_s2 = encode(1000.0 * sky)
    assert np.allclose(e2, e, atol=1e-6) and math.isclose(log_s2 - log_s, math.log(1000.0), rel_tol=1e-9)
    # the exposure is the mean luminance: a unit-grey sky has s = 1 and e = 1; 8x brighter texels e = 2
    e1, ls1 = encode(np.ones((32, 128, 3)))
    assert abs(ls1) < 1e-12 and np.allclose(e1, 1.0)
    patch = np.ones((32, 128, 3))
    patch[:4] = 8.0
    e8, _ = encode(patch)
    assert np.allclose(e8[:, :4] / e8[:, 4:].mean(), 2.0)
    t = decode_torch(torch.from_numpy(e)[None], torch.tensor([log_s]))
    assert np.allclose(t[0].permute(1, 2, 0).numpy(), back, rtol=1e-5)
    assert math.isclose(float(sky_solid_angles().sum()), 2 * math.pi, rel_tol=1e-12)


def test_sun_centring_puts_the_sun_at_azimuth_zero():
    grid = LatLongGrid(64, 128)
    azimuth = math.radians(70.0)
    probe = clear_sky(grid, math.radians(30.0), azimuth)
    sky, found = centred_sky(full_sphere(probe))
    assert abs(found - azimuth) < math.radians(1.0)
    lum = sky @ np.array([0.2126, 0.7152, 0.0722])
    row, col = np.unravel_index(np.argmax(lum), lum.shape)
    assert col in (63, 64)  # the sun straddles the centre edge (azimuth 0)
    # its elevation stays where it was
    assert abs(math.degrees(math.pi / 2 - grid.phi_rad[row]) - 30.0) < 3.0


def test_full_sphere_accepts_hemispheres_and_names_bad_files():
    hemi = np.ones((8, 32, 3))
    full = full_sphere(hemi)
    assert full.shape == (16, 32, 3) and full[8:].sum() == 0
    with pytest.raises(SkyFormatError, match="bad.exr"):
        full_sphere(np.ones((10, 13, 3)), "bad.exr")
    with pytest.raises(SkyFormatError, match="nan.exr"):
        full_sphere(np.full((8, 16, 3), np.nan), "nan.exr")


def test_centred_sky_of_a_rotated_probe_is_the_same():
    grid = LatLongGrid(64, 128)
    a = clear_sky(grid, math.radians(40.0), 0.5)
    b = clear_sky(grid, math.radians(40.0), 0.5 + 2 * math.pi * 16 / 128)  # 16 columns further
    sa, _ = centred_sky(a, azimuth=0.5)
    sb, _ = centred_sky(b, azimuth=0.5 + 2 * math.pi * 16 / 128)
    assert np.allclose(sa, sb, rtol=1e-4, atol=1e-6 * sa.max())
    assert direction_from_angles(0.0, 0.0)[2] == -1.0  # azimuth 0 is the camera's view, -Z
