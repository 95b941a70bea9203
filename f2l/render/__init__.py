"""Realistic evaluation faces: an independent path tracer (Mitsuba 3) over heads f2l did not model
(Anny), under real HDR maps and Hosek–Wilkie skies (``f2l eval render-faces``, ``make eval-real``).

Needs the ``render`` extra (``pip install 'f2l[render]'``); :class:`RenderExtraMissing` names it.
"""


class RenderExtraMissing(ImportError):
    """mitsuba or anny is not installed."""

    def __init__(self, exc: ImportError):
        super().__init__(f"the realistic renderer needs the render extra: pip install 'f2l[render]' ({exc})")
