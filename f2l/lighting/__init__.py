"""Lighting geometry: lat-long grids, spherical harmonics, resampling, analytic lobes."""

from f2l.lighting.grid import LatLongGrid, rotate_y

__all__ = ["LatLongGrid", "rotate_y"]
