"""``f2l calibrate``: ColorChecker photos → colour corrections, ``colour.parquet`` and reports.

Output directory layout::

    OUT/colour.parquet         one row per photo (schema ``colour``), written atomically at the end
    OUT/reports/<stem>.png     photo with detected patches above corrected | reference swatches
    OUT/reports/<stem>.md      per-patch ΔE2000 table (before: white balance + exposure; after)

Per-photo status: ``ok`` (all 24 patches used), ``partial`` (some excluded, named in the
reason), ``identity`` (chart found, too few usable patches: identity correction), ``no_chart``,
``error`` (unreadable photo or unexpected failure). One bad photo never stops the batch; rows
that were not fitted carry the identity correction, so :func:`apply_correction` is always safe.
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from f2l.colour.chart import DEFAULT_EDITION, reference_chart
from f2l.colour.detect import VARIANTS, ChartDetection, detect_chart
from f2l.colour.fit import ChartFit, ColourCorrection, apply_correction, fit_correction, resolve_method
from f2l.io.progress import Progress, ProgressCallback

__all__ = ["CalibrationResult", "apply_correction", "calibrate", "calibrate_photo", "format_summary",
           "read_corrections", "summarise"]

TABLE_NAME = "colour.parquet"
REPORTS_DIR = "reports"
SCHEMA = "colour"


@dataclass
class CalibrationResult:
    """What became of one chart photo; ``correction`` is the identity unless the fit succeeded."""

    source_path: str
    status: str  # ok | partial | identity | no_chart | error
    reason: str
    correction: ColourCorrection
    edition: str
    camera: str = ""
    detection: ChartDetection | None = None
    fit: ChartFit | None = None
    report_png: str | None = None
    report_table: str | None = None
    seconds: float = 0.0

    def row(self) -> dict:
        """The ``colour`` table row of this result."""
        corr = self.correction.to_dict()
        stats = self.fit.stats() if self.fit is not None else {}
        finite = {k: (v if np.isfinite(v) else None) for k, v in stats.items()}
        names = reference_chart(self.edition).names
        excluded = [] if self.detection is None else [
            {"patch": number, "name": names[number - 1], "reason": reason}
            for number, reason in self.detection.excluded]
        return {
            "source_path": self.source_path, "status": self.status, "reason": self.reason, "camera": self.camera,
            "chart_edition": self.edition, "method": corr["method"], "gains": np.asarray(corr["gains"]),
            "matrix": np.asarray(corr["matrix"]), "n_terms": corr["n_terms"], "degree": corr["degree"],
            "exposure_gain": corr["exposure_gain"],
            "n_valid_patches": int(self.fit.valid.sum()) if self.fit is not None else 0,
            "excluded_json": json.dumps(excluded), "patches_json": json.dumps(self._patches(names)),
            "detector_variant": self.detection.variant if self.detection is not None else "",
            "mcc_cost": self.detection.mcc_cost if self.detection is not None else None,
            **{f"{stat}_delta_e_{when}": finite.get(f"{stat}_delta_e_{when}")
               for when in ("before", "after") for stat in ("mean", "median", "max")},
            "report_png": self.report_png, "report_table": self.report_table, "seconds": round(self.seconds, 4),
        }

    def _patches(self, names) -> list[dict]:
        if self.fit is None:
            return []

        def num(v):
            return float(v) if np.isfinite(v) else None

        reasons = self.detection.reasons if self.detection is not None else [""] * len(names)
        return [{"patch": i + 1, "name": names[i],
                 "rgb": [num(v) for v in self.fit.measured_rgb[i]] if np.isfinite(self.fit.measured_rgb[i]).all()
                 else None,
                 "used": bool(self.fit.valid[i]), "reason": reasons[i],
                 "delta_e_before": num(self.fit.delta_e_before[i]), "delta_e_after": num(self.fit.delta_e_after[i])}
                for i in range(len(names))]


def _camera(exif: dict) -> str:
    return " ".join(str(exif[k]).strip() for k in ("make", "model") if exif.get(k)).strip()


def calibrate_photo(display: np.ndarray, linear: np.ndarray, *, clipped: np.ndarray | None = None,
                    edition: str = DEFAULT_EDITION, method: str = "3x3", source: str = "photo"):
    """(status, reason, detection, fit) for one decoded photo; no files are written."""
    log: list[str] = []
    detection = detect_chart(display, linear, clipped=clipped, log=log)
    if detection is None:
        tried = "; ".join(log) or ", ".join(VARIANTS)
        return "no_chart", f"{source}: no ColorChecker Classic found ({tried})", None, None
    fit = fit_correction(detection.rgb, detection.valid, method=method, edition=edition)
    excluded = ", ".join(f"{n} ({r})" for n, r in detection.excluded)
    if fit.status != "ok":
        return "identity", f"{source}: {fit.reason}" + (f"; excluded {excluded}" if excluded else ""), detection, fit
    if excluded:
        return "partial", f"{source}: {len(detection.excluded)} patches excluded: {excluded}", detection, fit
    return "ok", "", detection, fit


def _report_stem(path: Path, used: set[str]) -> str:
    stem = re.sub(r"[^A-Za-z0-9._+=@#-]", "_", path.stem).lstrip("._-+=@#") or "photo"
    candidate, k = stem, 2
    while candidate in used:
        candidate, k = f"{stem}-{k}", k + 1
    used.add(candidate)
    return candidate


def calibrate(chart_photos, out_dir, *, edition: str = DEFAULT_EDITION, method: str = "3x3",
              reports: bool = True, progress: ProgressCallback | None = None) -> list[CalibrationResult]:
    """Calibrate every chart photo (files, or folders searched recursively) into ``out_dir``.

    ``method``: ``3x3`` or ``root-polynomial``; ``edition``: a 24-patch name of
    ``colour.CCS_COLOURCHECKERS``. Bad values raise ValueError before anything is written.
    ``progress``: a callback told of each photo, and of each one not ok (:mod:`f2l.io.progress`).
    """
    from f2l.io.photo import PhotoError, load_photo
    from f2l.face.run import expand_photos
    from f2l.io.tables import ParquetAppender

    resolve_method(method)
    reference_chart(edition)
    out = Path(out_dir)
    (out / REPORTS_DIR).mkdir(parents=True, exist_ok=True)
    files = expand_photos(chart_photos)
    bar = Progress(progress, "calibrate", "photo", len(files))
    results: list[CalibrationResult] = []
    used_stems: set[str] = set()
    with ParquetAppender(out / TABLE_NAME, SCHEMA, rows_per_group=256) as table:
        for path in files:
            t0 = time.perf_counter()
            result = CalibrationResult(str(path), "error", "", ColourCorrection.identity(), edition)
            try:
                photo = load_photo(path)
                result.camera = _camera(photo.exif)
                status, reason, detection, fit = calibrate_photo(
                    photo.display, photo.linear, clipped=photo.clipped, edition=edition, method=method,
                    source=str(path))
                result.status, result.reason, result.detection, result.fit = status, reason, detection, fit
                if fit is not None:
                    result.correction = fit.correction
                    if reports:
                        from f2l.colour.report import write_report

                        stem = _report_stem(path, used_stems)
                        result.report_png = f"{REPORTS_DIR}/{stem}.png"
                        result.report_table = f"{REPORTS_DIR}/{stem}.md"
                        write_report(fit, out / result.report_png, out / result.report_table,
                                     detection=detection, display=photo.display, title=str(path),
                                     status=status, reason=reason)
            except PhotoError as exc:
                result.status, result.reason = "error", str(exc)
            except Exception as exc:  # noqa: BLE001 - one bad photo must not stop the batch
                result.status, result.reason = "error", f"{path}: {type(exc).__name__}: {exc}"
                result.correction, result.detection, result.fit = ColourCorrection.identity(), None, None
                result.report_png = result.report_table = None
            result.seconds = time.perf_counter() - t0
            table.append(result.row())
            results.append(result)
            if result.status != "ok":
                bar.note(f"{result.status}: {result.reason}")
            bar.advance()
    return results


def summarise(results: list[CalibrationResult], out_dir) -> dict:
    """JSON-able summary of a batch: counts per status and per-photo ΔE figures."""
    counts = {s: 0 for s in ("ok", "partial", "identity", "no_chart", "error")}
    photos = []
    for r in results:
        counts[r.status] += 1
        stats = r.fit.stats() if r.fit is not None else {}
        photos.append({"path": r.source_path, "status": r.status, "reason": r.reason,
                       "method": r.correction.method,
                       "n_valid_patches": int(r.fit.valid.sum()) if r.fit is not None else 0,
                       **{k: round(v, 3) for k, v in stats.items() if np.isfinite(v)}})
    return {"out": str(out_dir), "table": str(Path(out_dir) / TABLE_NAME), "photos": len(results),
            "status": counts, "results": photos}


def format_summary(summary: dict) -> str:
    """A Markdown table of :func:`summarise` output: one line per photo, ΔE2000 mean / max."""
    def pair(r, when):
        return (f"{r[f'mean_delta_e_{when}']:.2f} / {r[f'max_delta_e_{when}']:.2f}"
                if f"mean_delta_e_{when}" in r else "–")

    lines = ["| photo | status | method | patches | ΔE00 before (mean / max) | ΔE00 after (mean / max) |",
             "|---|---|---|---:|---:|---:|"]
    for r in summary["results"]:
        lines.append(f"| {r['path']} | {r['status']} | {r['method']} | {r['n_valid_patches']} | "
                     f"{pair(r, 'before')} | {pair(r, 'after')} |")
    notes = [f"{r['status']}: {r['reason']}" for r in summary["results"] if r["reason"]]
    counts = ", ".join(f"{k} {v}" for k, v in summary["status"].items() if v)
    return "\n".join(lines + [""] + notes + [f"{summary['photos']} photo(s): {counts}; table {summary['table']}"])


def read_corrections(path) -> dict[str, ColourCorrection]:
    """``{source_path: ColourCorrection}`` from a ``colour.parquet`` (validated; failed rows give identity)."""
    import pyarrow.parquet as pq

    from f2l.io.schema import validate_table

    table = pq.read_table(path)
    validate_table(table, SCHEMA, source=str(path))
    out = {}
    for row in table.to_pylist():
        out[row["source_path"]] = ColourCorrection.from_dict(row)
    return out
