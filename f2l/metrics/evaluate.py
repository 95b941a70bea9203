"""``f2l evaluate``: the seven §5.1 metrics for every estimate that has a ground-truth probe.

Reads ``estimates.parquet`` and ``run.json`` written by ``f2l estimate``, finds each face's
ground-truth probe through its shard record (``gt_probe_path``; overcast flag and true sun
direction from the record's metadata), and writes ``metrics_per_face.csv``, ``metrics_summary.csv``
and ``metrics_summary.md`` (mean ± std per model with the mean run time per face).

Per face, besides the metrics: ``gt_overcast`` (the record's sky kind, else
:func:`~f2l.metrics.lighting.is_overcast` of the ground truth) and the sun energy share of the
estimate and of the ground truth (:mod:`f2l.metrics.sun_share`). The summary adds the median
Sun-dω MAE and Sun-ang and, per model, the overcast faces whose estimated sun share exceeds the
ground truth's by more than 0.1.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from f2l.io.tables import ESTIMATE_RUN_FILE as RUN_FILE, ESTIMATES_FILE
from f2l.io.atomic import atomic_path, write_text_atomic


def ground_truth_index(shards: list[Path]) -> dict[str, dict]:
    """face_id -> {probe: absolute path or None, meta: dict}, reading only the small columns.

    >>> import tempfile, pyarrow as pa
    >>> table = pa.table({"face_id": ["f1", "f2"], "gt_probe_path": ["probes/f1.exr", None],
    ...                   "meta_json": ['{"sky": {"kind": "overcast"}}', None]})
    >>> with tempfile.TemporaryDirectory() as tmp:
    ...     pq.write_table(table, Path(tmp) / "part-0.parquet")
    ...     index = ground_truth_index([Path(tmp)])
    ...     index["f1"]["probe"] == str(Path(tmp) / "probes/f1.exr")
    True
    >>> index["f1"]["meta"], index["f2"]
    ({'sky': {'kind': 'overcast'}}, {'probe': None, 'meta': {}})
    """
    index: dict[str, dict] = {}
    for shard in shards:
        shard = Path(shard)
        files = sorted(shard.glob("*.parquet")) if shard.is_dir() else [shard]
        base = shard if shard.is_dir() else shard.parent
        for f in files:
            try:
                table = pq.read_table(f, columns=["face_id", "gt_probe_path", "meta_json"])
            except Exception:  # noqa: BLE001 - a bad shard was already reported by estimate
                continue
            for fid, gt, meta in zip(*(table.column(c).to_pylist() for c in ("face_id", "gt_probe_path", "meta_json"))):
                index[fid] = {"probe": str(base / gt) if gt else None, "meta": json.loads(meta or "{}")}
    return index


def _overcast_and_sun(meta: dict):
    sky = meta.get("sky", meta)
    kind = sky.get("kind")
    overcast = None if kind is None else kind == "overcast"
    sun = sky.get("sun_direction")
    return overcast, (None if sun is None or overcast else np.asarray(sun, dtype=np.float64))


CONE_COLUMNS = ("sun_cone68_deg", "sun_cone90_deg", "predicted_mae_s")  # estimates schema 4 (f2l.estimate.uncertainty)


def evaluate_estimates(estimates_dir: Path, shards: list[Path] | None = None) -> dict:
    from f2l.metrics.calibration import calibration_table, usable
    from f2l.io.exr import read_exr
    from f2l.lighting.grid import LatLongGrid
    from f2l.metrics import METRIC_NAMES, evaluate_pair, summarise, summary_records, to_csv, to_markdown
    from f2l.metrics.lighting import is_overcast
    from f2l.metrics.sun_share import GT_OVERCAST, SUN_SHARE_EST, SUN_SHARE_GT, sun_shares

    estimates_dir = Path(estimates_dir)
    if shards is None:
        run = json.loads((estimates_dir / RUN_FILE).read_text())
        shards = [Path(s) for s in run["shards"]]
    gt = ground_truth_index(shards)
    table = pq.read_table(estimates_dir / ESTIMATES_FILE).to_pylist()
    rows = []
    for est in table:
        if est["status"] != "ok":
            continue
        truth = gt.get(est["face_id"])
        if truth is None or truth["probe"] is None:
            continue
        grid = LatLongGrid(est["grid_height"], est["grid_width"])
        est_probe = read_exr(estimates_dir / est["probe_path"])
        gt_probe = read_exr(truth["probe"])
        overcast, gt_sun = _overcast_and_sun(truth["meta"])
        if overcast is None:
            overcast = bool(is_overcast(gt_probe, grid))
        est_sun = None if est.get("sun_direction") is None else np.asarray(est["sun_direction"])
        metrics = evaluate_pair(est_probe, gt_probe, grid, overcast=overcast, est_sun_dir=est_sun, gt_sun_dir=gt_sun)
        rows.append({"model": est["model"], "face_id": est["face_id"], "runtime_s": est["runtime_s"], **metrics,
                     GT_OVERCAST: overcast, **sun_shares(est_probe, gt_probe, grid),
                     **{k: est.get(k) for k in CONE_COLUMNS}})
    if not rows:
        raise SystemExit(f"{estimates_dir}: no successful estimate with a ground-truth probe to evaluate")
    summary = summarise(rows, by="model")
    per_face_csv = estimates_dir / "metrics_per_face.csv"
    summary_csv = estimates_dir / "metrics_summary.csv"
    summary_md = estimates_dir / "metrics_summary.md"
    columns = ["model", "face_id", *METRIC_NAMES, "runtime_s", GT_OVERCAST, SUN_SHARE_EST, SUN_SHARE_GT, *CONE_COLUMNS]
    _write_rows_csv(rows, per_face_csv, columns)
    to_csv(summary, summary_csv)
    markdown = to_markdown(summary)
    if usable(rows):  # the sun cones' calibration and risk-coverage (f2l.evaluation.calibration)
        markdown += "\n\nThe sun's uncertainty (faces with a sun)\n\n" + calibration_table(rows, key="model")
    write_text_atomic(summary_md, markdown + "\n")
    return {
        "rows": rows, "summary": summary, "summary_rows": [_json_ready(r) for r in summary_records(summary)],
        "markdown": markdown, "per_face_csv": str(per_face_csv), "summary_csv": str(summary_csv),
        "summary_md": str(summary_md),
    }


def _json_ready(record: dict) -> dict:
    """``record`` with non-finite floats as None (strict JSON has no NaN)."""
    return {k: None if isinstance(v, float) and not np.isfinite(v) else v for k, v in record.items()}


def _write_rows_csv(rows: list[dict], path: Path, columns: list[str]) -> None:
    import csv

    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        for r in rows:
            writer.writerow(r)
