"""Lighting geometry: lat-long grids, spherical harmonics, resampling, analytic lobes.

>>> from f2l.lighting import LatLongGrid, rotate_y
>>> LatLongGrid().shape  # the default grid: the full sphere at 64 x 128
(64, 128)
>>> rotate_y(LatLongGrid().solid_angles, 1.0).shape
(64, 128)
"""

from f2l.lighting.grid import LatLongGrid, rotate_y

__all__ = ["LatLongGrid", "rotate_y"]
