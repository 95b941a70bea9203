"""The Preetham et al. (1999) analytic daylight sky, for numpy arrays and torch tensors alike.

A. J. Preetham, P. Shirley, B. Smits, "A practical analytic model for daylight", SIGGRAPH 1999,
appendix A.2. Every function here takes numpy arrays or torch tensors (the namespace follows the
first argument) and broadcasts; angles are radians, t is the (dimensionless) turbidity.

- Perez et al. (1993) distribution, one per quantity q in (Y, x, y):
      F(theta, gamma) = (1 + A e^{B / cos theta}) (1 + C e^{D gamma} + E cos^2 gamma),
  theta the zenith angle of the sky element, gamma its angle to the sun.
  ``cos theta`` is clamped to >= ``COS_THETA_MIN`` (1e-3), so F is finite at and below the
  horizon (B < 0 for t > 1.2, so the clamp changes nothing visible: e^{B/1e-3} ~ 0).
- Coefficients linear in t (A2): [A, B, C, D, E]_q = slope_q t + offset_q  (``PEREZ_SLOPE/OFFSET``).
- Zenith luminance (A2), Y_z in kcd/m^2:
      Y_z = (4.0453 t - 4.9710) tan chi - 0.2155 t + 2.4192,  chi = (4/9 - t/120)(pi - 2 theta_s).
- Zenith chromaticity (A2): x_z = [t^2, t, 1] M_x [theta_s^3, theta_s^2, theta_s, 1]^T, same for y.
- Sky element: q(theta, gamma) = q_z F_q(theta, gamma) / F_q(0, theta_s).

The fit is valid for roughly 2 <= t <= 10 and the sun above the horizon. Over the paper's
1.7 <= t <= 35 the Perez functions stay finite and positive (tests/test_sunsky.py), but the
chromaticity leaves the RGB gamut for t >~ 20 (x + y > 1 in places; the sunsky model clips RGB
at 0) and Y_z turns negative near the horizon for t > 11.2 -- callers that normalise the sky's
integral (as the sunsky model does) never need Y_z.
"""

from __future__ import annotations

import math

import numpy as np
import torch

COS_THETA_MIN = 1e-3

# Rows Y, x, y; columns A, B, C, D, E (Preetham 1999, appendix A.2).
PEREZ_SLOPE = np.array(
    [
        [0.1787, -0.3554, -0.0227, 0.1206, -0.0670],
        [-0.0193, -0.0665, -0.0004, -0.0641, -0.0033],
        [-0.0167, -0.0950, -0.0079, -0.0441, -0.0109],
    ]
)
PEREZ_OFFSET = np.array(
    [
        [-1.4630, 0.4275, 5.3251, -2.5771, 0.3703],
        [-0.2592, 0.0008, 0.2125, -0.8989, 0.0452],
        [-0.2608, 0.0092, 0.2102, -1.6537, 0.0529],
    ]
)
# Zenith chromaticity: rows t^2, t, 1; columns theta_s^3, theta_s^2, theta_s, 1.
ZENITH_X = np.array(
    [
        [0.00166, -0.00375, 0.00209, 0.0],
        [-0.02903, 0.06377, -0.03202, 0.00394],
        [0.11693, -0.21196, 0.06052, 0.25886],
    ]
)
ZENITH_Y = np.array(
    [
        [0.00275, -0.00610, 0.00317, 0.0],
        [-0.04214, 0.08970, -0.04153, 0.00516],
        [0.15346, -0.26756, 0.06670, 0.26688],
    ]
)


def _ns(x):
    return torch if isinstance(x, torch.Tensor) else np


def _const(arr: np.ndarray, like):
    if isinstance(like, torch.Tensor):
        return torch.as_tensor(arr, dtype=like.dtype, device=like.device)
    return arr


def perez_coefficients(turbidity):
    """(..., 3, 5) Perez coefficients [A..E] for Y, x, y at turbidity (...,)."""
    t = turbidity if isinstance(turbidity, torch.Tensor) else np.asarray(turbidity, dtype=np.float64)
    t = t[..., None, None]
    return t * _const(PEREZ_SLOPE, t) + _const(PEREZ_OFFSET, t)


def perez_theta_factor(cos_theta, coeffs):
    """1 + A e^{B / cos theta}, cos theta clamped to >= COS_THETA_MIN; coeffs (..., 5)."""
    xp = _ns(cos_theta)
    ct = np.clip(cos_theta, COS_THETA_MIN, None) if xp is np else cos_theta.clamp_min(COS_THETA_MIN)
    return 1.0 + coeffs[..., 0] * xp.exp(coeffs[..., 1] / ct)


def perez_gamma_factor(gamma, cos_gamma, coeffs):
    """1 + C e^{D gamma} + E cos^2 gamma; coeffs (..., 5)."""
    xp = _ns(gamma)
    return 1.0 + coeffs[..., 2] * xp.exp(coeffs[..., 3] * gamma) + coeffs[..., 4] * (cos_gamma * cos_gamma)


def perez(cos_theta, gamma, cos_gamma, coeffs):
    """Perez F(theta, gamma); coeffs (..., 5) broadcast against the angles' shape + (5,) -> (...).

    ``cos_theta`` is clamped to >= COS_THETA_MIN (finite at and below the horizon); ``gamma``
    (radians) and ``cos_gamma`` are both passed so a caller can compute gamma robustly.
    """
    return perez_theta_factor(cos_theta, coeffs) * perez_gamma_factor(gamma, cos_gamma, coeffs)


def zenith_luminance(turbidity, sun_zenith_rad):
    """Y_z (kcd/m^2) of Preetham's appendix A.2 (may be negative outside the fit's range)."""
    xp = _ns(turbidity)
    t = turbidity
    chi = (4.0 / 9.0 - t / 120.0) * (math.pi - 2.0 * sun_zenith_rad)
    return (4.0453 * t - 4.9710) * xp.tan(chi) - 0.2155 * t + 2.4192


def zenith_chromaticity(turbidity, sun_zenith_rad):
    """(x_z, y_z) CIE chromaticity of the zenith (Preetham appendix A.2 cubic polynomials)."""
    xp = _ns(turbidity)
    t, s = turbidity, sun_zenith_rad
    tv = xp.stack([t * t, t, t * 0.0 + 1.0], -1)
    sv = xp.stack([s * s * s, s * s, s, s * 0.0 + 1.0], -1)
    return _bilinear(tv, ZENITH_X, sv), _bilinear(tv, ZENITH_Y, sv)


def _bilinear(u, m, v):
    """sum_ij u_i m_ij v_j over the last axes of u (..., 3) and v (..., 4)."""
    return (u[..., :, None] * _const(m, u) * v[..., None, :]).sum((-1, -2))


def sky_xyY(cos_theta, gamma, cos_gamma, turbidity, sun_zenith_rad, y_floor: float = 1e-3):
    """Relative sky colour (x, y, Y_rel) with Y_rel = F_Y(theta, gamma) / F_Y(0, theta_s).

    The absolute zenith luminance Y_z is left out (it only scales the sky, and turns negative
    outside the fit's range). ``turbidity`` and ``sun_zenith_rad`` have the batch shape (...,);
    the angles have shape (..., N) (or broadcast to it); each output is (..., N). F_Y is floored
    at 1e-12 and y at ``y_floor`` so the xyY -> XYZ division is always finite.
    """
    xp = _ns(cos_theta)
    coeffs = perez_coefficients(turbidity)  # (..., 3, 5), rows Y, x, y
    ts = sun_zenith_rad
    one = ts * 0.0 + 1.0
    f0 = perez(one[..., None], ts[..., None], xp.cos(ts)[..., None], coeffs)  # (..., 3)
    # (..., 3, N): quantity axis before the texel axis, so broadcasting stays contiguous
    f = perez(cos_theta[..., None, :], gamma[..., None, :], cos_gamma[..., None, :], coeffs[..., None, :])
    rel = f / f0[..., None]
    xz, yz = zenith_chromaticity(turbidity, ts)
    x = xz[..., None] * rel[..., 1, :]
    y = yz[..., None] * rel[..., 2, :]
    big = rel[..., 0, :]
    if xp is np:
        return x, np.maximum(y, y_floor), np.maximum(big, 1e-12)
    return x, y.clamp_min(y_floor), big.clamp_min(1e-12)


def xyY_to_XYZ(x, y, big_y, axis: int = -1):
    """CIE xyY -> XYZ, stacked on a new ``axis``: X = x Y / y, Z = (1 - x - y) Y / y."""
    xp = _ns(x)
    r = big_y / y
    return xp.stack([x * r, big_y, (1.0 - x - y) * r], axis)
