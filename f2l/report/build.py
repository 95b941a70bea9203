"""``f2l report FOLDER``: one self-contained HTML page (plus a folder of cached thumbnails beside
it) for an evaluation folder (``f2l demo``'s output, or any folder holding ``shards/`` and
``estimates/``) or a ``build-dataset`` output folder (``dataset_card.json``).

Sections, each present when its inputs are:

- **Metrics**: ``estimates/metrics_summary.csv`` (every model's §5.1 means and run time) and the
  error-against-run-time plot (log time axis, labelled decades only);
- **The sun's uncertainty**: per model, how often the true sun lies inside the estimates' 68% and
  90% sun cones (``estimates.parquet``'s ``sun_cone68_deg`` / ``sun_cone90_deg``, f2l.estimate.uncertainty)
  and the risk–coverage curve (mean Sun-ang of the most confident faces; f2l.evaluation.calibration);
- **Warnings**: the dataset card's warnings and left-out inputs (path, stage, status, reason);
- **Sessions**: per session of the card, its probe (tone-mapped, with its coverage and the sun
  marked), the brackets and their statuses and the charts' ΔE from ``WORK`` (``--work``) when given;
- **Faces**: per face, the photo, mask counts and status, the ground-truth probe next to every
  model's estimate and its relit preview, and the face's metrics (``metrics_per_face.csv``) with
  the estimate's sun cones and predicted relit error.
  Faces are paginated (``page_size`` per page: ``report.html``, ``report-2.html``, ...); images
  are lazy-loaded thumbnails cached in ``report_files/`` by the source's path, size and mtime, so a
  re-run rewrites only what changed.

Everything from the input (file names, EXIF, session.toml values, messages) is escaped
(:mod:`f2l.report.html`); the page loads nothing remote and runs no script.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from f2l.report.html import Html, el, href, page

__all__ = ["write_report", "ReportSummary"]

THUMB_PX = 160
FILES_DIR = "report_files"


@dataclass
class ReportSummary:
    pages: list[str] = field(default_factory=list)
    faces: int = 0
    thumbnails_written: int = 0
    thumbnails_reused: int = 0

    def to_json(self) -> dict:
        return dict(self.__dict__)


class _Thumbs:
    """Thumbnails in ``out_dir/report_files``, keyed by source path + size + mtime."""

    def __init__(self, out_dir: Path, summary: ReportSummary) -> None:
        self.dir = out_dir / FILES_DIR
        self.dir.mkdir(parents=True, exist_ok=True)
        self.out_dir, self.summary = out_dir, summary

    def _name(self, source: Path, kind: str) -> Path:
        st = source.stat()
        key = f"{source.resolve()}|{st.st_size}|{st.st_mtime_ns}|{kind}|{THUMB_PX}"
        return self.dir / f"{hashlib.sha1(key.encode()).hexdigest()[:20]}.png"

    def image(self, source: Path, kind: str = "photo", **marks) -> str | None:
        """Relative URL of a thumbnail of ``source`` (PNG/JPEG photo, or an HDR probe when kind is
        "probe": tone-mapped, sun marked), or None when the source is missing or unreadable."""
        if not source.is_file():
            return None
        target = self._name(source, kind + json.dumps(marks, sort_keys=True))
        if target.is_file():
            self.summary.thumbnails_reused += 1
        else:
            try:
                maker = {"probe": _probe_thumb, "scene": _scene_thumb}.get(kind)
                img = maker(source, **marks) if maker else _photo_thumb(source)
            except Exception:  # an unreadable input shows as a missing image with its name
                return None
            from f2l.io.preview import save_png

            save_png(target, img)
            self.summary.thumbnails_written += 1
        return href(os.path.relpath(target, self.out_dir).replace(os.sep, "/"))


def _photo_thumb(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        im = im.convert("RGB")
        im.thumbnail((THUMB_PX, THUMB_PX))
        return np.asarray(im)


def _scene_thumb(path: Path) -> np.ndarray:
    """The evaluation scene (f2l.metrics.scene) relit by the probe, at its own mean exposure."""
    from f2l.io.preview import tonemap
    from f2l.io.probe_io import read_hdr_image
    from f2l.metrics.scene import render_scene

    img, mask = render_scene(read_hdr_image(path))
    scale = 0.18 / max(float((img[mask] @ np.array([0.2126, 0.7152, 0.0722])).mean()), 1e-12)
    return tonemap(img * scale, exposure_ev=0.0)


def _probe_thumb(path: Path, sun_elevation_deg=None, sun_azimuth_deg=None, coverage: str | None = None) -> np.ndarray:
    from PIL import Image

    from f2l.io.preview import tonemap
    from f2l.io.probe_io import read_hdr_image

    hdr = read_hdr_image(path)
    img = tonemap(hdr)
    if coverage and Path(coverage).is_file():  # dim what no view saw
        with Image.open(coverage) as c:
            seen = np.asarray(c.convert("L").resize(img.shape[1::-1])) > 127
        img = np.where(seen[..., None], img, (img * 0.3 + 60).astype(np.uint8))
    h, w = img.shape[:2]
    scale = max(1, int(round(2 * THUMB_PX / w)))
    img = np.repeat(np.repeat(img, scale, axis=0), scale, axis=1) if scale > 1 else img
    if sun_elevation_deg is not None and sun_azimuth_deg is not None:
        h, w = img.shape[:2]
        r = int(round((0.5 - sun_elevation_deg / 180.0) * h))
        c = int(round((0.5 + sun_azimuth_deg / 360.0) * w)) % w
        img = img.copy()
        for dr, dc in [(d, 0) for d in range(-6, 7)] + [(0, d) for d in range(-6, 7)]:
            if 0 <= r + dr < h:
                img[r + dr, (c + dc) % w] = (255, 0, 255)
    pil = Image.fromarray(img)
    pil.thumbnail((2 * THUMB_PX, THUMB_PX))
    return np.asarray(pil)


def _figure(src: str | None, caption: str, alt: str) -> Html:
    img = el("img", src=src, alt=alt, loading="lazy", decoding="async") if src else el("span", "(missing)", class_="bad")
    return el("figure", img, el("figcaption", caption))


def _read_csv(path: Path) -> list[dict]:
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _fmt(value) -> str:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return str(value)
    if not math.isfinite(v):
        return "–"
    return f"{v:.4g}"


def _metrics_section(est: Path, out_dir: Path) -> list[Html]:
    from f2l.metrics import METRIC_NAMES

    rows = _read_csv(est / "metrics_summary.csv")
    head = el("tr", el("th", "model", class_="l"), el("th", "n"), *[el("th", m) for m in METRIC_NAMES],
              el("th", "s / face"))
    body = [el("tr", el("td", r["model"], class_="l"), el("td", r["n"]),
                *[el("td", _fmt(r.get(f"{m} mean"))) for m in METRIC_NAMES], el("td", _fmt(r.get("runtime_s mean"))),
                id=f"metrics-{r['model']}") for r in rows]
    from f2l.report.plots import plot_error_vs_runtime

    plot = out_dir / FILES_DIR / "error_vs_runtime.png"
    plot_error_vs_runtime(rows, plot)
    return [el("h2", "Metrics (paper §5.1), mean over faces", id="metrics"), el("table", head, *body, id="metrics-table"),
            el("p", "Per-face values: ", el("span", os.path.relpath(est / "metrics_per_face.csv", out_dir), class_="small")),
            _figure(href(os.path.relpath(plot, out_dir).replace(os.sep, "/")), "error against run time", "plot")]


UNCERTAINTY_COLUMNS = {"sun_cone68_deg": "sun cone 68% (°)", "sun_cone90_deg": "sun cone 90% (°)",
                       "predicted_mae_s": "predicted MAE (s)"}


def _uncertainty(est: Path) -> dict:
    """{(face_id, model): {column: value}} of the estimates' sun-uncertainty columns; empty for a
    table without them (written before estimates schema 4) or none."""
    import pyarrow.parquet as pq

    path = est / "estimates.parquet"
    if not path.is_file():
        return {}
    names = pq.read_schema(path).names
    if not all(k in names for k in UNCERTAINTY_COLUMNS):
        return {}
    table = pq.read_table(path, columns=["face_id", "model", *UNCERTAINTY_COLUMNS]).to_pylist()
    return {(r["face_id"], r["model"]): {k: r[k] for k in UNCERTAINTY_COLUMNS} for r in table}


def _calibration_section(est: Path, out_dir: Path, uncertainty: dict) -> list[Html]:
    """Per model: the share of faces whose true sun lies inside its 68% / 90% cone and the mean
    Sun-ang of the most confident faces, with the risk–coverage plot; nothing without cones."""
    from f2l.evaluation.calibration import FRACTIONS, cone_coverage, plot_risk_coverage, risk_coverage, usable

    per_face = est / "metrics_per_face.csv"
    if not uncertainty or not per_face.is_file():
        return []
    rows = usable([{**r, **uncertainty.get((r["face_id"], r["model"]), {})} for r in _read_csv(per_face)])
    if not rows:
        return []
    models = sorted({r["model"] for r in rows})
    curves = {m: risk_coverage([r for r in rows if r["model"] == m]) for m in models}
    head = el("tr", el("th", "model", class_="l"), el("th", "faces"), el("th", "inside 68% cone"),
              el("th", "inside 90% cone"), *[el("th", f"mean Sun-ang, most confident {f:.0%} (°)") for f in FRACTIONS])
    body = []
    for m in models:
        cov = cone_coverage([r for r in rows if r["model"] == m])
        body.append(el("tr", el("td", m, class_="l"), el("td", cov["n"]), el("td", f"{cov['inside 68%']:.0%}"),
                       el("td", f"{cov['inside 90%']:.0%}"), *[el("td", _fmt(v)) for _, _, v in curves[m]],
                       id=f"calibration-{m}"))
    plot = out_dir / FILES_DIR / "risk_coverage.png"
    plot_risk_coverage(curves, plot)
    return [el("h2", "The sun's uncertainty: calibration and risk–coverage", id="calibration"),
            el("p", "Calibrated cones hold the true sun for about 68% and 90% of the faces with a sun; a useful "
                    "confidence gives its most confident faces a lower mean Sun-ang."),
            el("table", head, *body, id="calibration-table"),
            _figure(href(os.path.relpath(plot, out_dir).replace(os.sep, "/")), "risk–coverage", "risk-coverage plot")]


def _warnings_section(card: dict) -> list[Html]:
    warnings, left = card.get("warnings", []), card.get("left_out", [])
    out = [el("h2", f"Warnings ({len(warnings)}) and inputs left out ({len(left)})", id="warnings")]
    out.append(el("ul", *[el("li", w, class_="warn") for w in warnings]) if warnings else el("p", "No warnings."))
    if left:
        out.append(el("table", el("tr", *[el("th", k, class_="l") for k in ("path", "stage", "status", "reason")]),
                      *[el("tr", *[el("td", r.get(k, ""), class_="l") for k in ("path", "stage", "status", "reason")])
                        for r in left]))
    return out


def _sessions_section(card: dict, out_dir: Path, folder: Path, work: Path | None, thumbs: _Thumbs) -> list[Html]:
    import pyarrow.parquet as pq

    probes_rows, captures = {}, []
    if work is not None and (work / "probes.parquet").is_file():
        probes_rows = {(r["kind"], r["name"]): r for r in pq.read_table(work / "probes.parquet").to_pylist()}
    if work is not None and (work / "captures.parquet").is_file():
        captures = pq.read_table(work / "captures.parquet").to_pylist()
        root = _capture_root(work)
        if root is not None:  # messages name files relative to the capture tree, as the card does
            from f2l.pipeline.plan import relative_message

            for r in captures:
                r["message"] = relative_message(r["message"], root)
    out = [el("h2", f"Sessions ({len(card.get('sessions', []))})", id="sessions")]
    for s in card.get("sessions", []):
        name = s["name"]
        probe = s.get("probe") or {}
        row = probes_rows.get(("probe", name), {})
        marks = {"sun_elevation_deg": row.get("sun_elevation_deg"), "sun_azimuth_deg": row.get("sun_azimuth_deg")}
        if row.get("path") and work is not None:
            marks["coverage"] = str(work / row["path"].replace(".exr", ".coverage.png"))
        src = thumbs.image(folder / probe["file"], "probe", **marks) if probe.get("file") else None
        facts = [f"{s['face_photos']} face photos, {s['records']} records"]
        if row:
            facts.append(f"coverage {row.get('coverage_fraction') or 0:.0%}, saturated {row.get('saturated_fraction') or 0:.2%}"
                         f", colour {row.get('colour_space')}")
        brackets = [r for r in probes_rows.values() if r["kind"] == "view" and r["session"] == name]
        files = [r for r in captures if r["session"] == name]
        out.append(el("div", el("h3", f"session {name}"),
                      _figure(src, "probe (sun marked; unseen dimmed)", f"probe of {name}"),
                      el("p", "; ".join(facts)),
                      el("table", el("tr", *[el("th", k, class_="l") for k in ("bracket", "frames", "status", "message")]),
                         *[el("tr", el("td", b["name"], class_="l"), el("td", b["frames"]), el("td", b["status"], class_="l"),
                              el("td", b["message"], class_="l")) for b in brackets]) if brackets else None,
                      el("table", el("tr", *[el("th", k, class_="l") for k in ("file", "role", "camera", "lens",
                                                                              "status", "message")]),
                         *[el("tr", *[el("td", r.get(k) or "", class_="l") for k in ("path", "role", "camera", "lens",
                                                                                    "status", "message")])
                           for r in files]) if files else None,
                      _colour_table(s.get("face_colour", {}), work),
                      el("p", "skipped: " + "; ".join(f"{k}: {v}" for k, v in s.get("skipped", {}).items()))
                      if s.get("skipped") else None, class_="session"))
    return out


def _capture_root(work: Path) -> Path | None:
    from f2l.pipeline.build import ROOT_FILE

    try:
        return Path(json.loads((work / ROOT_FILE).read_text(encoding="utf-8"))["root"])
    except (OSError, ValueError, KeyError):
        return None


def _colour_table(face_colour: dict, work: Path | None) -> Html | None:
    """Per camera: the correction applied to its faces, and its chart's ΔE2000 (mean / max,
    before → after) from the calibrate cache entry when ``work`` is given."""
    if not face_colour:
        return None
    rows = []
    for camera, c in sorted(face_colour.items()):
        delta = ""
        done = work / "cache" / "calibrate" / c["chart_key"] / "done" if work is not None and c.get("chart_key") else None
        if done is not None and done.is_file():
            de = json.loads(done.read_text()).get("delta_e", {})
            delta = (f"mean {_fmt(de.get('mean_delta_e_before'))} → {_fmt(de.get('mean_delta_e_after'))}, "
                     f"max {_fmt(de.get('max_delta_e_before'))} → {_fmt(de.get('max_delta_e_after'))}")
        rows.append(el("tr", *[el("td", v, class_="l") for v in (camera or "(unknown camera)", c.get("method"),
                                                                 c.get("chart") or "", delta, c.get("note"))]))
    head = el("tr", *[el("th", k, class_="l") for k in ("camera", "colour correction", "chart", "chart ΔE2000", "note")])
    return el("table", head, *rows)


def _face_rows(folder: Path, est: Path) -> tuple[list[dict], dict]:
    """(records as dicts: face_id, photo, gt probe, status, pixels, source) and per-face metrics."""
    from f2l.io.shards import iter_records

    shards = folder / "shards" if (folder / "shards").is_dir() else folder
    faces = []
    for rec in iter_records(shards):
        overlay = (rec.meta or {}).get("overlay_path")
        faces.append({"face_id": rec.face_id, "photo": shards / rec.photo_path if rec.photo_path else None,
                      "overlay": shards / overlay if overlay else None,
                      "gt": shards / rec.gt_probe_path if rec.gt_probe_path else None, "status": rec.status,
                      "message": rec.message, "pixels": rec.num_pixels, "source": rec.source_path})
    metrics: dict = {}
    per_face = est / "metrics_per_face.csv"
    if per_face.is_file():
        for r in _read_csv(per_face):
            metrics.setdefault(r["face_id"], {})[r["model"]] = r
    return faces, metrics


def _face_block(face: dict, metrics: dict, est: Path, thumbs: _Thumbs, uncertainty: dict | None = None) -> Html:
    from f2l.metrics import METRIC_NAMES

    fid = face["face_id"]
    figs = [_figure(thumbs.image(face["photo"]) if face["photo"] else None, "photo", f"photo {fid}"),
            _figure(thumbs.image(face["overlay"]), "fit overlay", f"overlay {fid}") if face["overlay"] else None,
            _figure(thumbs.image(face["gt"], "probe") if face["gt"] else None, "ground truth", f"truth {fid}")]
    models = sorted(metrics.get(fid, {}))
    for m in models:
        figs.append(_figure(thumbs.image(est / "probes" / m / f"{fid}.exr", "probe"), m, f"{m} probe {fid}"))
    if face["gt"]:
        figs.append(_figure(thumbs.image(face["gt"], "scene"), "scene under the truth", f"scene {fid}"))
    for m in models:
        figs.append(_figure(thumbs.image(est / "probes" / m / f"{fid}.exr", "scene"), f"scene under {m}",
                            f"{m} scene {fid}"))
    unc = uncertainty or {}
    extra = list(UNCERTAINTY_COLUMNS) if any((fid, m) in unc for m in models) else []
    table = el("table", el("tr", el("th", "model", class_="l"), *[el("th", k) for k in METRIC_NAMES], el("th", "s"),
                           *[el("th", UNCERTAINTY_COLUMNS[k]) for k in extra]),
               *[el("tr", el("td", m, class_="l"), *[el("td", _fmt(metrics[fid][m].get(k))) for k in METRIC_NAMES],
                    el("td", _fmt(metrics[fid][m].get("runtime_s"))),
                    *[el("td", _fmt(unc.get((fid, m), {}).get(k))) for k in extra]) for m in models]) if models else None
    status = el("span", face["status"], class_="ok" if face["status"] == "ok" else "bad")
    return el("div", el("div", el("strong", fid), " ", status, f" · {face['pixels']} mask pixels · ",
                        el("span", face["source"] or "", class_="small"),
                        el("div", face["message"], class_="small") if face["message"] else None, table),
              *figs, class_="face", id=f"face-{fid}")


def write_report(folder: str | os.PathLike, out: str | os.PathLike | None = None, *, work: str | os.PathLike | None = None,
                 estimates: str | os.PathLike | None = None, page_size: int = 200,
                 title: str | None = None) -> ReportSummary:
    """Write ``out`` (default ``FOLDER/report.html``) and its thumbnails; returns what was written.
    ``estimates``: the ``f2l estimate`` output evaluated against these shards (default
    ``FOLDER/estimates``)."""
    folder = Path(folder)
    out = Path(out) if out is not None else folder / "report.html"
    out_dir = out.parent
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = ReportSummary()
    thumbs = _Thumbs(out_dir, summary)
    est = Path(estimates) if estimates is not None else folder / "estimates"
    card_path = folder / "dataset_card.json"
    card = json.loads(card_path.read_text()) if card_path.is_file() else None
    top: list[Html] = []
    uncertainty = _uncertainty(est)
    if (est / "metrics_summary.csv").is_file():
        top += _metrics_section(est, out_dir)
        top += _calibration_section(est, out_dir, uncertainty)
    from f2l.report.video import clip_section, is_clip_output

    if is_clip_output(folder):  # an f2l video output
        top += clip_section(folder, out_dir, thumbs)
    sheets = [p for p in (folder / "probes_contact_sheet.png", folder / "relit_scene_contact_sheet.png") if p.is_file()]
    if sheets:
        top.append(el("h2", "Contact sheets", id="pictures"))
        top += [_figure(href(os.path.relpath(p, out_dir).replace(os.sep, "/")), p.name, p.stem) for p in sheets]
    if card is not None:
        top += _warnings_section(card)
        top += _sessions_section(card, out_dir, folder, Path(work) if work else None, thumbs)
    faces, metrics = _face_rows(folder, est) if (folder / "shards").is_dir() or list(folder.glob("part-*.parquet")) else ([], {})
    summary.faces = len(faces)
    pages = [faces[i:i + page_size] for i in range(0, len(faces), page_size)] or [[]]
    names = [out.name] + [f"{out.stem}-{k + 1}{out.suffix}" for k in range(1, len(pages))]
    heading = title or f"f2l report: {folder.resolve().name}"
    nav = el("nav", *[el("a", f"page {k + 1}", href=href(n)) for k, n in enumerate(names)]) if len(names) > 1 else None
    for k, chunk in enumerate(pages):
        body = list(top) if k == 0 else []
        if faces:
            first = k * page_size
            body.append(el("h2", f"Faces {first + 1}–{first + len(chunk)} of {len(faces)}", id="faces"))
            body += [_face_block(f, metrics, est, thumbs, uncertainty) for f in chunk]
        target = out_dir / names[k]
        tmp = target.with_name(target.name + ".tmp")
        tmp.write_text(page(heading, *body, nav=nav), encoding="utf-8")
        tmp.replace(target)
        summary.pages.append(str(target))
    return summary
