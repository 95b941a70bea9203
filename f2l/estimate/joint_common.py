"""What every joint estimator shares (f2l.estimate.joint for the generic models,
f2l.estimate.latent_joint for latent-sky ones): the result types, the refusal, and the faces'
weights from their pixels and noise (``face_noise``, ``face_weights``; see f2l.estimate.joint)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from f2l.estimate.config import EstimateResult, EstimatorConfig
from f2l.estimate.observation import EstimationError, FaceObservation, usable_pixels

SIGMA_MODEL = 0.05  # the relative misfit of the forward model itself, added to each face's noise
DISAGREE_RATIO = 2.0  # agreement above this: the face does not share the group's light
# faces that must agree on one light before it decides, ahead of any fit, who joins (1: any light)
CONSENSUS_MIN_VOTES = 2
DARK_RATIO = 0.3  # a face whose albedo is below this x its photo-mates' median is left out (in shade)
# a face that shows less than SUN_SEEN_MIN of the group's sun, where the sun makes at least
# SUN_SHARE_MIN of its predicted shading and a photo-mate shows at least SUN_SEEN_PEER of it, is
# left out (in shade; sun_search.sun_seen); read off make eval-shade's seed 11 (docs/experiments/joint_estimate.md)
SUN_SEEN_MIN = 0.15
SUN_SHARE_MIN = 0.15
SUN_SEEN_PEER = 0.5
# a face that shows less than SUN_SEEN_RELATIVE x the median of its photo-mates' sun seen and reads
# darker than DIM_RATIO x their median albedo is left out: two weak signs of shade together (the board
# that grazes a face, a sun that carries a third of the light). The mates' median counts up to
# SUN_SEEN_MATES_CAP (1: lit as the light says; the ratio b/a runs away above it). Chosen on make
# eval-shade's seed 11 and make eval-groups' seed 0 together (docs/experiments/joint_estimate.md,
# "A face that shows less sun than its photo-mates")
SUN_SEEN_RELATIVE = 0.6
DIM_RATIO = 0.8
SUN_SEEN_MATES_CAP = 1.0


class JointUnsupported(EstimationError):
    """The model cannot be estimated jointly (the message says why); estimate its faces one by one."""


@dataclass
class FaceShare:
    """One face's part in a joint estimate: its weight, albedo, ground albedo and exposure gain
    (relative to the group's first photo), its data term under the joint light, its agreement
    (module docstring; None where not measured), whether the final fit used it and why not."""

    face_id: str
    weight: float
    albedo: np.ndarray | None = None
    ground_albedo: float | None = None
    gain: float = 1.0
    data: float | None = None
    agreement: float | None = None
    # how much of the joint light's sun the face shows (1 lit as the light says, 0 none) and the
    # sun's share of its predicted shading (``sun_search.sun_seen``); None where not measured
    sun_seen: float | None = None
    sun_share: float | None = None
    darkness: float | None = None  # its apparent albedo over its photo-mates' median (``darkness``)
    used: bool = True
    reason: str = ""


@dataclass
class JointResult:
    """The group's light (an :class:`EstimateResult`; its albedo is the used faces' weighted mean)
    and each face's share, in the order given."""

    result: EstimateResult
    faces: list[FaceShare] = field(default_factory=list)


def face_noise(obs: FaceObservation, pixel_rc: np.ndarray | None) -> float:
    """The face's relative noise: 1.4826 MAD / sqrt(2) of the luminance differences between
    horizontally adjacent usable pixels, over their mean luminance (0 without pixel positions)."""
    if pixel_rc is None or len(pixel_rc) != len(obs.observed_rgb):
        return 0.0
    idx = usable_pixels(obs)
    rc = np.asarray(pixel_rc, np.int64)[idx]
    lum = np.asarray(obs.observed_rgb, np.float64)[idx] @ np.array([0.2126, 0.7152, 0.0722])
    width = int(rc[:, 1].max()) + 2
    key = rc[:, 0] * width + rc[:, 1]
    order = np.argsort(key)
    key, lum = key[order], lum[order]
    pos = np.searchsorted(key, key + 1)
    has = (pos < len(key)) & (key[np.minimum(pos, len(key) - 1)] == key + 1)
    if has.sum() < 20:
        return 0.0
    diff = lum[pos[has]] - lum[has]
    sigma = 1.4826 * float(np.median(np.abs(diff - np.median(diff)))) / math.sqrt(2.0)
    return sigma / max(float(lum.mean()), 1e-12)


def face_weights(observations: list[FaceObservation], cfg: EstimatorConfig, noise: list[float]) -> np.ndarray:
    """w_i proportional to n_i / (sigma_i^2 + SIGMA_MODEL^2), summing to the number of faces; n_i
    the usable pixels, capped at the fit's own cap (``sun_max_pixels`` or ``max_pixels``)."""
    cap = cfg.sun_max_pixels or cfg.max_pixels or None
    n = np.array([usable_pixels(o, cfg.highlight_mad).size for o in observations], np.float64)
    if cap:
        n = np.minimum(n, cap)
    q = n / (np.asarray(noise, np.float64) ** 2 + SIGMA_MODEL**2)
    return len(q) * q / q.sum()


def darkness(albedo: dict[int, np.ndarray], group: dict[int, int], gloss: float = 0.0) -> dict[int, float]:
    """Each face's mean apparent albedo (rho + ``gloss``, the skin's gloss of sun models) under the
    joint light over the median of the other faces' of its photo (``group``: face -> exposure group;
    1 where it is alone in its photo). Under the group's sun, a face in another's shadow or under a
    hat reads as a far darker skin than its neighbours'. Faces of other photos do not count: their
    exposure and albedo cannot be told apart. The gloss counts because the shading sees rho + g:
    with g = 0.1, a dark skin's rho alone reads 0.15-0.3x its lighter neighbours' and passed for a
    face in shade (eval-groups: 11 of 18 faces left out at 3 faces; docs/experiments/joint_estimate.md)."""
    level = {i: float(np.mean(a)) + gloss for i, a in albedo.items()}
    out = {}
    for i in level:
        others = [level[o] for o in level if o != i and group[o] == group[i]]
        out[i] = level[i] / max(float(np.median(others)), 1e-12) if others else 1.0
    return out
