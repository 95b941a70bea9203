"""``OUT/dataset_card.json``: what a build-dataset output is and how it was made.

Deterministic by construction: the same capture tree, pipeline and software give the same bytes
(key-sorted JSON, lists in path order, no timings, no absolute paths, no clock). Sections:

- ``build_key``: SHA-256 over the output files' cache keys, the pipeline and the versions;
- ``pipeline``: name, version, file name and SHA-256, every stage's parameters (defaults filled);
- ``versions``: f2l, Python, the libraries that shape the numbers, each stage's code version,
  the face landmarker model's SHA-256;
- ``inputs``: every file of ``captures.parquet`` (path, SHA-256, session, role, status) and the
  SHA-256 of that list;
- ``sessions``: per session its probe (source, status, what was applied to it), the colour
  correction applied to its faces per camera, its photo and record counts, stages it skipped;
- ``shards``: the shard files with their record counts and keys;
- ``counts``, ``left_out`` (every input or face not in the shards, with stage and reason) and
  ``warnings``.

Validated against ``schemas/dataset_card.schema.json`` before it is written.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import platform

import f2l
from f2l.pipeline.spec import canonical_json

CARD_VERSION = 1
LIBRARIES = ("numpy", "scipy", "pyarrow", "OpenEXR", "Pillow", "rawpy", "pycolmap",
             "opencv-contrib-python-headless", "colour-science", "ai-edge-litert",
             "embreex", "trimesh")


def library_versions() -> dict:
    out = {}
    for name in LIBRARIES:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = None
    return out


def stage_versions() -> dict:
    from f2l.capture.ingest import INGEST_VERSION
    from f2l.pipeline import assemble, faces, probes

    return {"ingest": INGEST_VERSION, "merge": probes.MERGE_VERSION,
            "sphere": probes.SPHERE_VERSION, "given-probe": probes.GIVEN_PROBE_VERSION,
            "calibrate": faces.CALIBRATE_VERSION, "fit-faces": faces.FIT_VERSION,
            "gt-probe": assemble.GT_PROBE_VERSION, "shards": assemble.SHARDS_VERSION}


def versions() -> dict:
    from f2l.face.mesh import FACE_LANDMARKER_SHA256

    return {"f2l": f2l.__version__, "python": platform.python_version(),
            "libraries": library_versions(), "stages": stage_versions(),
            "face_landmarker_sha256": FACE_LANDMARKER_SHA256}


def input_list(rows: list[dict]) -> dict:
    files = [{"path": r["path"], "sha256": r["sha256"], "session": r["session"],
              "role": r["role"], "status": r["status"]}
             for r in sorted(rows, key=lambda r: r["path"])]
    digest = hashlib.sha256(canonical_json(files).encode("ascii")).hexdigest()
    return {"files": files, "sha256": digest}


def build_key(files: dict, pipeline_json: dict, version_info: dict) -> str:
    """SHA-256 over {relative output path: cache key}, the pipeline and the versions."""
    doc = {"files": {rel: key for rel, (_, key) in sorted(files.items())},
           "pipeline": pipeline_json, "versions": version_info}
    return hashlib.sha256(canonical_json(doc).encode("ascii")).hexdigest()


def make_card(*, pipeline_json: dict, version_info: dict, inputs: dict, sessions: list[dict],
              shards: list[dict], counts: dict, left_out: list[dict], warnings: list[str],
              files: dict) -> dict:
    """The card as a dict (module docstring); validated against its schema."""
    import jsonschema

    from f2l.io.schema import load_schema

    card = {
        "card_version": CARD_VERSION,
        "format": {"records": "face_record", "layout": "part-NNNNN.parquet + probes/<session>.exr "
                   "+ photos/<face_id>.png (+ overlays/<face_id>.png)",
                   "observed_rgb": "linear, after the session's colour correction (meta.colour)",
                   "gt_probe": "float32 lat-long, DESIGN convention, one per session"},
        "build_key": build_key(files, pipeline_json, version_info),
        "pipeline": pipeline_json,
        "versions": version_info,
        "inputs": inputs,
        "sessions": sessions,
        "shards": shards,
        "counts": counts,
        "left_out": sorted(left_out, key=lambda r: (r["path"], r["stage"], r["status"],
                                                    r["reason"])),
        "warnings": sorted(set(warnings)),
    }
    jsonschema.validate(card, load_schema("dataset_card"))
    return card


def non_finite_numbers(value, where: str = "") -> list[str]:
    """Where ``value`` (JSON-like) holds a NaN or an infinity: ``["sessions[1].probe.x = nan"]``."""
    import math

    if isinstance(value, float) and not math.isfinite(value):
        return [f"{where or '(top)'} = {value}"]
    if isinstance(value, dict):
        return [p for k, v in value.items() for p in non_finite_numbers(v, f"{where}.{k}" if where else str(k))]
    if isinstance(value, (list, tuple)):
        return [p for i, v in enumerate(value) for p in non_finite_numbers(v, f"{where}[{i}]")]
    return []


def card_text(card: dict) -> str:
    """The card's bytes (as text): key-sorted, indented JSON, no NaN, trailing newline; a NaN or
    infinity that reached the card is a ValueError naming where it is."""
    import json

    bad = non_finite_numbers(card)
    if bad:
        raise ValueError(f"dataset card: not finite, so not JSON: {', '.join(bad[:10])}"
                         + (f" and {len(bad) - 10} more" if len(bad) > 10 else ""))
    return json.dumps(card, sort_keys=True, indent=1, ensure_ascii=False, allow_nan=False) + "\n"
