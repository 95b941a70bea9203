"""Sun energy share of an estimated and a ground-truth probe, and the overcast excess summary.

A probe's sun share is :func:`f2l.metrics.lighting.sun_energy_fraction`: the fraction of its
upper-hemisphere energy ``Σ_c l_c dΩ`` inside the 13° cap around its own brightest (max Rec.709 Y)
upper texel, so it needs no sun direction and is invariant to the probe's scale. Under an overcast
ground truth an estimate should not invent a sun: its excess is ``est share − gt share``, and a
face counts as exceeding when the excess is greater than :data:`SUN_SHARE_MARGIN` (0.1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from f2l.lighting.grid import LatLongGrid
from f2l.metrics.lighting import sun_energy_fraction

__all__ = [
    "SUN_SHARE_MARGIN",
    "SUN_SHARE_EST",
    "SUN_SHARE_GT",
    "GT_OVERCAST",
    "OvercastExcess",
    "sun_shares",
    "overcast_excess",
]

SUN_SHARE_MARGIN = 0.1
SUN_SHARE_EST = "sun_share_est"
SUN_SHARE_GT = "sun_share_gt"
GT_OVERCAST = "gt_overcast"


def sun_shares(est: np.ndarray, gt: np.ndarray, grid: LatLongGrid) -> dict[str, float]:
    """``{sun_share_est, sun_share_gt}``: the sun energy share of each (H, W, 3) probe.

    >>> grid = LatLongGrid(16, 32)
    >>> est = np.ones((16, 32, 3))
    >>> est[3, 20] = 2000.0  # an estimate with a sun under an overcast (uniform) ground truth
    >>> {name: round(share, 3) for name, share in sun_shares(est, np.ones((16, 32, 3)), grid).items()}
    {'sun_share_est': 0.889, 'sun_share_gt': 0.032}
    """
    return {SUN_SHARE_EST: sun_energy_fraction(est, grid), SUN_SHARE_GT: sun_energy_fraction(gt, grid)}


@dataclass(frozen=True)
class OvercastExcess:
    """Over a group's overcast faces with finite shares: ``n`` faces, ``exceed`` of them with
    ``est share > gt share + margin``, and ``max_excess = max(est share − gt share)`` (NaN if n = 0)."""

    n: int
    exceed: int
    max_excess: float

    @property
    def fraction(self) -> float:
        """``exceed / n`` (NaN if n = 0).

        >>> OvercastExcess(4, 1, 0.3).fraction, OvercastExcess(0, 0, math.nan).fraction
        (0.25, nan)
        """
        return self.exceed / self.n if self.n else math.nan


def _finite(v) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return math.nan
    return x if math.isfinite(x) else math.nan


def overcast_excess(rows: list[dict], margin: float = SUN_SHARE_MARGIN) -> OvercastExcess:
    """:class:`OvercastExcess` of the rows whose ``gt_overcast`` is a true bool (rows without
    both finite shares are left out).

    >>> rows = [
    ...     {"gt_overcast": True, "sun_share_est": 0.40, "sun_share_gt": 0.05},   # exceeds by 0.35
    ...     {"gt_overcast": True, "sun_share_est": 0.10, "sun_share_gt": 0.05},   # within the margin
    ...     {"gt_overcast": False, "sun_share_est": 0.90, "sun_share_gt": 0.80},  # clear: not counted
    ... ]
    >>> excess = overcast_excess(rows)
    >>> excess.n, excess.exceed, round(excess.max_excess, 6), excess.fraction
    (2, 1, 0.35, 0.5)
    """
    excess = []
    for r in rows:
        flag = r.get(GT_OVERCAST)
        if not isinstance(flag, (bool, np.bool_)) or not flag:
            continue
        d = _finite(r.get(SUN_SHARE_EST)) - _finite(r.get(SUN_SHARE_GT))
        if math.isfinite(d):
            excess.append(d)
    if not excess:
        return OvercastExcess(0, 0, math.nan)
    x = np.asarray(excess)
    return OvercastExcess(int(x.size), int(np.sum(x > margin)), float(x.max()))
