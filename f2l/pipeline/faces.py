"""The calibrate and fit-faces (+ transport) stages of ``build-dataset``: one cache entry per photo.

- ``calibrate`` entry (key: the chart photo's path and SHA-256, method, chart edition): ``done``
  holds ``{status, reason, camera, correction, delta_e}`` from
  :func:`f2l.colour.calibrate.calibrate_photo`. Statuses as ``f2l calibrate``: ``ok``,
  ``partial``, ``identity``, ``no_chart``, ``error``; every row carries a correction (identity
  unless fitted).
- ``fit-faces`` entry (key: the photo's path and SHA-256, the landmarker model's pinned SHA-256,
  the fit-faces and transport parameters and the grid): ``part-00000.parquet`` (the photo's
  face records in camera RGB, schema ``face_record``, ``source_path`` relative to the capture
  root, no ground truth yet), ``photos/<face_id>.png`` crops and ``overlays/<face_id>.png``;
  ``done`` holds ``{status, message, num_detected, face_ids, rejected}`` with statuses as
  ``f2l fit-faces`` (``ok``, ``no_face``, ``rejected``, ``error``) plus per-photo ``timings``
  that only the run log reads. Transport runs inside the fit (one Embree scene per face), so
  it has no entries of its own. Records hold no timings (``meta.timings`` is dropped), so the
  same photo gives the same bytes.

A photo that cannot be read or fitted gets its status and a message (relative paths); the
failure is cached like a success, so an unchanged bad photo is not retried.
"""

from __future__ import annotations

import time
from pathlib import Path

from f2l.pipeline.cache import Cache, stage_key
from f2l.pipeline.plan import relative_message

CALIBRATE_VERSION = 1
FIT_VERSION = 5  # 2: large photos detected on a reduced copy, fitted from full-resolution windows;
# 3: clipped skin pixels get traced visibility (the estimator reads them as censored observations);
# 4: faces at every scale (BlazeFace full range over a pyramid of windows), every face of a photo,
# the face width along the eye line, a whole-photo overlay; 5: blurred faces refused (blur index)


def _rounded(stats: dict) -> dict:
    import math

    return {k: (round(float(v), 6) if math.isfinite(v) else None) for k, v in sorted(stats.items())}


def calibrate_chart(cache: Cache, root: Path, row: dict, params: dict, counts: dict,
                    timings: dict) -> dict:
    """The chart photo's correction: ``{"key", "path", "camera", **result}``."""
    method, edition = params["method"], params["chart"]
    key = stage_key("calibrate", CALIBRATE_VERSION, {"path": row["path"], "sha256": row["sha256"]},
                    {"method": method, "chart": edition})

    def produce(tmp: Path) -> dict:
        from f2l.colour.calibrate import calibrate_photo
        from f2l.colour.fit import ColourCorrection
        from f2l.io.photo import load_photo

        t0 = time.perf_counter()
        out = {"status": "error", "reason": "", "correction": ColourCorrection.identity().to_dict(),
               "delta_e": {}, "n_valid_patches": 0}
        try:
            photo = load_photo(root / row["path"])
            status, reason, _, fit = calibrate_photo(
                photo.display, photo.linear, clipped=photo.clipped, edition=edition,
                method=method, source=row["path"])
            out.update(status=status, reason=reason)
            if fit is not None:
                out.update(correction=fit.correction.to_dict(), delta_e=_rounded(fit.stats()),
                           n_valid_patches=int(fit.valid.sum()))
        except Exception as exc:  # noqa: BLE001 - one bad chart never stops the build
            out["reason"] = relative_message(str(exc), root)
        timings[f"calibrate {row['path']}"] = round(time.perf_counter() - t0, 3)
        return out

    result, _ = cache.get_or_make("calibrate", key, produce, counts)
    return {"key": key, "path": row["path"], "camera": row["camera"] or "", **result}


def fit_options(fit: dict, transport: dict, grid_hw: tuple[int, int]):
    """:class:`f2l.face.fit.FitOptions` of the pipeline's fit-faces and transport parameters."""
    from f2l.face.fit import FitOptions
    from f2l.lighting.grid import LatLongGrid

    return FitOptions(
        resolution=int(fit["resolution"]), margin=float(fit["margin"]),
        subdivisions=int(fit["subdivisions"]), depth_source=fit["depth"],
        grid=LatLongGrid(*grid_hw), visibility_method=transport["visibility"],
        lattice_levels=int(transport["lattice_levels"]), transport_pixels=transport["pixels"],
        threads=int(transport["threads"]), min_face_px=float(fit["min_face_px"]),
        max_yaw_deg=float(fit["max_yaw_deg"]),
        max_outside_fraction=float(fit["max_outside_fraction"]),
        min_mask_pixels=int(fit["min_mask_pixels"]), max_faces=int(fit["max_faces"]))


def fit_key(row: dict, fit: dict, transport: dict, grid_hw: tuple[int, int]) -> str:
    from f2l.face.landmarker import DETECTOR_SHA256
    from f2l.face.mesh import FACE_LANDMARKER_SHA256

    return stage_key("fit-faces", FIT_VERSION,
                     {"path": row["path"], "sha256": row["sha256"],
                      "landmarker_sha256": FACE_LANDMARKER_SHA256, "detector_sha256": DETECTOR_SHA256},
                     {"fit-faces": fit, "transport": transport, "grid": list(grid_hw)})


class FaceFitter:
    """Fits face photos into cache entries; the landmarker loads with the first photo to fit."""

    def __init__(self, cache: Cache, root: Path, fit: dict, transport: dict,
                 grid_hw: tuple[int, int], landmarker_path=None):
        self.cache, self.root = cache, root
        self.fit, self.transport, self.grid_hw = fit, transport, tuple(grid_hw)
        self.options = fit_options(fit, transport, grid_hw)
        self.landmarker_path = landmarker_path
        self._landmarker = None

    def landmarker(self):
        if self._landmarker is None:
            from f2l.face.landmarker import FaceLandmarker

            self._landmarker = FaceLandmarker(self.landmarker_path, threads=1)
        return self._landmarker

    def __call__(self, row: dict, counts: dict, timings: dict) -> dict:
        """The photo's entry: ``{"key", "entry", "path", "camera", **result}``."""
        key = fit_key(row, self.fit, self.transport, self.grid_hw)
        result, entry = self.cache.get_or_make(
            "fit-faces", key, lambda tmp: self._produce(tmp, row, timings), counts)
        return {"key": key, "entry": str(entry), "path": row["path"], "sha256": row["sha256"],
                "camera": row["camera"] or "", **result}

    def _produce(self, tmp: Path, row: dict, timings: dict) -> dict:
        from f2l.face.fit import FaceFit, face_record, fit_photo_faces
        from f2l.io.photo import load_photo
        from f2l.face.run import _overlay, _photo_overlay, face_id
        from f2l.io.shards import ShardWriter
        from f2l.io.side_files import write_side_photo

        t0 = time.perf_counter()
        rel = row["path"]
        out = {"status": "error", "message": "", "num_detected": 0, "face_ids": [],
               "rejected": [], "timings": {}}
        try:
            photo = load_photo(self.root / rel)
            fits = fit_photo_faces(photo, self.landmarker(), self.options)
            out["num_detected"] = len(fits)
            written: list = []
            with ShardWriter(tmp, records_per_shard=max(1, len(fits))) as writer:
                for fit in fits:
                    if not isinstance(fit, FaceFit):
                        out["rejected"].append({"face_index": fit.face_index,
                                                "reason": fit.reason,
                                                "message": f"{rel}: {fit.message}",
                                                "box": None if fit.box is None else [round(v, 2) for v in fit.box]})
                        continue
                    fid = face_id(Path(rel), row["sha256"], fit.face_index)
                    record = face_record(fit, photo, fid, self.options, source_path=rel,
                                         photo_rel=write_side_photo(tmp, fid, fit.crop_display))
                    out["timings"][fid] = record.meta.pop("timings")
                    if self.fit["overlays"]:
                        record.meta["overlay_path"] = _overlay(tmp, fid, fit, self.options)
                    writer.write(record)
                    out["face_ids"].append(fid)
                    written.append((record, 0.0))
            if self.fit["overlays"] and fits:
                out["overlay_path"] = _photo_overlay(tmp, Path(rel), row["sha256"], photo, fits, written)
            if out["face_ids"]:
                out["status"] = "ok"
                out["message"] = f"{rel}: {len(out['face_ids'])} face(s)"
            elif fits:
                out["status"] = "rejected"
                out["message"] = "; ".join(r["message"] for r in out["rejected"])
            else:
                out["status"], out["message"] = "no_face", f"{rel}: no face detected"
        except Exception as exc:  # noqa: BLE001 - one bad photo never stops the build
            from f2l.face.landmarker import LandmarkerError
            from f2l.face.mesh import FaceMeshError

            if isinstance(exc, (LandmarkerError, FaceMeshError)):
                raise  # the model, not the photo: stop (nothing is cached)
            for part in tmp.glob("part-*.parquet"):
                part.unlink()
            out.update(status="error", face_ids=[], message=relative_message(str(exc), self.root))
            if not out["message"].startswith(rel):
                out["message"] = f"{rel}: {type(exc).__name__}: {out['message']}"
        out["timings"]["photo_s"] = round(time.perf_counter() - t0, 3)
        timings[f"fit-faces {rel}"] = out["timings"]["photo_s"]
        return out
