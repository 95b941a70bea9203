"""``f2l dev bench``: error versus run time of the installed lighting models on synthetic faces.

For each face (≈10k pixels at image_size 128, 64x128 grid by default) it times the transport build
(Embree visibility, adaptive and exact) once, then each model's estimate split into precompute
(T@B projection or low-rank factor) and fit, and scores the estimate with the seven §5.1 metrics.
Prints a Markdown table (time, throughput, peak memory, error) and writes a PNG plot of each
lighting metric against seconds per face.
"""

from __future__ import annotations

import json
import resource
import time
from pathlib import Path

import numpy as np

from f2l.dev.bench_transport import sunny_sky
from f2l.estimate import EstimationError, EstimatorConfig, FaceObservation, estimate
from f2l.io.atomic import write_text_atomic
from f2l.lighting.grid import LatLongGrid
from f2l.metrics import METRIC_NAMES, evaluate_pair
from f2l.metrics.lighting import sun_energy_fraction
from f2l.models.capabilities import declared
from f2l.models.registry import ModelNotFoundError, discover, load_model
from f2l.report.plots import log_time_axis
from f2l.synth.render import make_synthetic_set
from f2l.transport import Transport, compute_visibility, visibility_stats


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def visibility_error(bits: np.ndarray, exact: np.ndarray, normals: np.ndarray, grid: LatLongGrid) -> dict:
    """How far packed visibility ``bits`` is from ``exact``: the fraction of differing bits, and
    the shading error under a sunny sky (bench_transport.sunny_sky: the sun texel carries 10x
    the sky's irradiance), as ||T_a l - T_e l|| / ||T_e l|| and the fraction of pixels whose
    shading is off by more than 1%."""
    l = sunny_sky(grid)
    approx = Transport(bits, normals, grid).matmul(l)
    ref = Transport(exact, normals, grid).matmul(l)
    per_pixel = np.abs(approx - ref).max(axis=1) / np.maximum(np.abs(ref).max(axis=1), 1e-12)
    return {
        "bits_differ": float(np.unpackbits(bits ^ exact).sum() / (len(bits) * grid.size)),
        "sunny_rel_error": float(np.linalg.norm(approx - ref) / max(np.linalg.norm(ref), 1e-12)),
        "pixels_over_1pct": float(np.mean(per_pixel > 0.01)),
    }


def run_bench(
    faces: int = 1,
    models: list[str] | None = None,
    out_dir: Path = Path("bench_out"),
    image_size: int = 128,
    grid: LatLongGrid = LatLongGrid(),
    threads: int = 2,
    seed: int = 1,
    exact_visibility: bool = True,
    sun_skip_faces: int = 2,
) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = models or [n for n, info in discover().items() if info.ok]
    transport_rows = []
    model_rows: dict[str, list[dict]] = {n: [] for n in names}
    warmed: set[str] = set()
    for face in make_synthetic_set(faces, grid, seed, image_size=image_size, threads=threads):
        t0 = time.perf_counter()
        bits, vis_info = visibility_stats(face.vertices, face.faces, face.points, face.normals, grid, method="adaptive", threads=threads, pixel_rc=face.pixel_rc)
        adaptive_s = time.perf_counter() - t0
        row = {"pixels": face.num_pixels, "adaptive_s": adaptive_s, "adaptive_rays": vis_info["total_rays"], "exact_rays": vis_info["exact_rays"]}
        if exact_visibility:
            t0 = time.perf_counter()
            exact = compute_visibility(face.vertices, face.faces, face.points, face.normals, grid, method="exact", threads=threads)
            row["exact_s"] = time.perf_counter() - t0
            row.update(visibility_error(bits, exact, face.normals, grid))
        transport_rows.append(row)
        sky = face.meta.get("sky", {})
        overcast = sky.get("kind") == "overcast"
        gt_sun = None if overcast or sky.get("sun_direction") is None else np.asarray(sky["sun_direction"])
        obs = FaceObservation(face.normals, face.observed_rgb, face.mask, bits, grid, points=face.points)
        for name in names:
            try:  # a plugin that is refused (capabilities) or fails to load is a row, not a crash
                model = load_model(name, grid)
            except ModelNotFoundError as exc:
                model_rows[name].append({"error": str(exc)})
                continue
            if name not in warmed:  # one untimed run: imports and caches are not per-face costs
                warmed.add(name)
                try:
                    estimate(obs, model, EstimatorConfig(threads=threads))
                except Exception:  # noqa: BLE001 - reported by the timed run below
                    pass
            try:
                res = estimate(obs, model, EstimatorConfig(threads=threads))
            except EstimationError as exc:
                model_rows[name].append({"error": str(exc)})
                continue
            except Exception as exc:  # noqa: BLE001 - a plugin's own error: name the model and its class
                caps = ", ".join(declared(model)) or "none"
                model_rows[name].append({"error": f"{name} ({type(model).__module__}:{type(model).__qualname__}, "
                                                  f"capabilities: {caps}): {type(exc).__name__}: {exc}"})
                continue
            metrics = evaluate_pair(res.probe, face.gt_probe, grid, overcast=overcast, est_sun_dir=res.sun_direction, gt_sun_dir=gt_sun)
            model_rows[name].append({**res.timings, **metrics, "iterations": res.iterations})

    lines = []
    tr = transport_rows
    lines.append(f"Transport ({len(tr)} face(s), {np.mean([r['pixels'] for r in tr]):.0f} pixels, grid {grid.height}x{grid.width}, {threads} threads)")
    lines.append("")
    lines.append("| visibility | time per face (s) | Mrays cast | bits differing from exact | T·l error, sunny sky | pixels > 1% off |")
    lines.append("|---|---|---|---|---|---|")
    mean = lambda key: float(np.mean([r[key] for r in tr]))  # noqa: E731
    median = lambda key: float(np.median([r[key] for r in tr]))  # noqa: E731
    err = (f"{mean('bits_differ'):.2e} | {mean('sunny_rel_error'):.2e} | {mean('pixels_over_1pct'):.2%} |"
           if exact_visibility else "- | - | - |")
    lines.append(f"| adaptive | {median('adaptive_s'):.3f} | {mean('adaptive_rays') / 1e6:.2f} | " + err)
    if exact_visibility:
        lines.append(f"| exact | {median('exact_s'):.3f} | {mean('exact_rays') / 1e6:.2f} | 0 | 0 | 0 |")
    lines.append("")
    lines.append("Times are medians over the faces (the shared machine's noise is one-sided); errors are "
                 "means. Per-face figures are in bench.json.")
    lines.append("")
    head = ["model", "faces", "precompute (s)", "fit (s)", "total (s)", "faces/min"] + list(METRIC_NAMES)
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "---|" * len(head))
    summary = {}
    for name, rows in model_rows.items():
        ok = [r for r in rows if "error" not in r]
        if not ok:
            lines.append(f"| {name} | 0 | failed: {rows[0]['error'] if rows else 'no faces'} |")
            continue
        mean = {k: float(np.nanmean([r[k] for r in ok])) if not all(np.isnan(r[k]) for r in ok) else float("nan")
                for k in METRIC_NAMES}
        mean.update({k: float(np.median([r[k] for r in ok])) for k in ["precompute_s", "fit_s", "total_s"]})
        if all("search_s" in r for r in ok):  # sun models: the search is part of the fit column
            mean["search_s"] = float(np.median([r["search_s"] for r in ok]))
        summary[name] = mean
        fit = f"{mean['fit_s']:.3f}" + (f" (+{mean['search_s']:.3f} search)" if "search_s" in mean else "")
        cells = [name, str(len(ok)), f"{mean['precompute_s']:.3f}", fit, f"{mean['total_s']:.3f}",
                 f"{60.0 / mean['total_s']:.0f}"] + [f"{mean[m]:.4g}" for m in METRIC_NAMES]
        lines.append("| " + " | ".join(cells) + " |")
    installed = discover()
    for name in names:  # every compact-sun model: what skipping the exact sun core saves when overcast
        if sun_skip_faces > 0 and name in summary and "compact-sun" in installed[name].capabilities:
            lines.append("")
            lines.extend(_sun_core_skip_table(name, sun_skip_faces, grid, threads, seed, image_size))
    lines.append("")
    lines.append(f"peak memory (RSS): {_peak_rss_mb():.0f} MiB")
    markdown = "\n".join(lines)
    table_md = out_dir / "bench.md"
    write_text_atomic(table_md, markdown + "\n")
    write_text_atomic(out_dir / "bench.json", json.dumps({"transport": transport_rows, "models": summary, "per_face": model_rows}, indent=2))
    plot_png = out_dir / "error_vs_runtime.png"
    _plot(summary, plot_png)
    return {"markdown": markdown, "table_md": str(table_md), "plot_png": str(plot_png), "summary": summary, "transport": transport_rows}


def _sun_core_skip_table(name: str, n: int, grid: LatLongGrid, threads: int, seed: int, image_size: int) -> list[str]:
    """A compact-sun model on ``n`` overcast faces with and without the exact sun core: what
    skipping it saves."""
    model = load_model(name, grid)
    rows = {"skipped when overcast (default)": [], "always exact": []}
    for face in make_synthetic_set(n, grid, seed + 1000, image_size=image_size, threads=threads, overcast_fraction=1.0):
        obs = FaceObservation(face.normals, face.observed_rgb, face.mask, face.visibility_bits, grid, points=face.points)
        for label, share in (("skipped when overcast (default)", 0.02), ("always exact", 0.0)):
            res = estimate(obs, model, EstimatorConfig(threads=threads, sun_core_min_share=share))
            m = evaluate_pair(res.probe, face.gt_probe, grid, overcast=True)
            rows[label].append((res.timings["fit_s"], res.timings["sun_core"], m["Full-dω MAE (l)"],
                                sun_energy_fraction(res.probe, grid) - sun_energy_fraction(face.gt_probe, grid)))
    out = [f"{name} on {n} overcast face(s): the exact sun core (sky_transport.py) is left out once the "
           "solution has no sun (share < 0.02 after the all-starts phase)",
           "", "| sun core | fit (s) | faces with core | Full-dω MAE (l) | sun share − truth |", "|---|---|---|---|---|"]
    for label, r in rows.items():
        a = np.array(r)
        out.append(f"| {label} | {np.median(a[:, 0]):.3f} | {int(a[:, 1].sum())}/{len(a)} | {a[:, 2].mean():.4g} | {a[:, 3].mean():+.3f} |")
    return out


def _plot(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 4, figsize=(14, 6.5))
    for ax, metric in zip(axes.ravel(), METRIC_NAMES):
        for name, mean in summary.items():
            ax.scatter(mean["total_s"], mean[metric], s=40)
            ax.annotate(name, (mean["total_s"], mean[metric]), fontsize=8, xytext=(3, 3), textcoords="offset points")
        log_time_axis(ax, [m["total_s"] for m in summary.values()])
        ax.set_xlabel("seconds per face")
        ax.set_title(metric, fontsize=9)
        ax.grid(alpha=0.3)
    axes.ravel()[-1].axis("off")
    fig.suptitle("f2l dev bench: error vs run time (synthetic faces)")
    fig.tight_layout()
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=90)
    plt.close(fig)
    tmp.replace(path)
