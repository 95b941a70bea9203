"""The other heads of a photo as occluders: a neighbour's shadow on a face (joint estimates).

A face's transport holds its own head's shadow only (f2l.transport.visibility: rays against its
own fitted mesh). In a group photo the heads stand 30-60 cm apart, and a low sun along the row puts
part of a face in its neighbour's shadow; the joint estimate then reads that face as lit by a
lower or weaker sun than its photo-mates, and the one face with the steepest objective can pull the
group's light its way (docs/experiments/joint_estimate.md, "Neighbours' shadows").

Each other face of the same photo stands for its head by a sphere fitted from its record: centre
the face pixels' centroid moved back along their mean normal by ``DEPTH_SHARE`` x the face's width,
radius ``RADIUS_SHARE`` x that width (an adult face ~14 cm wide: a head sphere of r ~ 8.4 cm
centred ~7.7 cm behind the face's surface). Two spheres that overlap are not two heads (one head's
frames, faces rendered apart and stacked as one photo): they cast nothing on each other. From a pixel p the sphere (c, r) covers the cone of
directions w with

    w . (c - p) / |c - p| > sqrt(1 - r^2 / |c - p|^2),

and those texels' visibility bits are cleared. Points and directions are in the camera frame
(camera at the origin, the grid's axes: +Y up, the camera looking along -Z), as the records hold
them; the units cancel. Faces of other photos are not occluders (their frames differ).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from f2l.estimate.observation import FaceObservation

DEPTH_SHARE = 0.55  # the head sphere's centre behind the face's centroid, x the face's width
RADIUS_SHARE = 0.6  # the head sphere's radius, x the face's width
_POPCOUNT = np.array([bin(b).count("1") for b in range(256)], np.int64)  # set bits of a byte


def head_sphere(obs: FaceObservation) -> tuple[np.ndarray, float] | None:
    """(centre (3,), radius) of the sphere standing for ``obs``'s head, or None without points."""
    if obs.points is None:
        return None
    mask = np.asarray(obs.mask, bool)
    pts = np.asarray(obs.points, np.float64)[mask]
    nrm = np.asarray(obs.normals, np.float64)[mask]
    if len(pts) < 16:
        return None
    facing = nrm.mean(0)
    norm = float(np.linalg.norm(facing))
    if norm < 1e-6:
        return None
    facing /= norm
    # the face's width across its facing direction: the spread of its points in the plane
    centred = pts - pts.mean(0)
    across = centred - np.outer(centred @ facing, facing)
    width = float(np.percentile(np.linalg.norm(across, axis=1), 98)) * 2.0
    if not np.isfinite(width) or width <= 0:
        return None
    return pts.mean(0) - DEPTH_SHARE * width * facing, RADIUS_SHARE * width


def occluded_bits(points: np.ndarray, spheres: list[tuple[np.ndarray, float]], directions: np.ndarray) -> np.ndarray:
    """(N, ceil(L / 8)) uint8, little bit order (as visibility bits): texel j of pixel i is 1 where a
    sphere covers direction j from point i."""
    pts = np.asarray(points, np.float64)
    dirs = np.asarray(directions, np.float64)
    out = np.zeros((len(pts), (len(dirs) + 7) // 8), np.uint8)
    centroid = pts.mean(0)
    spread = float(np.linalg.norm(pts - centroid, axis=1).max())
    for centre, radius in spheres:
        # the texels any pixel can see the sphere in: within its cone from the centroid, widened by
        # the face's own extent (the pixels lie within ``spread`` of the centroid)
        to_c = centre - centroid
        d_c = float(np.linalg.norm(to_c))
        if d_c <= radius + spread:
            reach = np.pi
        else:
            reach = np.arcsin(min(1.0, radius / (d_c - spread))) + np.arcsin(min(1.0, spread / d_c))
        cols = np.flatnonzero(dirs @ (to_c / max(d_c, 1e-12)) > np.cos(min(reach, np.pi)))
        if cols.size == 0:
            continue
        v = centre[None, :] - pts
        dist = np.linalg.norm(v, axis=1)
        outside = dist > radius * (1.0 + 1e-6)
        cos_edge = np.sqrt(np.clip(1.0 - (radius / np.maximum(dist, 1e-12)) ** 2, 0.0, 1.0)).astype(np.float32)
        u = (v / np.maximum(dist, 1e-12)[:, None]).astype(np.float32)
        inside = ((u @ dirs[cols].T.astype(np.float32)) > cos_edge[:, None]) & outside[:, None]  # (N, k)
        for k, j in enumerate(cols):  # set bit j (little order: byte j // 8, bit j % 8)
            out[:, j // 8] |= inside[:, k].astype(np.uint8) << np.uint8(j % 8)
    return out


def with_neighbours(observations: list[FaceObservation], photo: list[int]) -> tuple[list[FaceObservation], list[float]]:
    """The observations with each face's visibility cleared where another head of its photo
    (``photo``: the faces' photo or exposure group numbers) covers the sky, and per face the share
    of its visible upper-hemisphere texel bits that were cleared. Faces without points, or alone in
    their photo, are returned as they are."""
    spheres = [head_sphere(o) for o in observations]
    out, shares = [], []
    for i, obs in enumerate(observations):
        own = spheres[i]
        # heads that overlap this one are not two heads (frames of one head, faces rendered apart
        # and stacked as one photo): no shadow from them
        others = [s for j, s in enumerate(spheres) if j != i and s is not None and photo[j] == photo[i]
                  and (own is None or np.linalg.norm(s[0] - own[0]) > s[1] + own[1])]
        if not others or obs.points is None:
            out.append(obs)
            shares.append(0.0)
            continue
        bits = np.asarray(obs.visibility_bits, np.uint8)
        occ = occluded_bits(obs.points, others, obs.grid.directions_flat)
        cleared = bits & ~occ
        upper = obs.grid.sky_rows * obs.grid.width // 8  # whole bytes of the upper rows
        before, after = int(_POPCOUNT[bits[:, :upper]].sum()), int(_POPCOUNT[cleared[:, :upper]].sum())
        shares.append(1.0 - after / max(before, 1))
        out.append(dataclasses.replace(obs, visibility_bits=cleared))
    return out, shares
