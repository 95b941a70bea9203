"""One sun across the segments of a clip whose suns agree (:mod:`f2l.video.estimate`, step 4).

A cloud over the sun, walking into shade or an exposure jump starts a segment but moves no sun in
the camera's frame; a cut may or may not (the colours of a frame cannot tell a cut from a cloud
that darkens the whole scene). Two consecutive segments whose suns agree within their 90% cones
(:func:`suns_agree`) share one: :class:`SunSharing` refits the windows at such a change with the
sun held at the cone-weighted mean of the run's windows at its changes (:func:`shared_sun_direction`,
:func:`sun_prior`), as the windows come.
"""

from __future__ import annotations

import math
import numpy as np

# annotations name f2l.video.estimate's Sample, SampleEstimate and VideoOptions (not imported: that
# module imports this one)

__all__ = ["SunSharing", "shared_sun_direction", "sun_prior", "sample_problem", "suns_agree"]


def sun_prior(model, direction, sigma_deg: float, weight: float):
    """params (B, P) -> (B,): weight · ½ |s − d|² / σ² for the model's sun s and unit ``direction`` d."""
    import torch

    lay = model.sun_angles
    s0 = torch.as_tensor(np.asarray(direction, np.float64))
    sigma = math.radians(sigma_deg)

    def prior(params):
        el, az = params[:, lay.elevation], params[:, lay.azimuth]
        d = torch.stack([torch.cos(el) * torch.sin(az), torch.sin(el), -torch.cos(el) * torch.cos(az)], 1)
        return weight * 0.5 * ((d - s0) ** 2).sum(1) / sigma**2

    return prior


def sample_problem(sample: Sample, model, cfg):
    """The sample's FaceProblem under ``cfg``, built once (a sample sits in several windows)."""
    import torch

    from f2l.estimate.problem import FaceProblem

    if sample.problem is None:
        sample.problem = FaceProblem(sample.observation, model, cfg, torch.float64)
    return sample.problem


def _angle_deg(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return math.degrees(math.acos(float(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)), -1.0, 1.0))))


def suns_agree(a: tuple, b: tuple) -> bool:
    """Whether two windows' suns agree (module docstring, step 4): ``a``, ``b`` = (unit sun, cones
    (r_68, r_90, ...)); the angle between the suns at most the smaller r_90. False without a sun or
    cones."""
    if a[0] is None or b[0] is None or a[1] is None or b[1] is None:
        return False
    return _angle_deg(a[0], b[0]) <= min(float(a[1][1]), float(b[1][1]))


def shared_sun_direction(points: list[tuple]) -> np.ndarray | None:
    """The unit mean of the (sun, cones) ``points``' suns, each weighted by 1 / r_68² (radii floored
    at 1°; points without a sun or cones left out); None without any."""
    total = np.zeros(3)
    for sun, cones in points:
        if sun is not None and cones is not None:
            total += np.asarray(sun, np.float64) / max(float(cones[0]), 1.0) ** 2
    norm = float(np.linalg.norm(total))
    return None if norm < 1e-12 else total / norm


class SunSharing:
    """The module docstring, as the windows come: :meth:`add` each new window's estimate. When a
    segment's first window agrees with the last window of the segment before, the run of agreeing
    segments goes on: both windows are refitted from their lights with the sun held at the
    cone-weighted mean of the run's windows at its changes so far (as each was estimated). Only the
    newest window keeps its samples (the one a refit may still need), so memory does not grow with
    the clip. A refit that fails, or a model without explicit sun angles, leaves the light as it is."""

    def __init__(self, model, cfg, options: VideoOptions, refit_joint, errors) -> None:
        self.model, self.cfg, self.options, self.refit_joint, self.errors = model, cfg, options, refit_joint, errors
        self.run: list[tuple] = []  # (sun, cones) of the run's windows at its changes, as estimated
        self.last: tuple | None = None  # (sun, cones) of the newest window as estimated
        self.refits = 0

    def add(self, estimate: SampleEstimate, previous: SampleEstimate | None) -> None:
        point = (None if estimate.sun_direction is None else np.asarray(estimate.sun_direction, np.float64),
                 estimate.cones)
        before, self.last = self.last, point
        if previous is not None:
            previous_samples, previous.samples = previous.samples, []  # its segment is over, or it is no boundary
        if previous is None or previous.segment == estimate.segment:
            if previous is None:
                self.run = []
            return
        if previous.segment + 1 != estimate.segment or before is None or not suns_agree(before, point):
            self.run = []
            return
        if not self.run or self.run[-1] is not before:
            self.run.append(before)
        self.run.append(point)
        shared = shared_sun_direction(self.run)
        if shared is None or not hasattr(self.model, "sun_angles"):
            return
        previous.samples = previous_samples
        for e in (previous, estimate):
            self._refit(e, shared)
        previous.samples = []

    def _refit(self, e: SampleEstimate, shared: np.ndarray) -> None:
        from f2l.lighting.grid import angles_from_direction

        if not e.samples:
            return
        lay = self.model.sun_angles
        el, az = angles_from_direction(shared)
        start = np.asarray(e.params, np.float64).copy()
        start[lay.elevation], start[lay.azimuth] = float(el), float(az)
        prior = sun_prior(self.model, shared, self.options.share_sigma_deg, self.options.temporal_weight)
        persons = [s.person for s in e.samples] if self.options.tie_albedo else None
        try:
            result, shares = self.refit_joint([s.observation for s in e.samples], self.model, start, self.cfg,
                                              extra_prior=prior, pixel_rc=[s.pixel_rc for s in e.samples],
                                              albedo_group=persons,
                                              problems=[sample_problem(s, self.model, self.cfg) for s in e.samples])
        except self.errors:
            return
        self.refits += 1
        e.params = np.asarray(result.params, np.float64)
        e.sun_direction = None if result.sun_direction is None else np.asarray(result.sun_direction)
        e.ground_albedo = result.ground_albedo
        e.residual = {(s.frame, s.person): share.data for s, share in zip(e.samples, shares) if share.data is not None}
