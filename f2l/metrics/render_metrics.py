"""Rendering metrics "(s)": MAE, RMSE and si-RMSE of the evaluation scene (Calian et al. 2018, §5.1).

Both probes are rendered with :mod:`f2l.metrics.scene`; only the ``P`` scene pixels (mask True)
count, over all 3 channels (``N = 3P`` values). Each rendering is normalised to mean 1,
``x ← x / mean(x)`` (an estimate whose rendering has mean <= 0 becomes all zeros, which scores
MAE = 1 against any ground truth). With ``a`` = normalised estimate, ``b`` = normalised truth::

    MAE     = Σ |a − b| / N
    RMSE    = sqrt(Σ (a − b)² / N)
    si-RMSE = sqrt(Σ (α a − b)² / N),   α = Σ a b / Σ a²  (least-squares scale; α = 0 if a ≡ 0)

References
----------
- Calian, Lalonde, Gotardo, Simon, Matthews, Mitchell. "From Faces to Outdoor Light Probes."
  Computer Graphics Forum (Eurographics) 37(2), 2018 (§5.1: the rendering metrics "(s)").
"""

from __future__ import annotations

import numpy as np

from f2l.lighting.grid import LatLongGrid
from f2l.metrics.scene import evaluation_scene

__all__ = ["RENDER_METRIC_NAMES", "normalise_rendering", "image_metrics", "rendering_metrics"]

RENDER_METRIC_NAMES = ("MAE (s)", "RMSE (s)", "si-RMSE (s)")


def normalise_rendering(x: np.ndarray) -> np.ndarray:
    """``x / mean(x)`` in float64; all zeros if ``mean(x) <= 0``.

    >>> normalise_rendering([1.0, 3.0]).tolist(), normalise_rendering([0.0, 0.0]).tolist()
    ([0.5, 1.5], [0.0, 0.0])
    """
    x = np.asarray(x, dtype=np.float64)
    m = float(x.mean())
    if not np.isfinite(m):
        return np.full_like(x, np.nan)
    return x / m if m > 0 else np.zeros_like(x)


def image_metrics(est: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """MAE/RMSE/si-RMSE (s) between two renderings of the same scene pixels (any equal shape).

    >>> image_metrics(np.array([1.0, 3.0]), np.array([2.0, 6.0]))  # the same up to scale
    {'MAE (s)': 0.0, 'RMSE (s)': 0.0, 'si-RMSE (s)': 0.0}
    >>> m = image_metrics(np.array([1.0, 2.0, 3.0]), np.array([3.0, 2.0, 1.0]))
    >>> {name: round(value, 4) for name, value in m.items()}
    {'MAE (s)': 0.6667, 'RMSE (s)': 0.8165, 'si-RMSE (s)': 0.7559}
    """
    est = np.asarray(est, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if est.shape != gt.shape:
        raise ValueError(f"shape mismatch {est.shape} vs {gt.shape}")
    if not float(gt.mean()) > 0:
        raise ValueError("ground-truth rendering has no positive mean intensity")
    a = normalise_rendering(est).ravel()
    b = normalise_rendering(gt).ravel()
    d = a - b
    aa = float(a @ a)
    alpha = float(a @ b) / aa if aa > 0 else 0.0
    return {
        "MAE (s)": float(np.mean(np.abs(d))),
        "RMSE (s)": float(np.sqrt(np.mean(d * d))),
        "si-RMSE (s)": float(np.sqrt(np.mean((alpha * a - b) ** 2))),
    }


def rendering_metrics(
    est_probe: np.ndarray, gt_probe: np.ndarray, grid: LatLongGrid | None = None
) -> dict[str, float]:
    """Render the evaluation scene under both probes (H, W, 3) and compare (see module doc).

    >>> sky = np.ones((8, 16, 3))  # a small grid keeps the scene's transport quick to build
    >>> sky[1, 5] = 500.0
    >>> m = rendering_metrics(3.0 * sky, sky)
    >>> {name: round(value, 4) for name, value in m.items()}
    {'MAE (s)': 0.0, 'RMSE (s)': 0.0, 'si-RMSE (s)': 0.0}
    >>> round(rendering_metrics(np.ones((8, 16, 3)), sky)["MAE (s)"], 3)
    0.592
    """
    est_probe = np.asarray(est_probe)
    gt_probe = np.asarray(gt_probe)
    if grid is None:
        grid = LatLongGrid(gt_probe.shape[0], gt_probe.shape[1])
    scene = evaluation_scene(grid)
    return image_metrics(scene.render_pixels(est_probe), scene.render_pixels(gt_probe))
