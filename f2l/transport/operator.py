"""The diffuse transport operator T, held in compact form (packed visibility bits + normals).

    T[p, w] = V(p, w) * max(0, <n_p, w>) * dOmega_w / pi          (N x L)

with V the binary visibility (:func:`f2l.transport.visibility.compute_visibility`), n_p the unit
normal of pixel p, w the texel-centre directions and dOmega_w the texel solid angles of a
:class:`~f2l.lighting.grid.LatLongGrid` (texels flattened row-major). Shading of pixel p is
``albedo * (T @ l)[p]`` for a probe radiance ``l`` (L, 3). T @ 1 is the cosine-weighted
unoccluded fraction of the hemisphere (1 for an unoccluded pixel, up to grid discretisation).

Only the packed bits (N x ceil(L/8) bytes) and the normals are kept; every product builds T in
chunks of rows (``chunk_pixels``), so the dense float32 T (4 N L bytes: 312 MiB for N = 10k,
L = 8192) exists only if :meth:`Transport.dense` is asked for it.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from threading import Lock

import numpy as np

from f2l.lighting.grid import LatLongGrid
from f2l.transport.visibility import compute_visibility, front_cosines, front_mask, packed_width

__all__ = ["Transport"]


class Transport:
    """Compact diffuse transport T (N x L) of N face pixels on a lat-long ``grid``.

    vis_bits: (N, ceil(L/8)) uint8, ``np.packbits(V, axis=1, bitorder="little")`` over the
    row-major texel index. Precondition: bits are 0 on back-facing texels (<n, w> <= 0), as
    :func:`compute_visibility` guarantees; the products rely on it (separable cosine, no clamp)
    while :meth:`dense` clamps. For bits of other origin pass ``clear_back_facing=True``
    (one pass over the bits, clears them in place on a copy).
    normals: (N, 3), normalised here.
    threads: worker threads for the chunked products (numpy releases the GIL).
    """

    def __init__(self, vis_bits: np.ndarray, normals: np.ndarray, grid: LatLongGrid,
                 chunk_pixels: int = 1024, threads: int | None = 2,
                 clear_back_facing: bool = False) -> None:
        copy = True if clear_back_facing else None  # never modify the caller's array
        vis_bits = np.array(vis_bits, dtype=np.uint8, order="C", copy=copy)
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        if vis_bits.ndim != 2 or vis_bits.shape[1] != packed_width(grid):
            raise ValueError(
                f"vis_bits must be (N, {packed_width(grid)}) for a {grid.height}x{grid.width} "
                f"grid, got {vis_bits.shape}")
        if len(normals) != len(vis_bits):
            raise ValueError(f"{len(vis_bits)} rows of bits but {len(normals)} normals")
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
        self.grid = grid
        self.vis_bits = vis_bits
        self.normals = normals
        self.chunk_pixels = int(chunk_pixels)
        self.threads = max(1, int(threads or os.cpu_count() or 1))
        # separable cosine: <n, w> dOmega/pi = s_r (nx sin t_c - nz cos t_c) + c_r ny
        a = grid.row_solid_angles / np.pi
        self._row_sin = np.sin(grid.phi_rad) * a  # (H,)
        self._row_cos = np.cos(grid.phi_rad) * a  # (H,)
        self._col_sin = np.sin(grid.theta_rad)  # (W,)
        self._col_cos = np.cos(grid.theta_rad)  # (W,)
        self._texel_weights = grid.directions_flat * (grid.solid_angles_flat / np.pi)[:, None]
        if clear_back_facing:
            self._clear_back_facing()

    # -- construction ---------------------------------------------------------------------
    @classmethod
    def from_mesh(cls, vertices, faces, points, normals, grid: LatLongGrid = LatLongGrid(),
                  method: str = "adaptive", threads: int | None = 2,
                  offset: float | None = None, **kwargs) -> "Transport":
        """Ray-cast the visibility of ``grid`` from ``points`` (see :func:`compute_visibility`)."""
        bits = compute_visibility(vertices, faces, points, normals, grid, method=method,
                                  threads=threads, offset=offset)
        return cls(bits, normals, grid, threads=threads, **kwargs)

    def _clear_back_facing(self) -> None:
        for s, e in self._chunks():
            front = front_mask(self.normals[s:e], self.grid)
            self.vis_bits[s:e] &= np.packbits(front, axis=1, bitorder="little")

    # -- sizes --------------------------------------------------------------------------------
    @property
    def num_pixels(self) -> int:
        return len(self.vis_bits)

    @property
    def num_texels(self) -> int:
        return self.grid.size

    @property
    def shape(self) -> tuple[int, int]:
        return (self.num_pixels, self.grid.size)

    @property
    def nbytes(self) -> int:
        """Bytes of the compact form (packed bits + float64 normals)."""
        return int(self.vis_bits.nbytes + self.normals.nbytes)

    def __repr__(self) -> str:
        return (f"Transport(N={self.num_pixels}, grid={self.grid.height}x{self.grid.width}, "
                f"{self.nbytes / 2**20:.1f} MiB packed)")

    # -- dense rows -----------------------------------------------------------------------------
    def _chunks(self, n: int | None = None):
        n = self.num_pixels if n is None else n
        return [(s, min(n, s + self.chunk_pixels)) for s in range(0, n, self.chunk_pixels)]

    def _rows_of(self, bits: np.ndarray, normals: np.ndarray, dtype) -> np.ndarray:
        """Dense T rows (m, L) for the given packed bits and unit normals."""
        m = len(bits)
        h, w = self.grid.shape
        dtype = np.dtype(dtype)
        az = (normals[:, 0:1] * self._col_sin - normals[:, 2:3] * self._col_cos).astype(dtype)
        el = (normals[:, 1:2] * self._row_cos).astype(dtype)  # (m, H)
        t = np.multiply(az[:, None, :], self._row_sin.astype(dtype)[None, :, None])
        t += el[:, :, None]
        np.maximum(t, 0, out=t)
        t *= np.unpackbits(bits, axis=1, count=h * w, bitorder="little").reshape(m, h, w)
        return t.reshape(m, h * w)

    def _row_index(self, rows):
        if rows is None:
            return slice(None)
        if isinstance(rows, slice):
            return rows
        return np.asarray(rows)

    def dense(self, dtype=np.float32, rows=None) -> np.ndarray:
        """Materialise T (or the rows ``rows``: slice, index or boolean array) as (n, L)."""
        idx = self._row_index(rows)
        bits, normals = self.vis_bits[idx], self.normals[idx]
        if bits.ndim == 1:  # a single integer row
            bits, normals = bits[None], normals[None]
        out = np.empty((len(bits), self.grid.size), dtype=dtype)

        def work(chunk):
            s, e = chunk
            out[s:e] = self._rows_of(bits[s:e], normals[s:e], dtype)

        self._map(work, len(bits))
        return out

    # -- products -------------------------------------------------------------------------------
    def _map(self, fn, n: int | None = None) -> None:
        chunks = self._chunks(n)
        if self.threads == 1 or len(chunks) == 1:
            for c in chunks:
                fn(c)
        else:
            with ThreadPoolExecutor(max_workers=self.threads) as pool:
                list(pool.map(fn, chunks))

    def _bits_rows(self, s: int, e: int, dtype) -> np.ndarray:
        """V rows s:e as (m, L) 0/1 in ``dtype``."""
        return np.unpackbits(self.vis_bits[s:e], axis=1, count=self.grid.size,
                             bitorder="little").astype(dtype)

    def matmul(self, l: np.ndarray, dtype=np.float32) -> np.ndarray:
        """T @ l for l (L,) or (L, C); returns (N,) or (N, C) in ``dtype``.

        Uses the separable cosine: with V = 0 on back-facing texels,
        ``T @ l = sum_k n[:, k] * (V @ (w_k dOmega/pi * l))`` for k = x, y, z, so each chunk of
        ``chunk_pixels`` rows only unpacks its bits and makes one (m, L) x (L, 3C) product.
        ``dtype=np.float64`` unpacks and accumulates in float64.
        """
        l = np.asarray(l)
        vec = l.ndim == 1
        l2 = l.reshape(l.shape[0], -1)
        if l2.shape[0] != self.grid.size:
            raise ValueError(f"l must have {self.grid.size} rows (texels), got {l.shape}")
        c = l2.shape[1]
        m3 = np.concatenate([self._texel_weights[:, k:k + 1] * l2 for k in range(3)], axis=1)
        m3 = m3.astype(dtype, copy=False)
        normals = self.normals.astype(dtype, copy=False)
        out = np.empty((self.num_pixels, c), dtype=dtype)

        def work(chunk):
            s, e = chunk
            r = self._bits_rows(s, e, dtype) @ m3
            n = normals[s:e]
            out[s:e] = n[:, 0:1] * r[:, :c] + n[:, 1:2] * r[:, c:2 * c] + n[:, 2:3] * r[:, 2 * c:]

        self._map(work)
        return out[:, 0] if vec else out

    __matmul__ = matmul

    def project(self, basis: np.ndarray, dtype=np.float32) -> np.ndarray:
        """T @ basis for a (L, K) basis (e.g. spherical harmonics sampled at texel centres)."""
        return self.matmul(basis, dtype=dtype)

    def rmatmul(self, g: np.ndarray, dtype=np.float32) -> np.ndarray:
        """T^T @ g for g (N,) or (N, C); returns (L,) or (L, C) (e.g. a loss gradient w.r.t. l).

        Separable form: ``T^T g = sum_k (w_k dOmega/pi) * (V^T (n[:, k] * g))``.
        """
        g = np.asarray(g)
        vec = g.ndim == 1
        g2 = g.reshape(g.shape[0], -1)
        if g2.shape[0] != self.num_pixels:
            raise ValueError(f"g must have {self.num_pixels} rows (pixels), got {g.shape}")
        c = g2.shape[1]
        acc = np.zeros((self.grid.size, 3 * c), dtype=dtype)
        lock = Lock()

        def work(chunk):
            s, e = chunk
            n = self.normals[s:e]
            y = np.concatenate([n[:, k:k + 1] * g2[s:e] for k in range(3)], axis=1)
            part = self._bits_rows(s, e, dtype).T @ y.astype(dtype, copy=False)
            with lock:
                acc[...] += part

        self._map(work)
        w = self._texel_weights.astype(dtype, copy=False)
        out = w[:, 0:1] * acc[:, :c] + w[:, 1:2] * acc[:, c:2 * c] + w[:, 2:3] * acc[:, 2 * c:]
        return out[:, 0] if vec else out

    def row_sums(self, texel_mask: np.ndarray | None = None, dtype=np.float64) -> np.ndarray:
        """(N,) sum of T over the texels in ``texel_mask`` ((L,) or (H, W) bool; None: all),
        i.e. T @ 1_mask -- e.g. the irradiance fraction from the ground (lower hemisphere)."""
        if texel_mask is None:
            ones = np.ones(self.grid.size, dtype=dtype)
        else:
            mask = np.asarray(texel_mask, dtype=bool).reshape(-1)
            if mask.size != self.grid.size:
                raise ValueError(f"texel_mask must have {self.grid.size} texels, got {mask.size}")
            ones = mask.astype(dtype)
        return self.matmul(ones, dtype=dtype)

    def visible_fraction(self, weighted: bool = True) -> np.ndarray:
        """(N,) fraction of each pixel's front hemisphere that is visible.

        weighted=True: cosine- and solid-angle-weighted, T @ 1 / sum_w max(0, <n, w>) dOmega/pi
        (1 - ambient occlusion); False: fraction of front-facing texels whose bit is set.
        """
        res = np.empty(self.num_pixels, dtype=np.float64)
        wgt = self.grid.solid_angles_flat / np.pi

        def work(c):
            s, e = c
            cos = front_cosines(self.normals[s:e], self.grid).reshape(e - s, -1)
            front = cos > 0.0
            bits = np.unpackbits(self.vis_bits[s:e], axis=1, count=self.grid.size,
                                 bitorder="little").astype(bool) & front
            if weighted:
                full = np.where(front, cos, 0.0) @ wgt
                vis = np.where(bits, cos, 0.0) @ wgt
            else:
                full, vis = front.sum(1), bits.sum(1)
            res[s:e] = np.divide(vis, full, out=np.zeros(e - s), where=full > 0)

        self._map(work)
        return res

    # -- compact forms for the sky (f2l.estimate.sky_transport) -------------------------------
    def block_sums(self, n_rows: int, block: tuple[int, int], dtype=np.float64, first_row: int = 0) -> np.ndarray:
        """(N, n_rows/br * W/bc) sums of T over blocks of br x bc texels in the ``n_rows`` rows
        from ``first_row`` (row-major over blocks): the transport onto a coarser lat-long grid,
        integrated exactly from the fine bits. ``n_rows`` and W must be multiples of the block.

        Texels of one row share the polar angle, so with the separable cosine a row's part of a
        block is dOmega_r/pi (n_x sin(phi_r) S_sin + n_y cos(phi_r) S_1 - n_z sin(phi_r) S_cos),
        S_f = sum of f(theta) over the visible texels. With bc = 4 the S_f of each half byte of
        bits come from a 16-entry table per column group (one gather, no unpacking).
        """
        br, bc = (int(b) for b in block)
        h, w = self.grid.shape
        if br <= 0 or bc <= 0 or n_rows <= 0 or first_row < 0:
            raise ValueError(f"block {block}, {n_rows} rows from row {first_row}: sizes must be positive")
        if n_rows % br or w % bc or first_row + n_rows > h or w % 8:
            raise ValueError(f"{n_rows} rows x {w} columns do not split into {br}x{bc} blocks")
        nb_r, nb_c = n_rows // br, w // bc
        if bc != 4:
            return self._block_sums_dense(first_row, n_rows, br, bc, dtype)
        rows = slice(first_row, first_row + n_rows)
        theta = self.grid.theta_rad.reshape(nb_c, 4)
        nibbles = (np.arange(16)[:, None] >> np.arange(4)[None, :]) & 1  # (16, 4) bit i = column i
        table = np.stack([nibbles @ np.sin(theta).T, nibbles @ np.ones((4, nb_c)), nibbles @ np.cos(theta).T],
                         -1).transpose(1, 0, 2).reshape(nb_c * 16, 3)  # (group x nibble, 3)
        table_t = np.ascontiguousarray(table.T, dtype=np.float32)
        a = self.grid.row_solid_angles[rows] / np.pi
        phi = self.grid.phi_rad[rows]
        row_k = np.stack([np.sin(phi) * a, np.cos(phi) * a, -np.sin(phi) * a], -1)  # (rows, 3)
        byte_cols = slice(first_row * w // 8, (first_row + n_rows) * w // 8)
        group_base = (np.arange(nb_c) * 16).reshape(1, 1, nb_c)
        out = np.empty((self.num_pixels, nb_r * nb_c), dtype=dtype)

        def work(chunk):
            s, e = chunk
            m = e - s
            b = self.vis_bits[s:e, byte_cols].reshape(m, n_rows, w // 8)
            nib = np.stack([b & 15, b >> 4], -1).reshape(m, n_rows, nb_c)  # group 2j: low half
            idx = nib.astype(np.int64) + group_base
            coef = (self.normals[s:e, None, :] * row_k[None]).astype(np.float32)[:, :, None, :]
            per_row = np.take(table_t[0], idx) * coef[..., 0]
            per_row += np.take(table_t[1], idx) * coef[..., 1]
            per_row += np.take(table_t[2], idx) * coef[..., 2]
            blocks = per_row.reshape(m, nb_r, br, nb_c).sum(2, dtype=np.float64)
            out[s:e] = np.maximum(blocks.reshape(m, -1), 0.0)

        self._map(work)
        return out

    def _block_sums_dense(self, first_row: int, n_rows: int, br: int, bc: int, dtype) -> np.ndarray:
        """:meth:`block_sums` for any block width, from unpacked bits (slower)."""
        w = self.grid.width
        nb_r, nb_c = n_rows // br, w // bc
        out = np.empty((self.num_pixels, nb_r * nb_c), dtype=dtype)
        texels = slice(first_row * w, (first_row + n_rows) * w)
        weights = self._texel_weights[texels].astype(np.float32)

        def work(chunk):
            s, e = chunk
            v = np.unpackbits(self.vis_bits[s:e, texels.start // 8: texels.stop // 8], axis=1, bitorder="little")
            v = v.astype(np.float32)
            acc = np.zeros((e - s, nb_r * nb_c), dtype=np.float64)
            for k in range(3):
                part = (v * weights[:, k]).reshape(e - s, nb_r, br, nb_c, bc).sum((2, 4))
                acc += self.normals[s:e, k:k + 1] * part.reshape(e - s, -1)
            out[s:e] = np.maximum(acc, 0.0)

        self._map(work)
        return out

    def columns(self, texels: np.ndarray, dtype=np.float64, rows=None) -> np.ndarray:
        """(N, k) exact columns T[:, texels] read from the packed bits (``texels`` flat indices;
        ``rows``: only these pixels, as for :meth:`dense`)."""
        texels = np.asarray(texels, dtype=np.int64).reshape(-1)
        idx = self._row_index(rows)
        if isinstance(idx, np.ndarray) and idx.ndim == 0:  # a single integer row
            idx = idx[None]
        bits = (self.vis_bits[idx][:, texels >> 3] >> (texels & 7).astype(np.uint8)) & 1
        cos = self.normals[idx] @ self._texel_weights[texels].T  # <n, w> dOmega / pi
        return (bits * np.maximum(cos, 0.0)).astype(dtype, copy=False)

    # -- low rank ---------------------------------------------------------------------------------
    def lowrank(self, k: int, seed: int = 0, niter: int = 2, oversample: int = 8,
                max_dense_bytes: int = 1 << 30) -> tuple[np.ndarray, np.ndarray]:
        """Rank-k factors (U (N, k), Vt (k, L)) float32 with T ~= U @ Vt (singular values folded
        into U), by randomized SVD: ``torch.svd_lowrank`` on the dense float32 T when it fits in
        ``max_dense_bytes``, else the same algorithm (Halko et al.) on chunked products.

        Caveat (notes/performance.md): low rank fills hard shadows in; keep exact columns /
        shadow rays for the sun.
        """
        import torch

        k = int(k)
        n, L = self.shape
        q = min(k + oversample, n, L)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            if n * L * 4 <= max_dense_bytes:
                a = torch.from_numpy(self.dense(np.float32))
                u, s, v = torch.svd_lowrank(a, q=q, niter=niter)
                u, s, v = u[:, :k], s[:k], v[:, :k]
                return (u * s).numpy().astype(np.float32), v.T.contiguous().numpy().astype(
                    np.float32)
            omega = torch.randn(L, q, dtype=torch.float64).numpy()
        y = self.matmul(omega, dtype=np.float64)  # (n, q)
        qm, _ = np.linalg.qr(y)
        for _ in range(niter):
            z, _ = np.linalg.qr(self.rmatmul(qm, dtype=np.float64))  # (L, q)
            qm, _ = np.linalg.qr(self.matmul(z, dtype=np.float64))
        b = self.rmatmul(qm, dtype=np.float64).T  # (q, L) = Q^T T
        ub, s, vt = np.linalg.svd(b, full_matrices=False)
        u = (qm @ ub[:, :k]) * s[:k]
        return u.astype(np.float32), np.ascontiguousarray(vt[:k], dtype=np.float32)
