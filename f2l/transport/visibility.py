"""Binary visibility V(p, w) of lat-long grid texels from face-mesh pixels, packed as bits.

Conventions
-----------
* Directions are the texel centres of a :class:`~f2l.lighting.grid.LatLongGrid`, flattened
  row-major (``index = row * W + col``), ``grid.directions_flat`` (L, 3).
* The result is ``uint8`` of shape (N, ceil(L / 8)) produced by
  ``np.packbits(bits, axis=1, bitorder="little")``: the bit of texel ``j`` for pixel ``i`` is
  ``(vis[i, j // 8] >> (j % 8)) & 1``.
* Bit = 1 means the texel is front-facing (``<n_p, w> > 0``) AND the ray
  ``o_p + t w`` (t > 0) escapes the mesh, with ``o_p = p + offset * n_p`` (``offset`` defaults to
  1e-4 x the mesh's bounding-box diagonal, to avoid self-hits). Back-facing texels are 0.

Rays are cast with embreex (Embree 4) ``OCCLUDED`` queries, directly (not trimesh's ray
engine), from a thread pool over pixel chunks (embreex releases the GIL).

Methods
-------
``"exact"``
    One ray per pixel and front-facing texel (N * L / 2 rays; 41M for N = 10k, 64 x 128).

``"adaptive"`` (default)
    Coarse-to-fine casting. The grid is split into f x f-texel cells (``coarse_factor`` f = 4: a
    16 x 32 cell grid at 64 x 128). Per pixel, each cell is *front* (all its texels
    front-facing), *back* (none: bits 0, no rays) or *horizon* (both), decided by a bound on the
    cell centre's cosine (``|<n, c>| > sin r_c``, r_c the largest centre-to-texel angle) and,
    where that is inconclusive, the exact per-texel test (the same ``<n, w> > 0`` as "exact").

    1. Cast one ray per front cell, through the cell centre.
    2. Horizon cells, by 2 x 2-texel sub-cells: one ray through the centre (normalised mean of
       the texel directions) of each all-front sub-cell, one ray per front-facing texel of the
       sub-cells that the horizon crosses (grazing rays are 5x more often blocked than others
       on a face mesh: 10% vs 2% on the synthetic head).
    3. Per cell, record whether its samples (the centre ray of a front cell, the rays of a
       horizon cell) include occluded and/or free rays. Dilate both flags over the 3 x 3 cell
       neighbourhood (wrapping in azimuth; across a pole, cell (0, c) neighbours
       (0, c + Wc/2)). Cells whose neighbourhood holds both occluded and free samples are
       re-cast at full resolution (both sides of every shadow boundary: all texels of a front
       cell, the sampled sub-cells of a horizon cell); all other cells keep their samples'
       values (a front cell is filled uniformly, free or occluded, from its centre ray).

    Failure mode: an occluder, or a gap in one, that lies within a single cell's interior and
    that no centre ray hits.

    Measured (``f2l.dev.bench_transport.benchmark_transport``: synthetic head of 20,480
    triangles, N = 10,000 pixels, 64 x 128 grid, 2 threads on the shared 2-core dev machine; best
    of 3 interleaved runs, with the range seen over the session under varying background load):

    ==========  ===============  =======  ======================================================
    method      wall s           CPU s    rays
    ==========  ===============  =======  ======================================================
    exact       7.9 (7.9-9.2)    15.5     40.96M
    adaptive    2.17 (2.2-2.7)   4.1      5.97M (2.36M centre, 1.58M horizon, 2.02M re-cast)
    ==========  ===============  =======  ======================================================

    i.e. 3.3-3.8x faster than exact, 6.9x fewer rays (the remaining rays are the expensive,
    grazing or boundary ones; about a third of the adaptive time is numpy bookkeeping).
    exact cost 5.7 s in notes/performance.md on a quieter machine.

    Reuse across the pixel lattice (``pixel_rc`` given; :mod:`f2l.transport.pixel_lattice`):
    only the pixels with even row and column run the steps above; every other pixel copies
    the bits on which its 2 or 4 lattice neighbours agree (all visible, or all front-facing and
    occluded) and casts one ray per remaining front-facing texel (about 8% of them, mostly the
    band near its horizon that some neighbour does not face). Failure mode: a shadow narrower
    than the lattice step that misses all the neighbours; so reuse is used only when the
    median neighbour distance is at most ``MAX_LATTICE_STEP`` (1.2%) of the mesh's bbox
    diagonal (a face of >= ~4.5k pixels). Measured on synthetic faces (``f2l dev bench``, MediaPipe
    canonical mesh of 14,368 triangles, 64 x 128, 2 threads): at 128 px (8.4k face pixels)
    0.49-0.50x the rays of the plain adaptive pass, 1.5-2.0 s instead of 2.5-3.2 s; bits
    differing from exact 0.7-1.3e-4; T l error under a sunny sky 1.9-2.7e-4 (plain adaptive
    2-4e-6); 0.03-0.14% of pixels off by more than 1%. At 64 px (step 1.5% of the diagonal)
    one face in two had a 1.1% T l error, hence the threshold.

    Error of adaptive vs exact: 4.9e-5 of the front-facing bits differ (2.5e-5 of all bits;
    4.0% of pixels have at least one differing bit; every differing texel is a missed grazing
    occlusion within ~3 deg of the pixel's horizon, median 1 deg, so it barely weighs in T).
    Under a sunny sky (``f2l.dev.bench_transport.sunny_sky``: the sun texel carries 10x the
    sky's irradiance, 0.6% of pixels in its cast shadow, no sun bit differs)
    ``||T_a l - T_e l|| / ||T_e l||`` = 2.1e-6, largest per-pixel relative error 9.3e-4
    (99th percentile 9.2e-6). On the flat occluders of the tests (a square over a
    plane, a box beside a slab) the bits are identical.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from threading import Lock

import numpy as np

from f2l.lighting.grid import LatLongGrid
from f2l.transport.pixel_lattice import plan_lattice

__all__ = ["compute_visibility", "visibility_stats", "packed_width", "unpack_bits", "front_cosines",
           "front_mask"]

_MAX_RAYS_PER_CALL = 1 << 20
MAX_LATTICE_STEP = 0.012  # largest pixel-lattice step (/ mesh bbox diagonal) that reuse accepts


def packed_width(grid: LatLongGrid) -> int:
    """Bytes per pixel of the packed visibility: ceil(L / 8)."""
    return (grid.size + 7) // 8


def unpack_bits(vis_bits: np.ndarray, num_texels: int) -> np.ndarray:
    """Unpack (n, ceil(L/8)) uint8 to (n, L) uint8 0/1 (little bit order, row-major texels)."""
    return np.unpackbits(vis_bits, axis=1, count=num_texels, bitorder="little")


# -- embree -------------------------------------------------------------------------------------
class _Scene:
    """An embreex scene for one triangle mesh, committed up front (safe to query from threads)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        from embreex.mesh_construction import TriangleMesh
        from embreex.rtcore_scene import EmbreeScene

        self.vertices = np.ascontiguousarray(vertices, dtype=np.float32)
        self.faces = np.ascontiguousarray(faces, dtype=np.int32)
        self.scene = EmbreeScene()
        # keep a reference to the geometry wrapper for the scene's lifetime
        self._mesh = TriangleMesh(self.scene, self.vertices, self.faces)
        # commit now (the wrapper commits lazily on the first run; avoid a race between threads)
        self.scene.run(np.zeros((1, 3), np.float32), np.array([[0, 1, 0]], np.float32),
                       query="OCCLUDED")

    def same_mesh(self, vertices: np.ndarray, faces: np.ndarray) -> bool:
        return (np.array_equal(self.faces, faces)
                and np.array_equal(self.vertices, np.asarray(vertices, dtype=np.float32)))

    def occluded(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Boolean (n,): True where the ray origins[i] + t directions[i], t > 0, hits the mesh."""
        n = len(origins)
        out = np.empty(n, dtype=bool)
        for s in range(0, n, _MAX_RAYS_PER_CALL):
            e = min(n, s + _MAX_RAYS_PER_CALL)
            r = self.scene.run(
                np.ascontiguousarray(origins[s:e], dtype=np.float32),
                np.ascontiguousarray(directions[s:e], dtype=np.float32),
                query="OCCLUDED",
            )
            out[s:e] = r != -1  # embreex: -1 = ray escaped
        return out

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> dict:
        """First hits: embreex's dict with ``primID`` (-1: missed), barycentrics ``u``, ``v``."""
        return self.scene.run(np.ascontiguousarray(origins, dtype=np.float32),
                              np.ascontiguousarray(directions, dtype=np.float32), output=1)


_LAST_SCENE: list = []  # [the last _Scene built]: a face is rasterised, then ray-cast


def scene_for(vertices: np.ndarray, faces: np.ndarray) -> _Scene:
    """A committed Embree scene of the mesh, reusing the last one built when the mesh is equal
    (embreex copies triangles at ~2 us each: 35 ms for a 14k-triangle face mesh)."""
    last = _LAST_SCENE[0] if _LAST_SCENE else None
    if last is not None and last.same_mesh(vertices, faces):
        return last
    scene = _Scene(vertices, faces)
    _LAST_SCENE[:] = [scene]
    return scene


@dataclass
class _Stats:
    rays: dict = field(default_factory=lambda: {"coarse": 0, "horizon": 0, "refine": 0, "exact": 0,
                                                 "reuse": 0})
    cells: dict = field(default_factory=lambda: {"front": 0, "horizon": 0, "refined": 0,
                                                 "front_texels": 0, "reused_pixels": 0})
    lock: Lock = field(default_factory=Lock)

    def add(self, kind: str, **counts: int) -> None:
        with self.lock:
            d = getattr(self, kind)
            for k, v in counts.items():
                d[k] += int(v)


# -- coarse-cell geometry ---------------------------------------------------------------------
@dataclass(frozen=True)
class _Cells:
    factor: int
    shape: tuple  # (Hc, Wc) cells
    centres_grid: "_Centres"  # cell-centre angles, for front_cosines
    centres32: np.ndarray  # (Lc, 3) float32 cell-centre directions
    sin_radius: np.ndarray  # (Lc,) sin of the largest centre-to-texel-centre angle (+ margin)
    texels: np.ndarray  # (Lc, f*f) flat fine texel indices of each cell, row-major in the cell
    cot_phi: np.ndarray  # (Hc, f) cos / sin of the polar angle of each cell row's texel rows
    sin_theta: np.ndarray  # (Wc, f) sin / cos of the azimuth of each cell column's texel columns
    cos_theta: np.ndarray
    sub_perm: np.ndarray  # (S, G) cell-local texel indices of each g x g sub-cell (g = 2 or 1)
    sub_dirs32: np.ndarray  # (Lc * S, 3) float32 sub-cell sample directions (mean of texels)


@dataclass(frozen=True)
class _Centres:
    """Duck-typed stand-in for LatLongGrid in front_cosines (the coarse height may be odd)."""

    phi_rad: np.ndarray
    theta_rad: np.ndarray


def _coarse_factor(grid: LatLongGrid, factor: int) -> int:
    for f in range(int(factor), 1, -1):
        if grid.height % f == 0 and grid.width % f == 0:
            return f
    return 1


def _cells(grid: LatLongGrid, f: int) -> _Cells:
    hc, wc = grid.height // f, grid.width // f
    # cell centres (a texel corner for even f), same formula as LatLongGrid.directions
    phi = (np.arange(hc) + 0.5) * np.pi / hc
    theta = np.pi * (2.0 * (np.arange(wc) + 0.5) / wc - 1.0)
    centres = np.stack(np.broadcast_arrays(
        np.sin(phi)[:, None] * np.sin(theta), np.cos(phi)[:, None],
        -np.sin(phi)[:, None] * np.cos(theta)), axis=-1).reshape(-1, 3)
    rows = (np.arange(hc)[:, None, None, None] * f + np.arange(f)[None, None, :, None])
    cols = (np.arange(wc)[None, :, None, None] * f + np.arange(f)[None, None, None, :])
    texels = (rows * grid.width + cols).reshape(hc * wc, f * f)
    cos = np.einsum("cjk,ck->cj", grid.directions_flat[texels], centres).min(axis=1)
    radius = np.arccos(np.clip(cos, -1.0, 1.0))
    trows = np.arange(hc)[:, None] * f + np.arange(f)
    tcols = np.arange(wc)[:, None] * f + np.arange(f)
    g = 2 if f % 2 == 0 and f >= 4 else 1
    sub_perm = np.arange(f * f).reshape(f // g, g, f // g, g).transpose(0, 2, 1, 3)
    sub_perm = np.ascontiguousarray(sub_perm.reshape(-1, g * g))
    sub_dirs = grid.directions_flat[texels[:, sub_perm]].sum(axis=2)  # (Lc, S, 3)
    sub_dirs /= np.linalg.norm(sub_dirs, axis=-1, keepdims=True)
    return _Cells(
        factor=f,
        shape=(hc, wc),
        centres_grid=_Centres(phi_rad=phi, theta_rad=theta),
        centres32=centres.astype(np.float32),
        sin_radius=np.sin(radius) + 1e-9,
        texels=np.ascontiguousarray(texels),
        cot_phi=(np.cos(grid.phi_rad) / np.sin(grid.phi_rad))[trows],
        sin_theta=np.sin(grid.theta_rad)[tcols],
        cos_theta=np.cos(grid.theta_rad)[tcols],
        sub_perm=sub_perm,
        sub_dirs32=np.ascontiguousarray(sub_dirs.reshape(-1, 3), dtype=np.float32),
    )


def _dilate3x3(flags: np.ndarray) -> np.ndarray:
    """3 x 3 binary dilation of (n, Hc, Wc) cell flags on the sphere.

    Wraps in azimuth; the neighbour across a pole of cell (0, c) is (0, c + Wc/2) (same at the
    nadir), so the pole rows are padded with their own rows rolled by half the width.
    """
    wc = flags.shape[2]
    top = np.roll(flags[:, :1], wc // 2, axis=2)
    bot = np.roll(flags[:, -1:], wc // 2, axis=2)
    p = np.concatenate([top, flags, bot], axis=1)
    v = p[:, :-2] | p[:, 1:-1] | p[:, 2:]
    return v | np.roll(v, 1, axis=2) | np.roll(v, -1, axis=2)


# -- per-chunk kernels ---------------------------------------------------------------------------
def front_cosines(normals: np.ndarray, grid: LatLongGrid) -> np.ndarray:
    """<n_p, w> for every pixel and texel centre, (n, H, W) float64, by the separable form

        <n, w(phi_r, theta_c)> = sin(phi_r) (n_x sin(theta_c) - n_z cos(theta_c)) + n_y cos(phi_r)

    (3-column matmuls are slow in BLAS). The front-facing test everywhere is ``cos > 0``.
    """
    az = normals[:, 0:1] * np.sin(grid.theta_rad) - normals[:, 2:3] * np.cos(grid.theta_rad)
    cos = np.multiply(np.sin(grid.phi_rad)[None, :, None], az[:, None, :])
    cos += (normals[:, 1:2] * np.cos(grid.phi_rad))[:, :, None]
    return cos


def front_mask(normals: np.ndarray, grid: LatLongGrid) -> np.ndarray:
    """Boolean (n, L): texel centre w_j front-facing for pixel i, ``<n_i, w_j> > 0``.

    Evaluated as a threshold on the separable form of :func:`front_cosines` (every texel centre
    has sin(phi) > 0): ``n_x sin(theta) - n_z cos(theta) > -n_y cos(phi) / sin(phi)``, one
    comparison per texel (10x faster than forming the cosines). This is the front-facing test
    of every method here; it can differ from ``front_cosines > 0`` only where the cosine rounds
    to zero, where a texel carries no weight in T.
    """
    az = normals[:, 0:1] * np.sin(grid.theta_rad) - normals[:, 2:3] * np.cos(grid.theta_rad)
    threshold = -(normals[:, 1:2] * (np.cos(grid.phi_rad) / np.sin(grid.phi_rad)))
    return (az[:, None, :] > threshold[:, :, None]).reshape(len(normals), grid.size)


def _nonzero(mask: np.ndarray) -> tuple:
    """np.nonzero(mask) via flatnonzero (9x faster on large 2-D masks)."""
    return np.unravel_index(np.flatnonzero(mask), mask.shape)


def _cell_texel_front(normals: np.ndarray, cells: "_Cells", pix: np.ndarray,
                      cell: np.ndarray) -> np.ndarray:
    """(m, f*f) bool front-facing test of the texels of cells ``cell`` (row-major within the
    cell) for pixels ``pix``, with the same floating-point operations as front_mask."""
    n = normals[pix]
    row, col = np.divmod(cell, cells.shape[1])
    az = n[:, 0:1] * cells.sin_theta[col] - n[:, 2:3] * cells.cos_theta[col]  # (m, f)
    threshold = -(n[:, 1:2] * cells.cot_phi[row])  # (m, f)
    return (az[:, None, :] > threshold[:, :, None]).reshape(len(cell), -1)


def _take_rows(table: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """table[idx] for a C-contiguous (k, 3) float32 table, gathering 12-byte records (faster)."""
    rec = table.view(np.dtype((np.void, table.dtype.itemsize * table.shape[1]))).ravel()
    return np.take(rec, idx).view(table.dtype).reshape(len(idx), table.shape[1])


def _repeat_rows(origins: np.ndarray, sorted_pix: np.ndarray) -> np.ndarray:
    """origins[sorted_pix] for a non-decreasing pixel index (as np.nonzero returns)."""
    return np.repeat(origins, np.bincount(sorted_pix, minlength=len(origins)), axis=0)


def _exact_chunk(scene: _Scene, origins, normals, grid: LatLongGrid, dirs32, stats: _Stats):
    front = front_mask(normals, grid)
    flat = np.flatnonzero(front)
    occ = scene.occluded(np.repeat(origins, front.sum(axis=1), axis=0),
                         _take_rows(dirs32, flat % grid.size))
    stats.add("rays", exact=len(flat))
    stats.add("cells", front_texels=len(flat))
    bits = np.zeros(front.shape, dtype=bool)
    bits[front] = ~occ  # boolean-mask order == nonzero order (row-major)
    return np.packbits(bits, axis=1, bitorder="little")


def _adaptive_chunk(scene: _Scene, origins, normals, grid: LatLongGrid, dirs32, cells: _Cells,
                    stats: _Stats):
    n = len(origins)
    f = cells.factor
    f2 = f * f
    hc, wc = cells.shape
    lc = hc * wc
    # classify cells: a bound on the centre cosine, then the exact per-texel test where the
    # bound is inconclusive (cells near the pixel's horizon)
    nc = front_cosines(normals, cells.centres_grid).reshape(n, lc)
    front = nc > cells.sin_radius
    pu, cu = _nonzero(np.abs(nc) <= cells.sin_radius)
    front_u = _cell_texel_front(normals, cells, pu, cu)  # (mu, f2)
    all_front = front_u.all(axis=1)
    front[pu[all_front], cu[all_front]] = True
    horizon = front_u.any(axis=1) & ~all_front
    ph, ch, front_h = pu[horizon], cu[horizon], front_u[horizon]
    tex_h = cells.texels[ch]  # (m, f2)

    # 1. one ray per front cell, through its centre
    pf, cf = _nonzero(front)
    occ_c = scene.occluded(_repeat_rows(origins, pf), _take_rows(cells.centres32, cf))

    # 2. horizon cells, by g x g sub-cells: one ray through the centre of each all-front
    #    sub-cell, one ray per front-facing texel of the other sub-cells
    ns, ng = cells.sub_perm.shape
    front_s = front_h[:, cells.sub_perm]  # (m, S, G)
    full_s = front_s.all(axis=2)  # (m, S)
    part_t = front_s & ~full_s[:, :, None]
    tex_s = tex_h[:, cells.sub_perm]  # (m, S, G)
    ms, ss = _nonzero(full_s)
    occ_s = scene.occluded(_repeat_rows(origins, ph[ms]),
                           _take_rows(cells.sub_dirs32, ch[ms] * ns + ss))
    mt, st, gt = _nonzero(part_t)
    occ_t = scene.occluded(_repeat_rows(origins, ph[mt]), _take_rows(dirs32, tex_s[mt, st, gt]))
    m = len(ph)
    free_hs = np.zeros(front_s.shape, dtype=bool)  # (m, S, G): 0 on back-facing texels
    free_hs[mt, st, gt] = ~occ_t
    free_hs[ms, ss] = ~occ_s[:, None]
    h_occ = np.zeros(m, dtype=bool)
    h_occ[mt[occ_t]] = True
    h_occ[ms[occ_s]] = True

    # 3. re-cast cells whose 3x3 neighbourhood holds both occluded and free samples
    has_occ = np.zeros((n, lc), dtype=bool)
    free_c = np.zeros((n, lc), dtype=bool)
    free_c[pf, cf] = ~occ_c
    has_occ[pf, cf] = occ_c
    has_free = free_c.copy()
    has_occ[ph, ch] = h_occ
    has_free[ph, ch] = free_hs.any(axis=(1, 2))
    mixed = _dilate3x3(has_occ.reshape(n, hc, wc)) & _dilate3x3(has_free.reshape(n, hc, wc))
    mixed = mixed.reshape(n, lc)
    pr, cr = _nonzero(front & mixed)
    tex_r = cells.texels[cr]  # (m2, f2): all front-facing
    occ_r = scene.occluded(np.repeat(origins, f2 * np.bincount(pr, minlength=n), axis=0),
                           _take_rows(dirs32, tex_r.reshape(-1)))
    n_recast = len(occ_r)
    if ng > 1:  # ... and, in mixed horizon cells, the texels of the sampled sub-cells
        mr, sr = _nonzero(full_s & mixed[ph, ch][:, None])
        occ_rs = scene.occluded(np.repeat(origins, ng * np.bincount(ph[mr], minlength=n), axis=0),
                                _take_rows(dirs32, tex_s[mr, sr].reshape(-1)))
        free_hs[mr, sr] = ~occ_rs.reshape(-1, ng)
        n_recast += len(occ_rs)

    stats.add("rays", coarse=len(pf), horizon=len(occ_s) + len(occ_t), refine=n_recast)
    stats.add("cells", front=len(pf), horizon=m, refined=len(pr),
              front_texels=f2 * len(pf) + int(front_h.sum()))

    # assemble: uniform cells from the coarse rays, then the finer ones
    bits = np.repeat(np.repeat(free_c.reshape(n, hc, wc), f, axis=1), f, axis=2).reshape(n, -1)
    bits[ph[:, None], tex_s.reshape(m, f2)] = free_hs.reshape(m, f2)
    bits[pr[:, None], tex_r] = ~occ_r.reshape(-1, f2)
    return np.packbits(bits, axis=1, bitorder="little")


def _reuse_chunk(scene: _Scene, origins, front, grid: LatLongGrid, dirs32, source_bits,
                 source_front, stats: _Stats):
    """Interpolated pixels (pixel_lattice): keep the bits on which all sources agree, cast the
    other front-facing texels. front (m, B): the pixels' packed front-facing masks;
    source_bits / source_front (m, k, B): those of each pixel's sources (visible; front)."""
    all_visible = np.bitwise_and.reduce(source_bits, axis=1)
    all_occluded = np.bitwise_and.reduce(source_front & ~source_bits, axis=1)
    cast = front & ~(all_visible | all_occluded)  # (m, B) packed; ~8% of front bits set
    out = front & all_visible
    # unpack only the non-zero bytes of `cast` (rows of the result stay in byte order)
    flat_byte = np.flatnonzero(cast)
    byte_bits = np.unpackbits(cast.reshape(-1)[flat_byte][:, None], axis=1, bitorder="little")
    k, bit = np.nonzero(byte_bits)
    key = flat_byte[k]  # flat byte index (pixel * B + byte) of every ray, non-decreasing
    pix, byte = np.divmod(key, cast.shape[1])
    tex = byte * 8 + bit
    occ = scene.occluded(_repeat_rows(origins, pix), _take_rows(dirs32, tex))
    # OR the free rays' bits back into `out`, one sum per byte (bits within a byte are distinct)
    if len(key):
        value = np.where(occ, 0, np.left_shift(1, bit)).astype(np.uint16)
        first = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        out.reshape(-1)[key[first]] |= np.add.reduceat(value, first).astype(np.uint8)
    stats.add("rays", reuse=len(pix))
    stats.add("cells", front_texels=int(np.unpackbits(front).sum()), reused_pixels=len(front))
    return out


def _map_chunks(n: int, chunk_pixels: int, threads: int, work) -> None:
    """Call work(start, end) over [0, n) in chunks, from a thread pool when threads > 1.

    Chunks are at most ``chunk_pixels`` and at least 4 per thread, so that the last round of a
    stage does not leave a thread idle (5 chunks on 2 threads wasted ~1/6 of the anchor stage).
    """
    if threads > 1:
        chunk_pixels = max(32, min(chunk_pixels, -(-n // (4 * threads))))
    starts = range(0, n, chunk_pixels)
    if threads == 1 or n <= chunk_pixels:
        for s in starts:
            work(s, min(n, s + chunk_pixels))
    else:
        with ThreadPoolExecutor(max_workers=threads) as pool:
            list(pool.map(lambda s: work(s, min(n, s + chunk_pixels)), starts))


# -- public API ---------------------------------------------------------------------------------
def _diagonal(vertices: np.ndarray) -> float:
    """The mesh's bounding-box diagonal (1 for an empty mesh)."""
    return float(np.linalg.norm(vertices.max(0) - vertices.min(0))) if len(vertices) else 1.0


def _prepare(vertices, faces, points, normals, offset):
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"faces must be integer (F, 3), got {faces.shape} {faces.dtype}")
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError("faces index outside the vertex array")
    if points.shape != normals.shape:
        raise ValueError(f"points {points.shape} and normals {normals.shape} differ in shape")
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    if offset is None:
        offset = 1e-4 * _diagonal(vertices)
    origins = (points + float(offset) * normals).astype(np.float32)
    return vertices, faces, origins, normals


def visibility_stats(vertices, faces, points, normals, grid: LatLongGrid = LatLongGrid(),
                     method: str = "adaptive", threads: int | None = 2,
                     offset: float | None = None, coarse_factor: int = 4,
                     chunk_pixels: int | None = None,
                     pixel_rc: np.ndarray | None = None,
                     lattice_levels: int = 1,
                     max_lattice_step: float = MAX_LATTICE_STEP) -> tuple[np.ndarray, dict]:
    """Like :func:`compute_visibility`, also returning counts: rays cast per stage, cells per
    class (adaptive), ``total_rays`` and ``exact_rays`` (what the exact method would cast)."""
    if method not in ("adaptive", "exact"):
        raise ValueError(f"method must be 'adaptive' or 'exact', got {method!r}")
    vertices, faces, origins, normals = _prepare(vertices, faces, points, normals, offset)
    n = len(origins)
    if pixel_rc is not None and len(pixel_rc) != n:
        raise ValueError(f"pixel_rc has {len(pixel_rc)} rows, points {n}")
    out = np.zeros((n, packed_width(grid)), dtype=np.uint8)
    stats = _Stats()
    f = _coarse_factor(grid, coarse_factor) if method == "adaptive" else 1
    if n == 0 or len(faces) == 0:
        # no occluder: visible == front-facing
        front = front_mask(normals, grid)
        out[:] = np.packbits(front, axis=1, bitorder="little")
        return out, {"rays": stats.rays, "cells": stats.cells, "total_rays": 0,
                     "exact_rays": int(front.sum()), "coarse_factor": f,
                     "lattice": {"levels": 0, "step_rel": None}}
    scene = scene_for(vertices, faces)
    dirs32 = grid.directions_flat.astype(np.float32)
    cells = _cells(grid, f) if f > 1 else None
    if chunk_pixels is None:
        chunk_pixels = 256 if cells is None else 512
    threads = max(1, int(threads or os.cpu_count() or 1))

    def direct(idx: np.ndarray):
        def work(s: int, e: int) -> None:
            sel = idx[s:e]
            if cells is None:
                out[sel] = _exact_chunk(scene, origins[sel], normals[sel], grid, dirs32, stats)
            else:
                out[sel] = _adaptive_chunk(scene, origins[sel], normals[sel], grid, dirs32,
                                           cells, stats)
        _map_chunks(len(idx), chunk_pixels, threads, work)

    plan = (plan_lattice(pixel_rc, lattice_levels) if pixel_rc is not None and cells is not None
            else None)
    lattice = {"levels": 0, "step_rel": None}
    if plan is not None and plan.steps:
        # the lattice must be fine against the mesh: shadows narrower than a step are missed
        pixels, sources = plan.steps[0]  # the coarsest step
        step = np.median(np.linalg.norm(origins[pixels] - origins[sources[:, 0]], axis=1))
        lattice["step_rel"] = float(step / _diagonal(vertices))
        if lattice["step_rel"] > max_lattice_step:
            plan = None
        else:
            lattice["levels"] = int(lattice_levels)
    if plan is None or not plan.steps:
        direct(np.arange(n))
    else:
        direct(plan.anchors)
        front = np.zeros_like(out)

        def front_bits(s: int, e: int) -> None:
            front[s:e] = np.packbits(front_mask(normals[s:e], grid), axis=1, bitorder="little")
        _map_chunks(n, 4 * chunk_pixels, threads, front_bits)
        for pixels, sources in plan.steps:
            def reuse(s: int, e: int) -> None:
                sel, src = pixels[s:e], sources[s:e]
                out[sel] = _reuse_chunk(scene, origins[sel], front[sel], grid, dirs32, out[src],
                                        front[src], stats)
            _map_chunks(len(pixels), chunk_pixels, threads, reuse)
    info = {
        "rays": dict(stats.rays),
        "cells": dict(stats.cells),
        "total_rays": int(sum(stats.rays.values())),
        "exact_rays": stats.cells["front_texels"],
        "coarse_factor": f,
        "lattice": lattice,
    }
    return out, info


def compute_visibility(vertices, faces, points, normals, grid: LatLongGrid = LatLongGrid(),
                       method: str = "adaptive", threads: int | None = 2,
                       offset: float | None = None, coarse_factor: int = 4,
                       chunk_pixels: int | None = None,
                       pixel_rc: np.ndarray | None = None,
                       lattice_levels: int = 1,
                       max_lattice_step: float = MAX_LATTICE_STEP) -> np.ndarray:
    """Packed visibility bits (N, ceil(L/8)) uint8 of ``grid``'s texels from each pixel.

    vertices (V, 3), faces (F, 3) int: the occluding triangle mesh (world frame).
    points (N, 3), normals (N, 3): the face pixels' surface points and (shading) normals.
    Bit j of pixel i (``np.packbits(..., bitorder="little")`` over the row-major texel index)
    is 1 iff ``<n_i, w_j> > 0`` and the ray from ``points[i] + offset * n_i`` along w_j
    escapes the mesh. ``offset`` defaults to 1e-4 x the mesh bbox diagonal.
    method: "adaptive" (default, near-exact, see the module docstring for its error) or
    "exact". threads: worker threads (None: all cores). coarse_factor: cell size in texels
    per axis for "adaptive" (reduced to a divisor of the grid; 1 means exact).
    pixel_rc (N, 2) int, optional: the pixels' (row, column) on the photo; with "adaptive" it
    turns on reuse across the pixel lattice (:mod:`f2l.transport.pixel_lattice`) with
    ``lattice_levels`` levels, provided the lattice step is at most ``max_lattice_step`` x the
    mesh bbox diagonal (otherwise every pixel is cast; ``visibility_stats`` reports which).
    """
    return visibility_stats(vertices, faces, points, normals, grid, method=method,
                            threads=threads, offset=offset, coarse_factor=coarse_factor,
                            chunk_pixels=chunk_pixels, pixel_rc=pixel_rc,
                            lattice_levels=lattice_levels,
                            max_lattice_step=max_lattice_step)[0]
