"""The shards stage: colour-corrected face records paired with their session's probe.

Colour (per session and camera). A face photo takes the correction of the session's first
usable chart photo (status ``ok`` or ``partial``, by path) of the same camera (the captures
``camera`` column, EXIF make and model); when the chart's or the photo's camera is unknown, the
first usable chart, with a note; otherwise the identity, with a warning. It is applied to
``observed_rgb`` with :func:`f2l.colour.fit.apply_correction` (``keep_exposure`` from the
pipeline: by default colour only, the photo's brightness scale kept), clipped at 0. Each record's
``meta.colour`` says what was applied.

Ground truth. The session's probe (sphere or given) becomes ``probes/<session>.exr`` in the shard
folder, one file per session that all its faces' ``gt_probe_path`` name (float32, the DESIGN
lat-long convention). On the way (a ``gt-probe`` entry): for a probe merged from brackets and
``correct_probe``, the correction chosen (as above) for the sky camera is applied, colour only,
so the probe keeps its absolute scale (1.0 = sensor full scale at EV100 0), clipped at 0; a
given probe is used as it is (its colour space is its own); and with the session
TOML's ``probe_azimuth_deg`` (the azimuth of the probe's centre column, positive toward the face
camera's right) it is turned about +Y into the face camera's frame
(:func:`f2l.lighting.grid.rotate_y` by −azimuth). Without it the probe keeps its tripod frame,
with a warning.

Shards. Face photos with records, by path, are cut into shards content-defined: after a photo
whose SHA-256 (first 32 bits) is ``photos_per_shard − 1`` modulo ``photos_per_shard``, or after
``4 × photos_per_shard`` photos. A changed photo so changes only its own shard (and at most the
next), and each shard is a ``shards`` cache entry keyed by its photos' fit keys, corrections and
probes. Records keep the face-index order of their photo.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from f2l.pipeline.cache import Cache, stage_key

SHARDS_VERSION = 1
GT_PROBE_VERSION = 2  # 2: chromaticities of a Rec.709 probe in the header
USABLE_CHART = ("ok", "partial")
MAX_SHARD_FACTOR = 4


def safe_name(name: str) -> str:
    """The probe side file's stem of a session: the name itself when it is file-name safe,
    else a safe form plus 8 hex of its SHA-256 (so two sessions never share a file)."""
    import hashlib

    out = "".join(c if c.isalnum() or c in "._-" else "_" for c in name).lstrip("._-")
    if out == name:
        return out
    return f"{out or 'session'}-{hashlib.sha256(name.encode('utf-8')).hexdigest()[:8]}"


def pick_correction(charts: list[dict], camera: str) -> tuple[dict | None, str]:
    """(chart result or None for the identity, note) for a photo of ``camera`` (module doc)."""
    usable = [c for c in charts if c["status"] in USABLE_CHART]
    for chart in usable:
        if camera and chart["camera"] == camera:
            return chart, ""
    for chart in usable:
        if not chart["camera"] or not camera:
            return chart, (f"camera unknown on the chart ({chart['path']}) or the photo: "
                           f"assumed to be the same camera")
    if usable:
        names = ", ".join(sorted({c["camera"] for c in usable}))
        return None, (f"no chart photo of camera {camera!r} in the session (charts of {names}): "
                      f"identity correction")
    if charts:
        statuses = ", ".join(f"{c['path']} {c['status']}" for c in charts)
        return None, f"no usable chart photo ({statuses}): identity correction"
    return None, "no chart photo in the session: identity correction"


def colour_description(chart: dict | None, note: str, keep_exposure: bool) -> dict:
    """What a correction does, for ``meta.colour`` and the dataset card."""
    if chart is None:
        return {"method": "identity", "chart": None, "chart_key": None, "keep_exposure": None,
                "note": note}
    return {"method": chart["correction"]["method"], "chart": chart["path"],
            "chart_key": chart["key"], "keep_exposure": bool(keep_exposure), "note": note}


def _correction(chart: dict | None):
    from f2l.colour.fit import ColourCorrection

    return None if chart is None else ColourCorrection.from_dict(chart["correction"])


def gt_probe(cache: Cache, session: str, probe: dict, chart: dict | None, note: str,
             azimuth_deg: float | None, counts: dict) -> dict:
    """The session's ground-truth probe entry: ``{"key", "entry", "applied", "problem"}`` (module
    doc): ``chart`` (a calibrate result, or None: nothing) is applied colour only, with ``note``
    saying why it was chosen or not. ``problem``: why the result is no probe (black, NaN, ...:
    :func:`f2l.lighting.plausibility.probe_problem`; then the caller must not use it), or None."""
    colour = colour_description(chart, note, False)
    applied = {"source": probe["row"]["kind"], "source_key": probe["key"], "colour": colour,
               "azimuth_deg": azimuth_deg,
               "frame": ("face camera (turned by probe_azimuth_deg)" if azimuth_deg is not None
                         else "tripod frame: session.toml has no probe_azimuth_deg")}
    key = stage_key("gt-probe", GT_PROBE_VERSION, {"session": session, "applied": applied}, {})

    def produce(tmp: Path) -> dict:
        from f2l.colour.fit import apply_correction
        from f2l.io.exr import read_exr, write_exr
        from f2l.lighting.grid import rotate_y

        radiance = read_exr(Path(probe["entry"]) / probe["row"]["path"])
        if chart is not None:
            radiance = np.maximum(apply_correction(radiance, _correction(chart),
                                                   keep_exposure=False), 0.0)
        if azimuth_deg is not None:
            radiance = rotate_y(radiance, -math.radians(azimuth_deg))
        from f2l.io.exr import REC709_CHROMATICITIES

        from f2l.lighting.plausibility import probe_problem

        rec709 = probe["row"].get("colour_space") == "rec709"
        write_exr(tmp / "probe.exr", np.asarray(radiance, np.float32), metadata={"f2l_session": session},
                  chromaticities=REC709_CHROMATICITIES if rec709 else None)
        problem = probe_problem(np.asarray(radiance, np.float32))
        return {"applied": applied, **({"problem": problem} if problem else {})}

    result, entry = cache.get_or_make("gt-probe", key, produce, counts)
    return {"key": key, "entry": str(entry), "applied": result["applied"],
            "problem": result.get("problem")}


def shard_chunks(photos: list[dict], photos_per_shard: int) -> list[list[dict]]:
    """Content-defined chunks of ``photos`` (each with ``sha256``), in order (module doc)."""
    n = int(photos_per_shard)
    chunks: list[list[dict]] = [[]]
    for photo in photos:
        chunks[-1].append(photo)
        if (int(photo["sha256"][:8], 16) % n == n - 1
                or len(chunks[-1]) >= MAX_SHARD_FACTOR * n):
            chunks.append([])
    return [c for c in chunks if c]


def write_shard(cache: Cache, chunk: list[dict], keep_exposure: bool, counts: dict,
                timings: dict) -> dict:
    """One shard entry (``part-00000.parquet``): ``{"key", "entry", "records"}``. Each photo
    dict has ``key``, ``entry`` (its fit-faces entry), ``path``, ``session``, ``chart``,
    ``colour`` and ``gt`` (the session's gt-probe entry or None)."""
    inputs = [{"fit": p["key"], "path": p["path"], "session": p["session"],
               "colour": p["colour"], "gt": None if p["gt"] is None else p["gt"]["key"],
               **({} if p.get("camera_yaw_deg") is None else {"camera_yaw_deg": p["camera_yaw_deg"]})}
              for p in chunk]
    key = stage_key("shards", SHARDS_VERSION, inputs, {"keep_exposure": bool(keep_exposure)})

    def produce(tmp: Path) -> dict:
        from f2l.colour.fit import apply_correction
        from f2l.io.shards import BadRecord, ShardWriter, iter_records

        t0 = time.perf_counter()
        n = 0
        with ShardWriter(tmp, records_per_shard=1 << 30) as writer:
            for p in chunk:
                correction = _correction(p["chart"])
                for record in iter_records(p["entry"]):
                    if isinstance(record, BadRecord):
                        raise RuntimeError(f"cache entry {p['entry']}: {record}")
                    if correction is not None:
                        record.observed_rgb = np.maximum(apply_correction(
                            record.observed_rgb, correction, keep_exposure=keep_exposure), 0.0)
                    record.gt_probe_path = (None if p["gt"] is None
                                            else f"probes/{safe_name(p['session'])}.exr")
                    record.meta["session"] = p["session"]
                    if p.get("camera_yaw_deg") is not None:  # f2l estimate --joint session turns the face by it
                        record.meta["camera_yaw_deg"] = float(p["camera_yaw_deg"])
                    record.meta["colour"] = p["colour"]
                    writer.write(record)
                    n += 1
        timings[f"shard {key[:12]}"] = round(time.perf_counter() - t0, 3)
        return {"records": n}

    result, entry = cache.get_or_make("shards", key, produce, counts)
    return {"key": key, "entry": str(entry), "records": int(result["records"])}
