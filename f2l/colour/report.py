"""Calibration reports: a Markdown ΔE2000 table and a PNG of corrected vs reference swatches.

The PNG has the photo (downscaled, detected patch squares drawn: green = used, red = excluded)
above a 4 × 6 swatch grid in chart order. Each swatch is split in two halves: left = the measured
patch after the full correction, right = the reference, both sRGB-encoded from linear Rec.709
without scaling (white patch ≈ 0.88); each is labelled with its patch number and ΔE2000 after
correction ("x" and a red frame mark an excluded patch). Files are written atomically.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from f2l.colour.chart import CHART_COLS, CHART_ROWS, srgb_encode_uint8
from f2l.colour.detect import ChartDetection
from f2l.colour.fit import ChartFit
from f2l.io.atomic import atomic_path

SWATCH_PX = 96
GAP_PX = 8


def _fmt(value: float) -> str:
    return "–" if not np.isfinite(value) else f"{value:.2f}"


def delta_e_table(fit: ChartFit, detection: ChartDetection | None = None, *, title: str = "",
                  status: str | None = None, reason: str | None = None) -> str:
    """Markdown table: per patch ΔE2000 before (white balance + exposure only) and after correction.

    ``status``/``reason`` default to the fit's own (``ok``/``identity``).
    """
    reasons = detection.reasons if detection is not None else ["" if v else "excluded" for v in fit.valid]
    status, reason = (fit.status if status is None else status), (fit.reason if reason is None else reason)
    lines = [f"## {title}", ""] if title else []
    lines += [f"Method: {fit.correction.method}; chart: {fit.reference.edition}; status: {status}"
              + (f" ({reason})" if reason else ""), "",
              "| patch | name | used | ΔE00 before | ΔE00 after |", "|---:|---|---|---:|---:|"]
    for i, name in enumerate(fit.reference.names):
        used = "yes" if fit.valid[i] else f"no: {reasons[i] or 'excluded'}"
        lines.append(f"| {i + 1} | {name} | {used} | {_fmt(fit.delta_e_before[i])} | {_fmt(fit.delta_e_after[i])} |")
    stats = fit.stats()
    for stat in ("mean", "median", "max"):
        lines.append(f"| {stat} (used patches) | | | {_fmt(stats[f'{stat}_delta_e_before'])} | "
                     f"{_fmt(stats[f'{stat}_delta_e_after'])} |")
    return "\n".join(lines) + "\n"


def swatch_image(fit: ChartFit) -> np.ndarray:
    """(H, W, 3) uint8 RGB swatch grid: left half corrected measurement, right half reference."""
    height = CHART_ROWS * SWATCH_PX + (CHART_ROWS + 1) * GAP_PX
    width = CHART_COLS * SWATCH_PX + (CHART_COLS + 1) * GAP_PX
    image = np.full((height, width, 3), 24, np.uint8)
    corrected = srgb_encode_uint8(np.where(np.isfinite(fit.corrected_rgb), fit.corrected_rgb, 0.0))
    reference = srgb_encode_uint8(fit.reference.rgb)
    half = SWATCH_PX // 2
    for i in range(CHART_ROWS * CHART_COLS):
        row, col = divmod(i, CHART_COLS)
        y, x = GAP_PX + row * (SWATCH_PX + GAP_PX), GAP_PX + col * (SWATCH_PX + GAP_PX)
        image[y:y + SWATCH_PX, x:x + half] = corrected[i]
        image[y:y + SWATCH_PX, x + half:x + SWATCH_PX] = reference[i]
        lum = float(fit.reference.rgb[i] @ [0.2126, 0.7152, 0.0722])
        ink = (0, 0, 0) if lum > 0.25 else (255, 255, 255)
        label = f"{i + 1} " + ("x" if not fit.valid[i] else f"{fit.delta_e_after[i]:.1f}")
        cv2.putText(image, label, (x + 4, y + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, ink, 1, cv2.LINE_AA)
        if not fit.valid[i]:
            cv2.rectangle(image, (x + 1, y + 1), (x + SWATCH_PX - 2, y + SWATCH_PX - 2), (255, 0, 0), 3)
    return image


def detection_overlay(display: np.ndarray, detection: ChartDetection, width: int) -> np.ndarray:
    """The display image scaled to ``width`` px with patch squares (green used, red excluded)."""
    scale = width / display.shape[1]
    image = cv2.resize(display, (width, max(1, round(display.shape[0] * scale))), interpolation=cv2.INTER_AREA)
    for polygon, reason in zip(detection.patch_polygons, detection.reasons):
        pts = np.round(polygon * scale * 4).astype(np.int32)
        cv2.polylines(image, [pts], True, (255, 0, 0) if reason else (0, 255, 0), 1, cv2.LINE_AA, shift=2)
    return image


def report_image(fit: ChartFit, detection: ChartDetection | None = None,
                 display: np.ndarray | None = None) -> np.ndarray:
    """Overlay (when ``display`` and ``detection`` are given) stacked above the swatch grid, uint8 RGB."""
    swatches = swatch_image(fit)
    if display is None or detection is None:
        return swatches
    overlay = detection_overlay(np.asarray(display, np.uint8), detection, swatches.shape[1])
    return np.concatenate([overlay, swatches], axis=0)


def write_png_atomic(path: str | os.PathLike, rgb: np.ndarray) -> Path:
    """Write an (H, W, 3) uint8 RGB image as PNG, atomically."""
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(encoded.tobytes())
    return Path(path)


def write_report(fit: ChartFit, png_path: str | os.PathLike, table_path: str | os.PathLike, *,
                 detection: ChartDetection | None = None, display: np.ndarray | None = None,
                 title: str = "", status: str | None = None, reason: str | None = None) -> tuple[Path, Path]:
    """Write the report PNG and the Markdown ΔE table atomically; returns both paths."""
    write_png_atomic(png_path, report_image(fit, detection, display))
    text = delta_e_table(fit, detection, title=title, status=status, reason=reason)
    with atomic_path(table_path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    return Path(png_path), Path(table_path)
