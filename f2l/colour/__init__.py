"""Colour calibration against a ColorChecker Classic: camera RGB → linear Rec.709 (D65).

Modules: ``chart`` (reference values, layout, synthetic chart photos), ``detect`` (OpenCV mcc
detection and patch measurement on the linear image), ``fit`` (white balance + exposure, then a
colour-science 3 × 3 or root-polynomial fit; ΔE2000; ``apply_correction``), ``report`` (ΔE table
and swatch PNG), ``calibrate`` (the ``f2l calibrate`` batch: ``colour.parquet`` and reports).
"""
