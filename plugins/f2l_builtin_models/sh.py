"""Spherical-harmonic lighting models SH9 (order 2) and SH25 (order 4), paper §3.3.

Basis: f2l's real orthonormal SH (``f2l.lighting.sh``; polar axis +Y, azimuth = grid theta, no
Condon-Shortley phase, index k = l(l+1)+m). Parameters are the coefficients, k-major then RGB:
params[3k + c]. The model covers the whole sphere (no separate ground), is linear in its
parameters (capability ``linear``: the estimator precomputes T @ Y once), and its probe is truncated at zero.

Prior (psi_l): a scale-invariant Gaussian on each band's coefficients relative to the mean DC
term, sigma_l = SIGMA_BAND[l]. A clamped-cosine (diffuse) observation sees band 3 not at all and
band 4 only weakly (A_3 = 0, A_4 = -pi/24), so without shadows those bands are set by the prior.
"""

from __future__ import annotations

import numpy as np
import torch

from f2l.lighting import sh as shlib
from f2l.models.base import LightingModel
from f2l.models.capabilities import LinearRadiance

SIGMA_BAND = (1.0, 2.0, 2.0, 1.0, 1.0)


class _SphericalHarmonics(LinearRadiance, LightingModel):
    order: int = 2
    domain = "sphere"
    version = "1"

    @property
    def num_coeffs(self) -> int:
        return (self.order + 1) ** 2

    @property
    def param_names(self) -> list[str]:
        names = []
        for l in range(self.order + 1):
            for m in range(-l, l + 1):
                names += [f"L{l}{m:+d}_{c}" for c in "RGB"]
        return names

    def initial_points(self) -> np.ndarray:
        """A uniform white sky (DC only), and the same plus light from above."""
        k = self.num_coeffs
        base = np.zeros((2, k, 3))
        base[:, 0, :] = 2.0 * np.sqrt(np.pi)  # radiance 1 everywhere
        base[1, 2, :] = 1.0  # l=1, m=0: brighter toward +Y
        return base.reshape(2, -1)

    def linear_basis(self) -> np.ndarray:
        return shlib.sh_basis_grid(self.grid, self.order)

    def radiance(self, params: torch.Tensor) -> torch.Tensor:
        basis = torch.as_tensor(np.array(self.linear_basis()), dtype=params.dtype, device=params.device)
        coeffs = params.reshape(params.shape[0], self.num_coeffs, 3)
        return torch.einsum("lk,bkc->blc", basis, coeffs)

    def prior_nll(self, params: torch.Tensor) -> torch.Tensor:
        coeffs = params.reshape(params.shape[0], self.num_coeffs, 3)
        dc = coeffs[:, 0, :].mean(-1).abs() + 1e-9  # (B,)
        nll = torch.zeros(params.shape[0], dtype=params.dtype, device=params.device)
        for l in range(1, self.order + 1):
            band = coeffs[:, l * l : (l + 1) * (l + 1), :]
            nll = nll + 0.5 * (band / (SIGMA_BAND[l] * dc[:, None, None])).pow(2).sum((1, 2))
        return nll

    def prior_nll_numpy(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """prior_nll and its gradient for one parameter vector, in closed form (numpy)."""
        coeffs = np.asarray(theta, dtype=np.float64).reshape(self.num_coeffs, 3)
        mean_dc = coeffs[0].mean()
        dc = abs(mean_dc) + 1e-9
        inv_var = np.zeros(self.num_coeffs)
        for l in range(1, self.order + 1):
            inv_var[l * l : (l + 1) * (l + 1)] = 1.0 / SIGMA_BAND[l] ** 2
        raw = 0.5 * float((inv_var[:, None] * coeffs**2).sum())
        grad = inv_var[:, None] * coeffs / dc**2
        grad[0] = -2.0 * raw / dc**3 * np.sign(mean_dc) / 3.0
        return raw / dc**2, grad.reshape(-1)

    def prior_precision(self, theta: np.ndarray) -> np.ndarray:
        """Diagonal of prior_nll's Hessian in theta (K, 3) with the DC scale held fixed (IRLS)."""
        coeffs = np.asarray(theta, dtype=np.float64).reshape(self.num_coeffs, 3)
        dc = abs(coeffs[0].mean()) + 1e-9
        prec = np.zeros_like(coeffs)
        for l in range(1, self.order + 1):
            prec[l * l : (l + 1) * (l + 1)] = 1.0 / (SIGMA_BAND[l] * dc) ** 2
        return prec

    def probe(self, params: np.ndarray) -> np.ndarray:
        """Reconstructed radiance truncated at zero (as the paper does for SH probes)."""
        return np.maximum(super().probe(params), 0.0)


class SH9(_SphericalHarmonics):
    name = "sh9"
    order = 2
    description = "Spherical harmonics to order 2 (9 RGB coefficients), full sphere"


class SH25(_SphericalHarmonics):
    name = "sh25"
    order = 4
    description = "Spherical harmonics to order 4 (25 RGB coefficients), full sphere"
