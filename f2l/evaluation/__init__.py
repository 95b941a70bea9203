"""The evaluation harness: render → fit → estimate → score against the truth, and its diagnostics
(``f2l eval real|twin-geometry|geometry|search|ablations|framings``, ``f2l eval compare-geometry``).

It scores what :mod:`f2l.render` (the independent renders) and :mod:`f2l.synth` (f2l's own) produce:
:mod:`~f2l.evaluation.evaluate` (one row per method and case, with baselines),
:mod:`~f2l.evaluation.eval_report` (the tables), :mod:`~f2l.evaluation.truth_fit` (the model families'
oracles), :mod:`~f2l.evaluation.photo_residual` and :mod:`~f2l.evaluation.highlight` (does the photo
prefer the truth?), :mod:`~f2l.evaluation.compare_geometry` (true-geometry twins),
:mod:`~f2l.evaluation.geometry_share` and :mod:`~f2l.evaluation.search_share` (the face fit's and the
search's shares of the error), :mod:`~f2l.evaluation.face_width` (accuracy against face size).
"""
