"""Latitude-longitude grids in the f2l convention.

World frame: +Y up, the camera looks along -Z (+Z points from the face toward the camera),
+X is the camera's right. Row 0 is the zenith, the last row the nadir; the centre column
(u = 0.5) is the camera's viewing direction (-Z). At texel centres u, v in [0, 1]:

    theta = pi (2u - 1)        (azimuth, radians)
    phi   = pi v               (polar angle from +Y, radians)
    x = sin(phi) sin(theta),  y = cos(phi),  z = -sin(phi) cos(theta)

Solid angle of a texel: (2 pi / W) (cos phi0 - cos phi1); they sum to 4 pi.
Texels are flattened row-major: index = row * W + col.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class LatLongGrid:
    """A full-sphere lat-long grid of ``height`` rows and ``width`` columns (height even).

    >>> grid = LatLongGrid(8, 16)
    >>> grid.shape, grid.size, grid.sky_rows
    ((8, 16), 128, 4)
    >>> round(float(grid.solid_angles.sum() / np.pi), 9)  # the texels tile the sphere: 4 pi
    4.0
    >>> round(float(grid.solid_angles[: grid.sky_rows].sum() / np.pi), 9)  # the sky: 2 pi
    2.0
    >>> grid.directions.shape, grid.directions_flat.shape
    ((8, 16, 3), (128, 3))
    >>> bool((grid.directions[: grid.sky_rows, :, 1] > 0).all())  # the first H/2 rows look up (+Y)
    True
    """

    height: int = 64
    width: int = 128

    def __post_init__(self) -> None:
        if self.height < 2 or self.width < 2:
            raise ValueError(f"grid must be at least 2x2, got {self.height}x{self.width}")
        if self.height % 2:
            raise ValueError(f"grid height must be even (horizon on a row edge), got {self.height}")

    # -- sizes ---------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    @property
    def size(self) -> int:
        """Number of texels L = H * W."""
        return self.height * self.width

    # -- coordinates ---------------------------------------------------------------------
    @cached_property
    def u(self) -> np.ndarray:
        """Column centres u in (0, 1), shape (W,)."""
        return (np.arange(self.width, dtype=np.float64) + 0.5) / self.width

    @cached_property
    def v(self) -> np.ndarray:
        """Row centres v in (0, 1), shape (H,)."""
        return (np.arange(self.height, dtype=np.float64) + 0.5) / self.height

    @cached_property
    def theta_rad(self) -> np.ndarray:
        """Azimuth of each column centre, shape (W,), in (-pi, pi)."""
        return np.pi * (2.0 * self.u - 1.0)

    @cached_property
    def phi_rad(self) -> np.ndarray:
        """Polar angle from +Y of each row centre, shape (H,), in (0, pi)."""
        return np.pi * self.v

    @cached_property
    def phi_edges_rad(self) -> np.ndarray:
        """Row edges phi_0 .. phi_H, shape (H + 1,)."""
        return np.linspace(0.0, np.pi, self.height + 1)

    @cached_property
    def theta_edges_rad(self) -> np.ndarray:
        """Column edges, shape (W + 1,), from -pi to pi."""
        return np.linspace(-np.pi, np.pi, self.width + 1)

    @cached_property
    def directions(self) -> np.ndarray:
        """Unit directions of texel centres, shape (H, W, 3), float64."""
        phi = self.phi_rad[:, None]
        theta = self.theta_rad[None, :]
        sin_phi = np.sin(phi)
        d = np.stack(
            np.broadcast_arrays(sin_phi * np.sin(theta), np.cos(phi), -sin_phi * np.cos(theta)),
            axis=-1,
        )
        d.setflags(write=False)
        return d

    @cached_property
    def directions_flat(self) -> np.ndarray:
        """Texel directions flattened row-major, shape (L, 3)."""
        d = np.ascontiguousarray(self.directions.reshape(-1, 3))
        d.setflags(write=False)
        return d

    @cached_property
    def row_solid_angles(self) -> np.ndarray:
        """Solid angle of one texel in each row, shape (H,): (2 pi / W)(cos phi0 - cos phi1)."""
        edges = self.phi_edges_rad
        return (2.0 * np.pi / self.width) * (np.cos(edges[:-1]) - np.cos(edges[1:]))

    @cached_property
    def solid_angles(self) -> np.ndarray:
        """Solid angle of every texel, shape (H, W), float64; sums to 4 pi."""
        sa = np.repeat(self.row_solid_angles[:, None], self.width, axis=1)
        sa.setflags(write=False)
        return sa

    @cached_property
    def solid_angles_flat(self) -> np.ndarray:
        sa = np.ascontiguousarray(self.solid_angles.reshape(-1))
        sa.setflags(write=False)
        return sa

    @property
    def sky_rows(self) -> int:
        """Rows of the upper hemisphere (y > 0): the first H/2 rows."""
        return self.height // 2

    @cached_property
    def upper_mask(self) -> np.ndarray:
        """Boolean (H, W) mask of the upper (sky) hemisphere."""
        m = np.zeros(self.shape, dtype=bool)
        m[: self.sky_rows] = True
        m.setflags(write=False)
        return m

    # -- conversions -----------------------------------------------------------------------
    def direction_to_uv(self, directions: np.ndarray) -> np.ndarray:
        """Map unit directions (..., 3) to (u, v) in [0, 1] (inverse of the texel formula).

        The camera's viewing direction -Z is the centre of the image (u = v = 0.5):

        >>> LatLongGrid(8, 16).direction_to_uv(np.array([0.0, 0.0, -1.0])).tolist()
        [0.5, 0.5]
        """
        d = np.asarray(directions, dtype=np.float64)
        x, y, z = d[..., 0], d[..., 1], d[..., 2]
        phi = np.arccos(np.clip(y, -1.0, 1.0))
        theta = np.arctan2(x, -z)
        return np.stack([(theta / np.pi + 1.0) / 2.0, phi / np.pi], axis=-1)

    def direction_to_texel(self, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row and column indices (int) of the texel containing each direction (..., 3).

        >>> row, col = LatLongGrid(8, 16).direction_to_texel(np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]))
        >>> row.tolist(), col.tolist()  # the zenith is in row 0; +X (azimuth +pi/2) in column 12
        ([0, 4], [15, 12])
        """
        uv = self.direction_to_uv(directions)
        col = np.clip(np.floor(uv[..., 0] * self.width).astype(np.int64), 0, self.width - 1)
        row = np.clip(np.floor(uv[..., 1] * self.height).astype(np.int64), 0, self.height - 1)
        return row, col

    def angle_to_columns(self, angle_rad: float) -> float:
        """Azimuth angle expressed in columns (W / 2 pi per radian).

        >>> LatLongGrid(64, 128).angle_to_columns(np.pi / 2)
        32.0
        """
        return angle_rad * self.width / (2.0 * np.pi)


def direction_from_angles(elevation_rad, azimuth_rad) -> np.ndarray:
    """Unit direction from elevation above the horizon and azimuth theta (grid convention).

    Azimuth 0 is the camera's viewing direction (-Z), +pi/2 is +X (camera right).

    >>> np.round(direction_from_angles(0.0, 0.0), 9).tolist()  # on the horizon, straight ahead: -Z
    [0.0, 0.0, -1.0]
    >>> bool(np.allclose(direction_from_angles(0.0, np.pi / 2), [1.0, 0.0, 0.0]))
    True
    >>> direction_from_angles([0.0, np.pi / 2], [0.0, 0.0]).shape  # broadcasts
    (2, 3)
    """
    elevation_rad = np.asarray(elevation_rad, dtype=np.float64)
    azimuth_rad = np.asarray(azimuth_rad, dtype=np.float64)
    phi = np.pi / 2.0 - elevation_rad
    return np.stack(
        [np.sin(phi) * np.sin(azimuth_rad), np.cos(phi), -np.sin(phi) * np.cos(azimuth_rad)], axis=-1
    )


def angles_from_direction(direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(elevation_rad, azimuth_rad) of unit directions (..., 3); inverse of direction_from_angles.

    >>> elevation, azimuth = angles_from_direction(direction_from_angles(0.5, -1.0))
    >>> round(float(elevation), 9), round(float(azimuth), 9)
    (0.5, -1.0)
    """
    d = np.asarray(direction, dtype=np.float64)
    elevation = np.arcsin(np.clip(d[..., 1], -1.0, 1.0))
    azimuth = np.arctan2(d[..., 0], -d[..., 2])
    return elevation, azimuth


def rotate_y(probe: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotate a lat-long probe (H, W, ...) by ``angle_rad`` about +Y (right-handed).

    A light at azimuth theta moves to theta - angle_rad (R_y maps theta to theta - angle), so the
    result is a column roll by -angle * W / (2 pi). Whole-column angles are an exact roll;
    fractional ones interpolate linearly between the two neighbouring rolls (periodic).

    >>> probe = np.zeros((4, 8))
    >>> probe[1, 4] = 1.0  # a light in column 4 (azimuth pi/8)
    >>> int(np.argmax(rotate_y(probe, 2 * np.pi / 8)[1]))  # rotated by one column's angle
    3
    >>> rotate_y(probe, np.pi / 8)[1].tolist()  # half a column: split between two columns
    [0.0, 0.0, 0.0, 0.5, 0.5, 0.0, 0.0, 0.0]
    """
    probe = np.asarray(probe)
    width = probe.shape[1]
    shift = -angle_rad * width / (2.0 * np.pi)
    whole = np.floor(shift)
    frac = shift - whole
    rolled = np.roll(probe, int(whole) % width, axis=1)
    if frac < 1e-12:
        return rolled
    if frac > 1.0 - 1e-12:
        return np.roll(probe, (int(whole) + 1) % width, axis=1)
    nxt = np.roll(rolled, 1, axis=1)
    return (1.0 - frac) * rolled + frac * nxt
