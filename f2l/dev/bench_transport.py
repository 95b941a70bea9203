"""Benchmark of visibility / transport on a synthetic head-like mesh.

``python -m f2l.dev.bench_transport [n_pixels] [threads]`` prints the figures as JSON.
The mesh is an icosphere (radius 1, centred at the origin) with a Gaussian 'nose' bump towards
the camera (+Z), two eye sockets (dents) and a chin ridge, so front pixels see real
self-occlusion. Pixels are sampled on front-facing triangles (z > 0 side) with barycentric
points and interpolated vertex normals.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from f2l.lighting.grid import LatLongGrid, direction_from_angles
from f2l.transport.operator import Transport
from f2l.transport.visibility import unpack_bits, visibility_stats

__all__ = ["synthetic_head", "sample_pixels", "sunny_sky", "benchmark_transport"]


def synthetic_head(subdivisions: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64, faces (F, 3) int64) of a unit sphere with a nose, eye sockets and
    a chin. subdivisions = 5 gives 20,480 triangles."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v = np.asarray(sphere.vertices, dtype=np.float64)
    d = v / np.linalg.norm(v, axis=1, keepdims=True)

    def bump(centre, sigma_rad, height):
        c = np.asarray(centre, dtype=np.float64)
        c = c / np.linalg.norm(c)
        ang = np.arccos(np.clip(d @ c, -1.0, 1.0))
        return height * np.exp(-0.5 * (ang / sigma_rad) ** 2)

    r = 1.0
    r = r + bump([0.0, -0.05, 1.0], 0.16, 0.40)  # nose
    r = r - bump([0.35, 0.25, 1.0], 0.14, 0.12)  # eye sockets
    r = r - bump([-0.35, 0.25, 1.0], 0.14, 0.12)
    r = r + bump([0.0, -0.75, 1.0], 0.20, 0.10)  # chin
    r = r + bump([0.0, 0.55, 1.0], 0.35, 0.06)  # brow
    return d * r[:, None], np.asarray(sphere.faces, dtype=np.int64)


def sample_pixels(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int = 0,
                  min_facing: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """n (point, unit normal) samples on triangles whose normal has z > min_facing (facing the
    camera), area-weighted, barycentric points and interpolated vertex normals."""
    import trimesh

    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    fn = mesh.face_normals
    ok = np.nonzero(fn[:, 2] > min_facing)[0]
    prob = mesh.area_faces[ok] / mesh.area_faces[ok].sum()
    rng = np.random.default_rng(seed)
    fi = ok[rng.choice(len(ok), size=n, p=prob)]
    b = rng.random((n, 2))
    flip = b.sum(1) > 1.0
    b[flip] = 1.0 - b[flip]
    bary = np.column_stack([1.0 - b.sum(1), b])
    tri = faces[fi]
    points = np.einsum("nk,nkd->nd", bary, vertices[tri])
    normals = np.einsum("nk,nkd->nd", bary, mesh.vertex_normals[tri])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return points, normals


def sunny_sky(grid: LatLongGrid, elevation_rad: float = np.radians(35.0),
              azimuth_rad: float = np.radians(120.0), sun_to_sky: float = 10.0) -> np.ndarray:
    """(L, 3) radiance: 1 on the upper hemisphere, 0.3 below, plus one sun texel whose
    irradiance (radiance x solid angle) is ``sun_to_sky`` x the sky's (pi for unit radiance)."""
    l = np.where(grid.upper_mask.reshape(-1), 1.0, 0.3)
    row, col = grid.direction_to_texel(direction_from_angles(elevation_rad, azimuth_rad))
    j = int(row) * grid.width + int(col)
    l = l.copy()
    l[j] += sun_to_sky * np.pi / grid.solid_angles_flat[j]
    return np.repeat(l[:, None], 3, axis=1) * np.array([1.0, 0.9, 0.8])


def benchmark_transport(n_pixels: int = 10000, grid: LatLongGrid = LatLongGrid(64, 128),
                        threads: int = 2, subdivisions: int = 5, seed: int = 0,
                        repeats: int = 1) -> dict:
    """Time exact and adaptive visibility on the synthetic head; compare them.

    Returns wall times (s, best of ``repeats``) and their process CPU seconds, rays and
    Mrays/s, bit disagreement of adaptive vs exact (over all bits and over front-facing bits),
    the relative error of T @ l under :func:`sunny_sky` (global Frobenius ratio and max / 99th
    percentile per pixel), the fraction of front rays occluded, memory of packed bits vs dense
    float32 T (MiB), and the times of ``Transport.project`` (K = 25), ``dense`` and ``matmul``.
    """
    vertices, faces = synthetic_head(subdivisions)
    points, normals = sample_pixels(vertices, faces, n_pixels, seed=seed)
    res: dict = {"n_pixels": n_pixels, "grid": list(grid.shape), "threads": threads,
                 "triangles": int(len(faces))}

    cpu: dict = {}

    def run(method):
        best, out = np.inf, None
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            out = visibility_stats(vertices, faces, points, normals, grid, method=method,
                                   threads=threads)
            wall = time.perf_counter() - t0
            if wall < best:
                best, cpu[method] = wall, time.process_time() - c0
        return best, out

    t_adapt, (bits_adapt, st_adapt) = run("adaptive")
    t_exact, (bits_exact, st_exact) = run("exact")
    # CPU seconds of this process: a load-independent companion to the wall times on a shared
    # machine (wall ~ cpu / threads when the cores are free)
    res.update(exact_cpu_s=cpu["exact"], adaptive_cpu_s=cpu["adaptive"])
    r_exact, r_adapt = st_exact["total_rays"], st_adapt["total_rays"]
    res.update(
        exact_s=t_exact, adaptive_s=t_adapt, speedup=t_exact / t_adapt,
        exact_rays=r_exact, adaptive_rays=r_adapt, adaptive_rays_by_stage=st_adapt["rays"],
        exact_mrays_per_s=r_exact / t_exact / 1e6,
        adaptive_mrays_per_s=r_adapt / t_adapt / 1e6,
    )
    # single-thread exact for the threading speed-up (only on a subset: it is slow)
    if threads > 1:
        sub = slice(0, min(n_pixels, 2000))
        t0 = time.perf_counter()
        visibility_stats(vertices, faces, points[sub], normals[sub], grid, method="exact",
                         threads=1)
        t1 = time.perf_counter() - t0
        t0 = time.perf_counter()
        visibility_stats(vertices, faces, points[sub], normals[sub], grid, method="exact",
                         threads=threads)
        res["thread_speedup_exact"] = t1 / (time.perf_counter() - t0)

    L = grid.size
    ue = unpack_bits(bits_exact, L).astype(bool)
    ua = unpack_bits(bits_adapt, L).astype(bool)
    front = (normals @ grid.directions_flat.T) > 0
    diff = ue != ua
    res["bits_differ_frac"] = float(diff.mean())
    res["front_bits_differ_frac"] = float(diff.sum() / front.sum())
    res["pixels_with_any_diff_frac"] = float(diff.any(1).mean())
    res["occluded_front_frac"] = float(1.0 - ue.sum() / front.sum())

    te = Transport(bits_exact, normals, grid)
    ta = Transport(bits_adapt, normals, grid)
    l = sunny_sky(grid)
    se = te.matmul(l, dtype=np.float64)
    sa = ta.matmul(l, dtype=np.float64)
    err = np.linalg.norm(sa - se, axis=1) / np.maximum(np.linalg.norm(se, axis=1), 1e-12)
    res["shading_rel_err"] = float(np.linalg.norm(sa - se) / np.linalg.norm(se))
    res["shading_rel_err_pixel_max"] = float(err.max())
    res["shading_rel_err_pixel_p99"] = float(np.percentile(err, 99))
    # the sun's cast shadow is where the error would matter most
    j = int(np.argmax(l[:, 0]))
    in_shadow = front[:, j] & ~ue[:, j]
    res["sun_shadow_pixel_frac"] = float(in_shadow.mean())
    res["sun_bit_differ_frac"] = float(diff[:, j].mean())
    res["packed_bits_mib"] = te.nbytes / 2**20
    res["dense_float32_mib"] = n_pixels * L * 4 / 2**20

    basis = np.random.default_rng(seed).standard_normal((L, 25))
    for th in sorted({1, threads}):
        te.threads = th
        best = np.inf
        for _ in range(3):
            t0 = time.perf_counter()
            te.project(basis)
            best = min(best, time.perf_counter() - t0)
        res[f"project_k25_threads{th}_s"] = best
    te.threads = threads
    t0 = time.perf_counter()
    te.dense()
    res["dense_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    te.matmul(l)
    res["matmul_c3_s"] = time.perf_counter() - t0
    return res


if __name__ == "__main__":  # pragma: no cover
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 10000
    th = int(sys.argv[2]) if len(sys.argv) > 2 else 2
    rep = int(sys.argv[3]) if len(sys.argv) > 3 else 1
    print(json.dumps(benchmark_transport(n_pixels=n, threads=th, repeats=rep), indent=1))
