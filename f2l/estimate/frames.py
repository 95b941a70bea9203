"""Faces of several photos in one frame: a face turned about +Y by its camera's heading.

A session's photos share the sky but not the camera's heading. A face photographed by a camera
turned ``yaw`` to the right of the session's reference camera sees at its probe azimuth ``a`` the
direction the reference camera sees at azimuth ``a + yaw`` (azimuth 0 = -Z, +90° = +X, the grid's
convention). Turning a face into the reference frame rotates its normals and points about +Y by
``yaw`` and rolls its visibility's columns by ``yaw / (360° / W)`` texels. The roll is exact for a
whole number of texels and rounded to the nearest one otherwise (at most half a texel: 1.4° on 128
columns), which is what the transport on the grid can represent.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from f2l.estimate.observation import FaceObservation
from f2l.lighting.grid import LatLongGrid


def yaw_columns(grid: LatLongGrid, yaw_deg: float) -> int:
    """The whole number of texel columns nearest to a turn of ``yaw_deg`` about +Y."""
    return int(round(float(yaw_deg) / (360.0 / grid.width)))


def yaw_matrix(yaw_rad: float) -> np.ndarray:
    """(3, 3) rotation about +Y taking azimuth a to a + yaw (azimuth = atan2(x, -z))."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def roll_probe(probe: np.ndarray, grid: LatLongGrid, yaw_deg: float) -> np.ndarray:
    """A probe (H, W, 3) of a camera turned ``yaw_deg`` right, seen from the reference frame (or,
    with ``-yaw_deg``, a reference probe seen from that camera): its columns rolled."""
    return np.roll(probe, yaw_columns(grid, yaw_deg), axis=1)


def turn_observation(obs: FaceObservation, yaw_deg: float) -> FaceObservation:
    """``obs`` (a face seen by a camera turned ``yaw_deg`` right of the reference camera) in the
    reference camera's frame: normals and points turned by the whole-column yaw, visibility rolled."""
    grid = obs.grid
    shift = yaw_columns(grid, yaw_deg)
    if shift % grid.width == 0:
        return obs
    turn = yaw_matrix(math.radians(shift * 360.0 / grid.width))
    bits = np.unpackbits(np.asarray(obs.visibility_bits), axis=1, bitorder="little", count=grid.size)
    bits = np.roll(bits.reshape(len(bits), grid.height, grid.width), shift, axis=2).reshape(len(bits), -1)
    packed = np.packbits(bits, axis=1, bitorder="little")
    normals = (np.asarray(obs.normals, np.float64) @ turn.T).astype(np.asarray(obs.normals).dtype)
    points = None if obs.points is None else (np.asarray(obs.points, np.float64) @ turn.T).astype(np.float32)
    return dataclasses.replace(obs, normals=normals, points=points, visibility_bits=packed)
