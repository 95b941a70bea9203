"""Box-bounded parameters as unconstrained variables (so a quasi-Newton method needs no bounds).

For bounds [lo, hi]:  both finite -> lo + (hi - lo) * sigmoid(x);  lo only -> lo + softplus(x);
hi only -> hi - softplus(x);  none -> x.  ``to_unconstrained`` is the inverse (clipped inside).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


class BoxTransform:
    def __init__(self, lower: np.ndarray, upper: np.ndarray) -> None:
        self.lower = np.asarray(lower, dtype=np.float64)
        self.upper = np.asarray(upper, dtype=np.float64)
        lo_ok, hi_ok = np.isfinite(self.lower), np.isfinite(self.upper)
        self.both = lo_ok & hi_ok
        self.lo_only = lo_ok & ~hi_ok
        self.hi_only = hi_ok & ~lo_ok

    def to_params(self, x: torch.Tensor) -> torch.Tensor:
        lo = torch.as_tensor(np.where(np.isfinite(self.lower), self.lower, 0.0), dtype=x.dtype)
        hi = torch.as_tensor(np.where(np.isfinite(self.upper), self.upper, 0.0), dtype=x.dtype)
        both = torch.as_tensor(self.both)
        lo_only = torch.as_tensor(self.lo_only)
        hi_only = torch.as_tensor(self.hi_only)
        out = x
        out = torch.where(both, lo + (hi - lo) * torch.sigmoid(x), out)
        out = torch.where(lo_only, lo + F.softplus(x), out)
        out = torch.where(hi_only, hi - F.softplus(x), out)
        return out

    def to_unconstrained(self, p: np.ndarray, margin: float = 1e-6) -> np.ndarray:
        """Inverse of :meth:`to_params`; values within ``margin`` (a fraction of a two-sided range,
        an absolute distance for a one-sided bound) of a bound are moved that far inside."""
        p = np.asarray(p, dtype=np.float64)
        x = p.copy()
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            span = np.where(self.both, self.upper - self.lower, 1.0)
            frac = np.clip((p - self.lower) / span, margin, 1 - margin)
            x = np.where(self.both, np.log(frac) - np.log1p(-frac), x)
            d_lo = np.clip(p - self.lower, 1e-6, None)  # softplus: no saturation at the bound
            x = np.where(self.lo_only, np.where(d_lo > 20, d_lo, np.log(np.expm1(d_lo))), x)
            d_hi = np.clip(self.upper - p, 1e-6, None)
            x = np.where(self.hi_only, np.where(d_hi > 20, d_hi, np.log(np.expm1(d_hi))), x)
        return x
