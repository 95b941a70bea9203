"""Fit a camera RGB → linear Rec.709 colour correction to measured chart patches.

Order of operations (each step on the valid patches only):

1. White balance and exposure, from the neutral row (patches 19-24): per-channel gains
   ``g_c = Σ m_c r_c / Σ m_c²`` (least squares through the origin of reference ``r`` on measured
   ``m``), so the neutral axis and the overall scale are right before any cross-talk is modelled.
   Doing this first (a) makes the "before" ΔE of the report the error that white balance and
   exposure alone leave, so the table shows what the matrix adds; (b) hands the matrix fit inputs
   already at reference scale; and (c) keeps exposure, which changes from photo to photo, in the
   gains, apart from the matrix, which belongs to the camera.
2. Colour matrix on the balanced values ``b = g ⊙ m`` with colour-science
   (:func:`colour.matrix_colour_correction`): ``"Cheung 2004"`` with 3 terms (a plain 3 × 3
   matrix, the default, CLI name ``3x3``) or ``"Finlayson 2015"`` root-polynomial of degree 2
   (terms R, G, B, √RG, √GB, √RB: exposure-invariant; CLI name ``root-polynomial``).

A correction maps camera RGB ``c`` to ``M · expand(g ⊙ c)``. ΔE2000 per patch is computed in
CIELAB with the D65 white (:func:`f2l.colour.chart.rgb709_to_lab`) against the reference chart,
"before" = after step 1 only, "after" = after both steps. With fewer than ``MIN_VALID_PATCHES``
(6; 10 for root-polynomial) valid patches or fewer than ``MIN_NEUTRAL_PATCHES`` (2) valid neutral
patches, the result is the identity correction with status ``identity`` and a reason; it never raises.
"""

from __future__ import annotations

from dataclasses import dataclass

import colour
import numpy as np

from f2l.colour.chart import DEFAULT_EDITION, NEUTRAL_INDICES, ChartReference, reference_chart, rgb709_to_lab

METHODS = {"3x3": "Cheung 2004", "root-polynomial": "Finlayson 2015"}
IDENTITY = "identity"
ROOT_POLYNOMIAL_DEGREE = 2
MIN_VALID_PATCHES = {"Cheung 2004": 6, "Finlayson 2015": 10}
MIN_NEUTRAL_PATCHES = 2
_CHUNK_PIXELS = 1 << 20


@dataclass
class ColourCorrection:
    """``rgb_709 = matrix · expand(gains ⊙ camera_rgb)``; ``method`` is a colour-science name or ``identity``.

    ``matrix`` is (3, n_terms): n_terms 3 for ``Cheung 2004``/identity, 6 for root-polynomial degree 2.
    ``exposure_gain`` (dimensionless) is the least-squares ratio of output luminance to input
    green on the chart's neutral patches: dividing by it applies the colour correction without
    changing the image's brightness scale.
    """

    method: str
    gains: np.ndarray
    matrix: np.ndarray
    degree: int = 1
    exposure_gain: float = 1.0

    @classmethod
    def identity(cls) -> ColourCorrection:
        return cls(IDENTITY, np.ones(3), np.eye(3), 1, 1.0)

    @property
    def is_identity(self) -> bool:
        return self.method == IDENTITY

    def to_dict(self) -> dict:
        return {"method": self.method, "gains": [float(v) for v in self.gains],
                "matrix": [float(v) for v in np.ravel(self.matrix)], "n_terms": int(self.matrix.shape[1]),
                "degree": int(self.degree), "exposure_gain": float(self.exposure_gain)}

    @classmethod
    def from_dict(cls, data: dict) -> ColourCorrection:
        matrix = np.asarray(data["matrix"], np.float64).reshape(3, int(data["n_terms"]))
        return cls(str(data["method"]), np.asarray(data["gains"], np.float64), matrix, int(data["degree"]),
                   float(data["exposure_gain"]))


def _expand(rgb: np.ndarray, correction: ColourCorrection) -> np.ndarray:
    if correction.method == "Finlayson 2015":
        return colour.characterisation.polynomial_expansion_Finlayson2015(rgb, correction.degree, True)
    return rgb


def apply_correction(rgb_linear: np.ndarray, correction: ColourCorrection | None, *,
                     keep_exposure: bool = True) -> np.ndarray:
    """Camera RGB (..., 3) → linear Rec.709 (float32, same shape); None or identity returns a copy.

    ``keep_exposure=False`` divides by ``correction.exposure_gain``: colour only, the brightness
    scale of the input is kept (for photos taken at another exposure than the chart).
    """
    rgb = np.asarray(rgb_linear)
    if correction is None or correction.is_identity:
        return rgb.astype(np.float32, copy=True)
    flat = rgb.reshape(-1, 3).astype(np.float64)
    out = np.empty(flat.shape, np.float32)
    scale = 1.0 if keep_exposure else 1.0 / correction.exposure_gain
    for start in range(0, flat.shape[0], _CHUNK_PIXELS):
        block = flat[start:start + _CHUNK_PIXELS] * correction.gains
        out[start:start + _CHUNK_PIXELS] = (_expand(block, correction) @ correction.matrix.T) * scale
    return out.reshape(rgb.shape)


@dataclass
class ChartFit:
    """A fitted correction and its per-patch ΔE2000 (index i = patch i + 1; NaN where not measured)."""

    correction: ColourCorrection
    status: str  # "ok" | "identity"
    reason: str
    valid: np.ndarray  # (24,) bool, patches used
    measured_rgb: np.ndarray  # (24, 3) camera RGB
    balanced_rgb: np.ndarray  # (24, 3) after white balance and exposure
    corrected_rgb: np.ndarray  # (24, 3) after the full correction
    delta_e_before: np.ndarray  # (24,)
    delta_e_after: np.ndarray  # (24,)
    reference: ChartReference

    def stats(self) -> dict:
        """Mean, median and max ΔE2000 over the valid patches, before and after (NaN when none)."""
        out = {}
        for name, values in (("before", self.delta_e_before), ("after", self.delta_e_after)):
            v = values[self.valid & np.isfinite(values)]
            for stat, fn in (("mean", np.mean), ("median", np.median), ("max", np.max)):
                out[f"{stat}_delta_e_{name}"] = float(fn(v)) if v.size else float("nan")
        return out


def delta_e_2000(rgb: np.ndarray, reference: ChartReference) -> np.ndarray:
    """(24,) CIE 2000 colour difference of linear Rec.709 patches against the reference chart."""
    return colour.delta_E(rgb709_to_lab(rgb), reference.lab, method="CIE 2000")


def _neutral_gains(measured: np.ndarray, target: np.ndarray) -> np.ndarray:
    return np.sum(measured * target, axis=0) / np.maximum(np.sum(measured * measured, axis=0), 1e-30)


def _exposure_gain(measured: np.ndarray, corrected: np.ndarray) -> float:
    green = measured[:, 1]
    luminance = corrected @ np.array([0.2126, 0.7152, 0.0722])
    denom = float(np.sum(green * green))
    return float(np.sum(luminance * green) / denom) if denom > 0 else 1.0


def resolve_method(method: str) -> str:
    """colour-science method name of a CLI name (``3x3``, ``root-polynomial``) or of itself."""
    if method in METHODS:
        return METHODS[method]
    if method in METHODS.values():
        return method
    raise ValueError(f"unknown colour-correction method {method!r}; choose from {sorted(METHODS)}")


def fit_correction(measured_rgb: np.ndarray, valid: np.ndarray | None = None, *, method: str = "3x3",
                   edition: str = DEFAULT_EDITION) -> ChartFit:
    """Fit gains then a colour matrix (module docstring) to (24, 3) measured camera RGB."""
    method = resolve_method(method)
    reference = reference_chart(edition)
    measured = np.asarray(measured_rgb, np.float64)
    if measured.shape != (len(reference.rgb), 3):
        raise ValueError(f"measured_rgb must have shape ({len(reference.rgb)}, 3), got {measured.shape}")
    finite = np.isfinite(measured).all(axis=1)
    valid = finite if valid is None else np.asarray(valid, bool) & finite
    neutral = np.zeros(len(valid), bool)
    neutral[list(NEUTRAL_INDICES)] = True
    n_valid, n_neutral = int(valid.sum()), int((valid & neutral).sum())
    if n_valid < MIN_VALID_PATCHES[method] or n_neutral < MIN_NEUTRAL_PATCHES:
        reason = (f"identity correction: {n_valid} valid patches ({MIN_VALID_PATCHES[method]} needed for "
                  f"{method}), {n_neutral} valid neutral patches ({MIN_NEUTRAL_PATCHES} needed)")
        return _fit_result(ColourCorrection.identity(), IDENTITY, reason, valid, measured, reference)
    gains = _neutral_gains(measured[valid & neutral], reference.rgb[valid & neutral])
    if not (np.isfinite(gains).all() and (gains > 0).all()):
        reason = "identity correction: the neutral patches give non-positive white-balance gains"
        return _fit_result(ColourCorrection.identity(), IDENTITY, reason, valid, measured, reference)
    balanced = measured * gains
    degree = ROOT_POLYNOMIAL_DEGREE if method == "Finlayson 2015" else 1
    kwargs = {"degree": degree} if method == "Finlayson 2015" else {"terms": 3}
    matrix = colour.matrix_colour_correction(balanced[valid], reference.rgb[valid], method=method, **kwargs)
    correction = ColourCorrection(method, gains, np.asarray(matrix, np.float64), degree)
    corrected = apply_correction(measured[valid & neutral], correction).astype(np.float64)
    correction.exposure_gain = _exposure_gain(measured[valid & neutral], corrected)
    if not (np.isfinite(correction.matrix).all() and np.isfinite(correction.exposure_gain)
            and correction.exposure_gain > 0):
        reason = "identity correction: the fit maps the neutral patches to non-positive luminance"
        return _fit_result(ColourCorrection.identity(), IDENTITY, reason, valid, measured, reference)
    return _fit_result(correction, "ok", "", valid, measured, reference)


def _fit_result(correction, status, reason, valid, measured, reference) -> ChartFit:
    safe = np.where(np.isfinite(measured), measured, 0.0)
    if correction.is_identity:
        balanced = safe.copy()
    else:
        balanced = safe * correction.gains
    corrected = apply_correction(safe, correction).astype(np.float64)
    missing = ~np.isfinite(measured).all(axis=1)
    before, after = delta_e_2000(balanced, reference), delta_e_2000(corrected, reference)
    before[missing] = np.nan
    after[missing] = np.nan
    return ChartFit(correction, status, reason, valid, measured, balanced, corrected, before, after, reference)
