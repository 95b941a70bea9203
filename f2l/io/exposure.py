"""Absolute light from a photo's exposure: the scale from its linear values to cd/m².

A photo's linear values (1.0 = full scale of its encoding, :mod:`f2l.io.photo`) are relative: the
camera's exposure (time t in s, f-number N, ISO speed S) decides which scene luminance lands where.
The reflected-light meter equation (ISO 2720) ties them together:

    L_avg · S · t / N² = K,        K = ``REFLECTED_LIGHT_K`` = 12.5 cd·s/m² (per unit ISO),

the luminance L_avg of an average scene that a metered exposure renders at middle grey, and ISO
12232's standard output sensitivity renders middle grey at ``MIDDLE_GREY`` = 18% of the linear full
scale (code 118 of 255 in sRGB). So a linear value v stands for the luminance

    L = v · K · N² / (t · S · MIDDLE_GREY)    [cd/m², of Rec.709 luminance Y]

and a probe estimated in the photo's linear units, times ``absolute_scale``, is in cd/m² (each RGB
channel scaled alike, so its Rec.709 Y is the luminance). K = 12.5 is the constant Canon, Nikon and
Sekonic meters use (others use 14); sensors keep different headroom above middle grey, so the
figure is good to a factor of about 1.5, not to a percent. With the exposure of the photo known
exactly (a calibrated capture: ``f2l make-probes``), the capture pipeline's own units are better.

Refused (``None`` with the reason) where the EXIF lacks a value or holds an implausible one:
exposure time outside (0, 3600] s, f-number outside [0.5, 128], ISO outside [1, 10⁷].
"""

from __future__ import annotations

import math

REFLECTED_LIGHT_K = 12.5  # cd·s/m² per unit ISO: ISO 2720 reflected-light meter calibration constant
MIDDLE_GREY = 0.18  # linear fraction of full scale for a metered average scene (ISO 12232 SOS)
RANGES = {"exposure_s": (0.0, 3600.0), "f_number": (0.5, 128.0), "iso": (1.0, 1e7)}
EXIF_NAMES = {"exposure_s": "ExposureTime", "f_number": "FNumber", "iso": "ISOSpeedRatings"}


def ev100(exposure_s: float, f_number: float, iso: float) -> float:
    """The exposure value at ISO 100: log2(N² / t · 100 / S)."""
    return math.log2(f_number ** 2 / exposure_s * 100.0 / iso)


def absolute_scale(exif: dict | None) -> tuple[float | None, str]:
    """(cd/m² per unit linear value, where it came from) of a photo whose EXIF summary
    (``Photo.exif``: ``exposure_s``, ``f_number``, ``iso``) states its exposure; (None, why not)."""
    exif = exif or {}
    values, missing, bad = {}, [], []
    for key, (lo, hi) in RANGES.items():
        v = exif.get(key)
        try:
            v = float(v) if v is not None else None
        except (TypeError, ValueError):
            v = math.nan
        if v is None:
            missing.append(EXIF_NAMES[key])
        elif not (math.isfinite(v) and (lo < v if key == "exposure_s" else lo <= v) and v <= hi):
            bad.append(f"{EXIF_NAMES[key]} {v:g} outside {'(' if key == 'exposure_s' else '['}{lo:g}, {hi:g}]")
        else:
            values[key] = v
    if missing or bad:
        why = "; ".join(([f"EXIF lacks {', '.join(missing)}"] if missing else []) + bad)
        return None, f"relative (no absolute scale: {why})"
    t, n, s = values["exposure_s"], values["f_number"], values["iso"]
    scale = REFLECTED_LIGHT_K * n * n / (t * s * MIDDLE_GREY)
    return scale, (f"EXIF t = {t:g} s, f/{n:g}, ISO {s:g} (EV100 {ev100(t, n, s):.2f}); "
                   f"L = v K N^2 / (t S g), K = {REFLECTED_LIGHT_K:g} cd s/m^2, g = {MIDDLE_GREY:g}")
