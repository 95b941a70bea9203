"""Hybrid sky transport for sun models: block-averaged T for the sky, exact columns for the sun.

    T l = T_blk m  +  sum_{w in core} R[:, w] sun_w                               (per channel)

- ``T_blk`` (N, nb): T summed over blocks of br x bc sky texels (``Transport.block_sums``, exact
  from the bits), and m_b = sum_{w in b} dOmega_w l_w / Omega_b the block's solid-angle-weighted
  mean radiance. This is T l exactly when either l or T / dOmega is constant inside each block,
  which holds well for the smooth sky (block 11 x 11 deg on 64 x 128).
- The sun lobe is not smooth, and a block average fills its hard cast shadows in (the bias of a
  low-rank T towards small kappa, shared notes/performance.md). So its ``core`` texels (the
  ``core_texels`` of the lobe's window holding the most energy: the whole lobe for kappa = 8192
  away from the zenith) get the exact correction R = T - T~, T~[:, w] = T_blk[:, b(w)] dOmega_w /
  Omega_b: the sun's core sees exact visibility, the far tail of a broad lobe the block average.
- Residual columns are read from the packed bits on first use and cached by texel
  (:class:`ColumnCache`): an estimate touches a few hundred texels around its starts.

Shapes: N pixels, Lu = sky_rows x W texels, B starts, K window texels; float64 throughout.
"""

from __future__ import annotations

import numpy as np
import torch

from f2l.lighting.grid import LatLongGrid
from f2l.transport import Transport

DEFAULT_BLOCK = (4, 4)
DEFAULT_CORE_TEXELS = 48


class ColumnCache:
    """Residual columns R[:, w] (float64 torch, stored one texel per row) filled on demand."""

    def __init__(self, transport: Transport, t_blk: np.ndarray, block_of: np.ndarray,
                 texel_share: np.ndarray) -> None:
        self.transport = transport
        self.t_blk = t_blk
        self.block_of = block_of  # (Lu,) block index of each sky texel
        self.texel_share = texel_share  # (Lu,) dOmega_w / Omega_b(w)
        n = transport.num_pixels
        self.slot = np.full(block_of.size, -1, dtype=np.int64)
        self.store = torch.empty((64, n), dtype=torch.float64)
        self.used = 0

    def rows(self, texels: np.ndarray) -> torch.Tensor:
        """(..., N) residual columns of the flat sky texel indices ``texels`` (any shape)."""
        slots = self.slots(texels)  # first: it may grow (replace) the store
        return self.store[slots]

    def slots(self, texels: np.ndarray) -> torch.Tensor:
        """Rows of :attr:`store` holding the residual columns of ``texels`` (read on first use)."""
        texels = np.asarray(texels, dtype=np.int64)
        missing = np.unique(texels[self.slot[texels] < 0])
        if missing.size:
            self._add(missing)
        return torch.from_numpy(self.slot[texels])

    def weighted_sum(self, texels: np.ndarray, weights: torch.Tensor) -> torch.Tensor:
        """(B, N) sum_j weights[:, j] R[:, texels[:, j]] for texels, weights (B, k), without
        gathering the (B, k, N) columns (``embedding_bag``; differentiable in ``weights``)."""
        slots = self.slots(texels)  # first: it may grow (replace) the store
        return torch.nn.functional.embedding_bag(slots, self.store, per_sample_weights=weights, mode="sum")

    def _add(self, texels: np.ndarray) -> None:
        need = self.used + texels.size
        if need > self.store.shape[0]:
            grown = torch.empty((max(need, 2 * self.store.shape[0]), self.store.shape[1]), dtype=torch.float64)
            grown[: self.used] = self.store[: self.used]
            self.store = grown
        exact = self.transport.columns(texels)  # (N, k)
        approx = self.t_blk[:, self.block_of[texels]] * self.texel_share[texels]
        self.store[self.used:need] = torch.from_numpy(np.ascontiguousarray((exact - approx).T))
        self.slot[texels] = np.arange(self.used, need)
        self.used = need


class SkyTransport:
    """T restricted to the sky rows in hybrid form (module docstring), for one face."""

    def __init__(self, transport: Transport, grid: LatLongGrid, block: tuple[int, int] = DEFAULT_BLOCK,
                 core_texels: int = DEFAULT_CORE_TEXELS) -> None:
        br, bc = block
        rows, width = grid.sky_rows, grid.width
        self.grid = grid
        self.block = (int(br), int(bc))
        self.core_texels = int(core_texels)
        self.shape_blocks = (rows // br, width // bc)
        self.num_pixels = transport.num_pixels
        t_blk = transport.block_sums(rows, self.block)  # (N, nb)
        sa = np.asarray(grid.solid_angles_flat[: rows * width], dtype=np.float64)
        r_idx, c_idx = np.divmod(np.arange(rows * width), width)
        block_of = (r_idx // br) * self.shape_blocks[1] + c_idx // bc
        omega_b = np.bincount(block_of, weights=sa, minlength=t_blk.shape[1])
        self.t_blk = torch.from_numpy(t_blk)
        self.d_omega = torch.from_numpy(sa.copy())
        self.omega_b = torch.from_numpy(omega_b)
        self.block_of = block_of
        self.cache = ColumnCache(transport, t_blk, block_of, sa / omega_b[block_of])
        self._share = None  # dOmega_w / Omega_b(w) as (rows / br, br, W / bc, bc), made on first use

    def sky_summary(self, sky: torch.Tensor, e_weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A sky radiance (B, Lu, 3) -> its block means (B, nb, 3) (as :meth:`block_means`) and
        sum_w e_weights[w] sky[:, w] (B, 3) (e.g. the horizontal irradiance E_h), in one autograd
        node (:class:`_SkySummary`): the full-resolution sky is read once and gets its gradient
        in one pass, where the elementwise form keeps several sky-sized arrays for backward."""
        (nbr, nbc), (br, bc) = self.shape_blocks, self.block
        if self._share is None:
            self._share = (self.d_omega / self.omega_b[torch.from_numpy(self.block_of)]).reshape(nbr, br, nbc, bc)
        return _SkySummary.apply(sky, self._share, e_weights.to(sky.dtype))

    def lobe_block_means(self, vals: torch.Tensor, flat: torch.Tensor) -> torch.Tensor:
        """(B, nb) block means of a sparse lobe (texel means ``vals`` (B, K) at ``flat`` (B, K))."""
        block_of = torch.as_tensor(self.block_of)[flat]
        sums = vals.new_zeros(vals.shape[0], self.t_blk.shape[1]).scatter_add_(1, block_of, vals * self.d_omega[flat])
        return sums / self.omega_b[None]

    def block_means(self, l_sky: torch.Tensor) -> torch.Tensor:
        """(B, Lu, 3) radiance -> (B, nb, 3) solid-angle-weighted block means m."""
        B = l_sky.shape[0]
        (nbr, nbc), (br, bc) = self.shape_blocks, self.block
        e = (l_sky * self.d_omega[None, :, None]).reshape(B, nbr, br, nbc, bc, 3).sum((2, 4))
        return e.reshape(B, nbr * nbc, 3) / self.omega_b[None, :, None]

    def core(self, sun_vals: torch.Tensor, sun_flat: torch.Tensor) -> tuple[torch.Tensor, np.ndarray]:
        """The window texels with the most energy: (values (B, k) differentiable, flat (B, k))."""
        k = min(self.core_texels, sun_vals.shape[1])
        energy = sun_vals.detach() * self.d_omega[sun_flat]
        pos = torch.topk(energy, k, dim=1).indices
        return torch.gather(sun_vals, 1, pos), torch.gather(sun_flat, 1, pos).numpy()

    def apply(self, l_sky: torch.Tensor, sun: tuple | None = None,
              block_means: torch.Tensor | None = None) -> torch.Tensor:
        """T_sky l (B, N, 3) for sky radiance (B, Lu, 3) that includes the sun (None where
        ``block_means`` is given: the radiance is read only through them and ``sun``).

        ``sun = (vals (B, K), flat (B, K), w_sun (B, 3))``: the lobe's texel means and RGB
        weight (``CompactSun.radiance_parts``) for the exact core correction; None skips it (a
        sun-less or overcast solution, or the block-only approximation). ``block_means``: the
        radiance's :meth:`block_means`, where the caller has them (another pixel set's transport
        on the same grid and blocks).
        """
        m = self.block_means(l_sky) if block_means is None else block_means  # (B, nb, 3)
        B = m.shape[0]
        tl = (self.t_blk @ m.transpose(0, 1).reshape(m.shape[1], 3 * B)).reshape(-1, B, 3).transpose(0, 1)
        if sun is not None and self.core_texels > 0:
            vals, flat, w_sun = sun
            core_vals, core_flat = self.core(vals, flat)
            shade = self.cache.weighted_sum(core_flat, core_vals)  # (B, N)
            tl = tl + shade[:, :, None] * w_sun[:, None, :]
        return tl


class _SkySummary(torch.autograd.Function):
    """(sky (B, Lu, 3), share (nbr, br, nbc, bc) = dOmega / Omega_b, e (Lu,)) -> (block means
    (B, nb, 3), e . sky (B, 3)). Both are linear in the sky, so the backward is one broadcast:
    dL/dsky_w = share_w dL/dm_b(w) + e_w dL/de, laid out as the sky is (a channel-first sky, as
    a model's transposed view, gets a channel-first gradient)."""

    @staticmethod
    def forward(ctx, sky, share, e):
        B, (nbr, br, nbc, bc) = sky.shape[0], share.shape
        channel_first = sky.stride(1) == 1 and sky.stride(2) != 1
        ctx.save_for_backward(share, e)
        ctx.channel_first = channel_first
        if channel_first:  # read the sky in its own memory order
            s = sky.transpose(1, 2).reshape(B, 3, nbr, br, nbc, bc)
            m = (s * share).sum((3, 5)).reshape(B, 3, nbr * nbc).transpose(1, 2)
            return m, sky.transpose(1, 2) @ e
        m = (sky.reshape(B, nbr, br, nbc, bc, 3) * share[..., None]).sum((2, 4)).reshape(B, nbr * nbc, 3)
        return m, e @ sky

    @staticmethod
    def backward(ctx, grad_m, grad_e):
        share, e = ctx.saved_tensors
        B, (nbr, _, nbc, _) = grad_m.shape[0], share.shape
        if ctx.channel_first:
            g = grad_m.transpose(1, 2).reshape(B, 3, nbr, 1, nbc, 1) * share
            g = g.reshape(B, 3, -1).addcmul_(grad_e[:, :, None], e[None, None, :])
            return g.transpose(1, 2), None, None
        g = grad_m.reshape(B, nbr, 1, nbc, 1, 3) * share[..., None]
        g = g.reshape(B, -1, 3).addcmul_(e[None, :, None], grad_e[:, None, :])
        return g, None, None

