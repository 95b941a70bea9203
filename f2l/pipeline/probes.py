"""The merge and sphere stages of ``build-dataset``: one cache entry per bracket, one per session.

- ``merge`` entry (key: the bracket id, its frames' paths and SHA-256s, the frames' ``view_json``
  (vignetting), ``view_max_side``): ``views/<bracket>.exr`` and ``.saturated.png`` from
  :func:`f2l.capture.views.merge_bracket_view`; ``done`` holds the ``probes`` row.
- ``sphere`` entry (key: the session, the merge keys and ``view_json`` of its placed views, the
  grid): ``probes/<session>.exr`` + ``.coverage.png`` from
  :func:`f2l.capture.probes.assemble_session`, reading the merged views back from their entries;
  a probe that is black, sees less than a quarter of the sky or is not finite
  (:func:`f2l.lighting.plausibility.probe_problem`) is an ``error`` row, never ground truth.
- A given probe (role ``probe``: EXR or Radiance ``.hdr``, full-sphere lat-long, W = 2H) is the
  session's probe instead: a ``given-probe`` entry (key: its path, SHA-256 and the grid) holds
  ``probe.exr``, area-resampled to the grid when its size differs; refused (``error``, naming
  the session and the file) when unreadable or when it fails the same check.
- No row holds a NaN or an infinity: such a number makes the row an ``error`` that names it
  (:func:`f2l.capture.probe_rows.finite_row`), so nothing non-finite reaches a cache entry's JSON.

Probes are in linear Rec.709 from the sky camera's colour matrix (``colour_space``, default) and in
the session's tripod frame here; the chart's refinement and the turn to the face camera's frame
happen when the shards are assembled
(:mod:`f2l.pipeline.assemble`). Rows carry no timings (those go to the run log) and messages no
absolute paths.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from f2l.pipeline.cache import Cache, stage_key
from f2l.pipeline.plan import SessionPlan, relative_message

MERGE_VERSION = 2  # 2: colour matrix to Rec.709, lens descriptions and fall-off models (f2l.capture.lens)
SPHERE_VERSION = 3  # 2: sun from the views, colour space in the EXR and the row; 3: black/uncovered probes refused
GIVEN_PROBE_VERSION = 2  # 2: black, uncovered or non-finite given probes refused (probe_problem)


def _clean_row(row: dict, root) -> dict:
    """A stage row for a cache entry: no timing, no absolute path, no NaN (a non-finite number
    makes the row an ``error`` naming it, :func:`f2l.capture.probe_rows.finite_row`)."""
    from f2l.capture.probe_rows import finite_row

    out = finite_row({k: v for k, v in row.items() if k != "seconds"})
    out.pop("seconds", None)
    out["message"] = relative_message(out.get("message", ""), root)
    return out


def _bracket_inputs(bid: str, frames: list[dict]) -> dict:
    frames = sorted(frames, key=lambda f: f["path"])
    return {"bracket": bid, "frames": [[f["path"], f["sha256"]] for f in frames],
            "view_json": [f["view_json"] for f in frames]}


def merge_session(cache: Cache, root: Path, plan: SessionPlan, params: dict, counts: dict,
                  timings: dict) -> list[dict]:
    """Merge every bracket of ``plan``: a list of ``{"key", "row", "entry", "view_json"}`` in
    bracket order."""
    import time

    out = []
    for bid in sorted(plan.brackets):
        frames = plan.brackets[bid]
        key = stage_key("merge", MERGE_VERSION, _bracket_inputs(bid, frames),
                        {"view_max_side": int(params["view_max_side"]),
                         "colour_space": params.get("colour_space", "rec709")})

        def produce(tmp: Path, bid=bid, frames=frames) -> dict:
            from f2l.capture.views import merge_bracket_view

            t0 = time.perf_counter()
            row, _ = merge_bracket_view(root, tmp, bid, frames, int(params["view_max_side"]),
                                        params.get("colour_space", "rec709"))
            timings[f"merge {bid}"] = round(time.perf_counter() - t0, 3)
            return {"row": _clean_row(row, root)}

        result, entry = cache.get_or_make("merge", key, produce, counts)
        first = sorted(frames, key=lambda f: f["path"])[0]
        out.append({"key": key, "row": result["row"], "entry": str(entry), "view_json": first["view_json"],
                    "focal_length_mm": first.get("focal_length_mm")})
    return out


def sphere_session(cache: Cache, plan: SessionPlan, merged: list[dict], grid_hw: tuple[int, int],
                   counts: dict, timings: dict, restore_sun: bool = False) -> dict | None:
    """Assemble the session's placed views: ``{"key", "row", "entry"}``, or None when no view is
    placed (every bracket failed or has no lens model)."""
    import time

    placed = [m for m in merged if m["row"]["status"] == "ok"]
    if not placed:
        return None
    key = stage_key("sphere", SPHERE_VERSION,
                    {"session": plan.name, "views": [[m["key"], m["view_json"]] for m in placed]},
                    {"grid": list(grid_hw), "restore_sun": bool(restore_sun)})

    def produce(tmp: Path) -> dict:
        from f2l.capture.probe_rows import finite_row
        from f2l.capture.probes import assemble_session
        from f2l.capture.views import load_view

        t0 = time.perf_counter()
        views = [load_view(m["entry"], m["row"], m["view_json"], m.get("focal_length_mm")) for m in placed]
        row = assemble_session(plan.name, views, tmp, *grid_hw, [m["row"].get("colour_space") for m in placed],
                               restore_sun)
        timings[f"sphere {plan.name}"] = round(time.perf_counter() - t0, 3)
        return {"row": {k: v for k, v in finite_row(row).items() if k != "seconds"}}

    result, entry = cache.get_or_make("sphere", key, produce, counts)
    return {"key": key, "row": result["row"], "entry": str(entry)}


def read_probe_file(path: Path, grid_hw: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W, 3) float32 of an EXR, Radiance ``.hdr``, PFM or float TIFF (ValueError naming the
    file). ``grid_hw``: the grid the probe goes to; then a file that is no lat-long is refused from
    its header, and one over the readers' decode limit comes back area-averaged to the grid,
    decoded in bands (:func:`f2l.capture.probes.read_given_probe`): memory bounded by the grid."""
    from f2l.io.probe_io import read_hdr_image

    if grid_hw is None:
        return read_hdr_image(path)
    from f2l.capture.probes import read_given_probe

    return read_given_probe(path, *grid_hw)


def given_probe(cache: Cache, root: Path, plan: SessionPlan, grid_hw: tuple[int, int],
                counts: dict) -> dict:
    """The session's given probe on the grid: ``{"key", "row", "entry"}`` (row status ``error``
    with the reason when it cannot be used)."""
    row = plan.given_probe
    key = stage_key("given-probe", GIVEN_PROBE_VERSION, {"path": row["path"],
                                                         "sha256": row["sha256"]},
                    {"grid": list(grid_hw)})

    def produce(tmp: Path) -> dict:
        from f2l.capture.probes import given_probe_on_grid
        from f2l.io.exr import write_exr
        from f2l.io.probe_io import hdr_image_size

        out = {"kind": "given", "name": row["path"], "session": plan.name, "status": "ok",
               "message": "", "path": None}
        try:
            path = root / row["path"]
            probe, out["message"] = given_probe_on_grid(read_probe_file(path, grid_hw), row["path"], *grid_hw,
                                                        source_hw=hdr_image_size(path))
            write_exr(tmp / "probe.exr", probe, metadata={"f2l_session": plan.name})
            out["path"] = "probe.exr"
        except (ValueError, ArithmeticError) as exc:  # not MemoryError: that is no property of the file
            out.update(status="error", message=f"session {plan.name}: given probe refused: "
                                               + relative_message(str(exc), root))
        return {"row": out}

    result, entry = cache.get_or_make("given-probe", key, produce, counts)
    return {"key": key, "row": result["row"], "entry": str(entry)}
