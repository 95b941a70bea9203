"""Fitted face geometry against the ground truth of synthetic photos (``f2l eval compare-geometry``).

Records pair up by photo: ``f2l eval synth`` writes ``photos/<face_id>.png``, so a fitted record's
source-file stem is the ground-truth face id. For each fitted record the *true-geometry twin*
keeps everything the fit measured (pixels, observed RGB, mask) and swaps the geometry for the
truth: the working pixels' camera rays (``meta["crop"]`` maps working pixel (r, c) to photo
point ``(x0 + (c + 0.5) k, y0 + (r + 0.5) k)``, k = side / resolution) are cast against the
true posed mesh (:func:`f2l.synth.render.posed_face_mesh`, the synthetic camera of
``meta["focal_px"]``), giving true points and normals, and the visibility is recomputed on that
mesh. Pixels the true mesh misses (or sees at grazing angles) are masked out of the twin.
Estimating both and comparing their Sun-ang isolates the cost of the fitted geometry. Normal
errors are the angles between fitted and twin normals over the pixels in both masks.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from f2l.face import geometry
from f2l.io.shards import ShardWriter, iter_records
from f2l.io.side_files import load_gt_probe, write_side_probe
from f2l.synth.render import posed_face_mesh
from f2l.transport import compute_visibility


def true_geometry_twin(fitted, truth, threads: int = 2):
    """(twin record, normal errors in degrees over the common masked pixels)."""
    pose = truth.meta["pose_deg"]
    vertices, faces, vnormals = posed_face_mesh((pose["yaw"], pose["pitch"], pose["roll"]))
    return twin_from_mesh(fitted, vertices, faces, vnormals, float(truth.meta["focal_px"]),
                          (truth.image_height, truth.image_width), dict(truth_id=truth.face_id), threads)


def twin_from_mesh(fitted, vertices, faces, vnormals, focal_px: float, image_hw, extra_meta=None,
                   threads: int = 2):
    """The twin of ``fitted`` on a true mesh given in the camera frame (camera at the origin
    looking along −Z, cm), seen by a pinhole of ``focal_px`` over an ``image_hw`` photo."""
    crop = fitted.meta["crop"]
    k = crop["side"] / crop["resolution"]
    rc = fitted.pixel_rc.astype(np.float64)
    xy = np.stack([crop["x0"] + (rc[:, 1] + 0.5) * k, crop["y0"] + (rc[:, 0] + 0.5) * k], axis=1)
    rays = geometry.rays_for(xy, float(focal_px), tuple(image_hw))
    hit, points, normals = geometry.rasterise(vertices, faces, vnormals, rays)
    bits = compute_visibility(vertices, faces, points, normals, fitted.grid, threads=threads,
                              pixel_rc=fitted.pixel_rc[hit])
    twin_points = fitted.points.copy()
    twin_normals = fitted.normals.copy()
    twin_bits = fitted.visibility_bits.copy()
    twin_points[hit], twin_normals[hit], twin_bits[hit] = points, normals, bits
    covered = np.zeros(fitted.num_pixels, dtype=bool)
    covered[hit] = True
    mask = fitted.mask & covered
    cos = np.einsum("ij,ij->i", twin_normals[mask].astype(np.float64),
                    fitted.normals[mask].astype(np.float64))
    errors = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    meta = dict(fitted.meta, true_geometry_of=fitted.face_id, **(extra_meta or {}))
    twin = dataclasses.replace(fitted, points=twin_points, normals=twin_normals,
                               visibility_bits=twin_bits, mask=mask, meta=meta)
    return twin, errors


def compare_geometry(fitted_shards, truth_shards, twin_out=None, threads: int = 2) -> list[dict]:
    """One row per fitted face with its normal-error distribution; with ``twin_out``, the
    true-geometry twins are written there as shards (same face ids, ground-truth probes copied)."""
    truth = {r.face_id: r for r in iter_records(truth_shards) if getattr(r, "ok", False)}
    fitted_dirs = [Path(p) for p in ([fitted_shards] if isinstance(fitted_shards, (str, Path))
                                     else fitted_shards)]
    writer = ShardWriter(twin_out, overwrite=True) if twin_out is not None else None
    rows = []
    try:
        for fitted_dir in fitted_dirs:
            for rec in iter_records(fitted_dir):
                gt = truth.get(Path(rec.source_path).stem) if getattr(rec, "ok", False) else None
                if gt is None:
                    continue
                twin, ang = true_geometry_twin(rec, gt, threads)
                if writer is not None:
                    probe = load_gt_probe(fitted_dir, rec) if rec.gt_probe_path else None
                    twin.gt_probe_path = (write_side_probe(twin_out, twin.face_id, probe)
                                          if probe is not None else None)
                    twin.photo_path = None
                    writer.write(twin)
                pose = gt.meta.get("pose_deg", {})
                fit_pose = rec.meta.get("pose_deg", {})
                rows.append({
                    "face_id": rec.face_id, "truth_id": gt.face_id, "compared_px": int(ang.size),
                    "median_deg": float(np.median(ang)) if ang.size else float("nan"),
                    "p90_deg": float(np.percentile(ang, 90)) if ang.size else float("nan"),
                    "yaw_true": pose.get("yaw"), "yaw_fit": fit_pose.get("yaw"),
                    "pitch_true": pose.get("pitch"), "pitch_fit": fit_pose.get("pitch"),
                })
    except BaseException:
        if writer is not None:
            writer.abort()
        raise
    if writer is not None:
        writer.close()
    return rows
