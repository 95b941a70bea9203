"""The report's section for an ``f2l video`` output folder: the sun over time, the segments, the
window estimates and a strip of the clip's probes."""

from __future__ import annotations

import json
import os
from pathlib import Path

from f2l.report.html import Html, el, href


def is_clip_output(folder: Path) -> bool:
    return (folder / "clip.json").is_file() and (folder / "frames.parquet").is_file()


def clip_section(folder: Path, out_dir: Path, thumbs, probes_shown: int = 8) -> list[Html]:
    """Headings, the sun-track figure, the segments and estimates tables and probe thumbnails."""
    import pyarrow.parquet as pq

    summary = json.loads((folder / "clip.json").read_text())
    rows = pq.read_table(folder / "frames.parquet").to_pylist()
    t = summary.get("timings", {})
    statuses: dict[str, int] = {}
    for r in rows:
        statuses[r["status"]] = statuses.get(r["status"], 0) + 1
    line = (f"{summary['clip']}: {summary['frames']} frames at {summary['fps']:.3g} fps, "
            f"{summary['width']}×{summary['height']}; {len(summary['segments'])} segment(s), "
            f"{len(summary['estimates'])} window estimates; {t.get('frames_per_s', 0) or 0:.1f} frames/s. "
            "Rows by status: " + ", ".join(f"{k} {v}" for k, v in sorted(statuses.items())))
    out: list[Html] = [el("h2", "Clip", id="clip"), el("p", line)]
    track = folder / "sun_track.png"
    if track.is_file():
        src = href(os.path.relpath(track, out_dir).replace(os.sep, "/"))
        out.append(el("figure", el("img", src=src, alt="sun track"),
                      el("figcaption", "The sun's elevation and azimuth over the clip (segments dotted).")))
    out.append(el("table", el("tr", el("th", "first frame"), el("th", "why", class_="l")),
                  *[el("tr", el("td", str(s["first_frame"])), el("td", s["why"], class_="l")) for s in summary["segments"]]))
    out.append(el("table", el("tr", *[el("th", h) for h in ("frame", "segment", "window (frames)", "first of its segment", "s")]),
                  *[el("tr", el("td", str(e["frame"])), el("td", str(e["segment"])),
                       el("td", " ".join(map(str, e["window"])), class_="l"), el("td", "yes" if e["cold"] else ""),
                       el("td", f"{e['runtime_s']:.2f}")) for e in summary["estimates"]]))
    probes = sorted({r["probe_path"] for r in rows if r.get("probe_path")})
    if probes:
        step = max(1, len(probes) // probes_shown)
        figures = []
        for rel in probes[::step][:probes_shown]:
            row = next(r for r in rows if r.get("probe_path") == rel)
            src = thumbs.image(folder / rel, "probe", sun_elevation_deg=row.get("sun_elevation_deg"),
                               sun_azimuth_deg=row.get("sun_azimuth_deg"))
            figures.append(el("figure", el("img", src=src, alt=rel) if src else el("span", "(missing)"),
                              el("figcaption", f"frame {row['frame']}")))
        out.append(el("div", *figures, class_="face"))
    return out
