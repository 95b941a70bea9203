"""The joint estimate for latent-sky models (f2l.estimate.latent_joint, reached through
f2l.estimate.joint.estimate_joint): one decoded sky for several faces of one photo or session.

Faces are tests/test_joint.py's renders (f2l.synth.render, Lambertian) under one clear sky on its
32 x 64 grid (the smallest whose sky splits into the latent transport's 4 x 4 blocks at two
sub-shifts; ``ae`` resamples its 32 x 128 sky to it), three in the sun and a "shaded" one with
the sun taken away. Checks: groups left with one face are the single estimate bit for bit;
three faces recover the sun; the shaded face is left out and the rest is the group without it;
an exposure difference between photos lands in that photo's gain; a fixed albedo is kept.
"""

from __future__ import annotations

import numpy as np
import pytest

from f2l.estimate import EstimatorConfig, estimate
from f2l.estimate.joint import DISAGREE_RATIO, estimate_joint
from f2l.estimate.latent_joint import estimate_joint_latent
from f2l.models import load_model
from tests.test_joint import CFG, GRID, SUN, _angle_deg, _obs, faces, skies  # noqa: F401  (the same renders and fixtures)


@pytest.fixture(scope="module")
def ae():
    return load_model("ae", GRID)


@pytest.fixture(scope="module")
def three(faces, ae):
    return estimate_joint([_obs(f, str(i)) for i, f in enumerate(faces[:3])], ae, CFG)


def _same(a, b) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("params", "probe", "albedo", "sun_direction")) \
        and a.ground_albedo == b.ground_albedo and a.loss == b.loss


def test_groups_left_with_one_face_are_the_single_estimate_bit_for_bit(faces, ae):
    single = estimate(_obs(faces[0], "a"), ae, CFG)
    for joint in (estimate_joint([_obs(faces[0], "a")], ae, CFG), estimate_joint_latent([_obs(faces[0], "a")], ae, CFG)):
        assert _same(joint.result, single)
        assert joint.faces[0].used and joint.faces[0].weight == 1.0
    pair = [_obs(faces[2], "c"), _obs(faces[3], "shaded")]
    joint = estimate_joint_latent(pair, ae, CFG)  # the two disagree: one of them is left out
    kept = [i for i, s in enumerate(joint.faces) if s.used]
    assert len(kept) == 1 and _same(joint.result, estimate(pair[kept[0]], ae, CFG))


def test_three_faces_under_one_sky_recover_its_sun(faces, three):
    assert all(s.used for s in three.faces)
    assert all(s.agreement is not None and s.agreement < DISAGREE_RATIO for s in three.faces)
    assert _angle_deg(three.result.sun_direction, SUN) < 10.0
    assert np.isfinite(three.result.probe).all() and three.result.probe.min() >= 0.0
    assert sum(s.weight for s in three.faces) == pytest.approx(3.0)
    assert all(np.all((s.albedo > 0) & (s.albedo <= 1)) and 0 < s.ground_albedo < 1 and s.data > 0
               for s in three.faces)
    assert three.result.timings["faces"] == 3.0
    # the group's sun cones, from the search summed over the faces and every face's pixels
    u = three.result.sun_uncertainty
    assert u is not None and 0 < u.cone68_deg < u.cone90_deg <= 180.0
    assert _angle_deg(three.result.sun_direction, SUN) <= u.cone90_deg
    assert u.num_pixels == sum(int(np.count_nonzero(_obs(f, str(i)).mask)) for i, f in enumerate(faces[:3]))


def test_a_face_in_the_shade_is_left_out_and_the_rest_is_the_group_without_it(faces, ae, three):
    observations = [_obs(f, str(i)) for i, f in enumerate(faces)]
    joint = estimate_joint(observations, ae, CFG)
    shaded = joint.faces[3]
    assert not shaded.used and "disagrees" in shaded.reason and shaded.agreement > DISAGREE_RATIO
    assert all(s.used for s in joint.faces[:3])
    assert np.array_equal(joint.result.params, three.result.params)
    kept = estimate_joint(observations, ae, CFG, disagree_ratio=None)  # the check can be turned off
    assert all(s.used for s in kept.faces) and kept.faces[3].agreement > DISAGREE_RATIO


def test_faces_of_two_photos_with_different_exposures_share_the_light(faces, ae, three):
    """A photo 2.5x darker: its face's exposure x albedo comes out 0.4x that of the same face in
    the first photo (channel mean, within 12%), and the sun holds."""
    observations = [_obs(faces[0], "a"), _obs(faces[1], "b", gain=0.4), _obs(faces[2], "c")]
    joint = estimate_joint(observations, ae, CFG, exposure_group=["p1", "p2", "p1"])
    assert joint.faces[0].gain == 1.0 and joint.faces[2].gain == 1.0 and joint.faces[1].gain < 1.0
    seen = lambda s: s.gain * float(np.mean(s.albedo))  # noqa: E731
    assert seen(joint.faces[1]) / seen(joint.faces[0]) == pytest.approx(
        0.4 * seen(three.faces[1]) / seen(three.faces[0]), rel=0.12)
    assert _angle_deg(joint.result.sun_direction, SUN) < 10.0


def test_a_fixed_albedo_is_every_face_albedo(faces, ae):
    cfg = EstimatorConfig(sun_prior_from_capture=False, skin_gloss=0.0, fixed_albedo=(0.5, 0.3, 0.2))
    joint = estimate_joint_latent([_obs(f, str(i)) for i, f in enumerate(faces[:2])], ae, cfg)
    assert all(np.allclose(s.albedo, (0.5, 0.3, 0.2)) for s in joint.faces if s.used)
    assert np.isfinite(joint.result.probe).all() and np.isfinite(joint.result.params).all()


def test_the_latent_consensus_needs_two_faces_that_agree_on_a_light():
    """Scores of each face's own light on every face: where two faces agree on a light it decides
    (the third face's ratio above the limit); where every light suits its own face alone there is
    no consensus (None), whatever the mean ratios."""
    from f2l.estimate.latent_joint import _consensus

    own = {j: [{"score": 1.0}] for j in range(3)}
    agree = {0: {"score": [1.0, 1.5, 9.0]}, 1: {"score": [1.4, 1.0, 8.0]}, 2: {"score": [5.0, 6.0, 1.0]}}
    support = _consensus(agree, own, [0, 1, 2], 2.0)
    assert support is not None and support[0] <= 2.0 and support[1] <= 2.0 and support[2] > 2.0
    alone = {0: {"score": [1.0, 3.0, 3.0]}, 1: {"score": [9.0, 1.0, 9.0]}, 2: {"score": [9.0, 9.0, 1.0]}}
    assert _consensus(alone, own, [0, 1, 2], 2.0) is None


def test_a_pair_of_two_photos_that_disagree_keeps_the_face_that_sees_its_sun(faces, ae, monkeypatch):
    """The pair rule's wiring for latent skies: two faces of two photos (their darkness cannot be
    compared) made to disagree leave out the one whose own best sky's sun lights less of it,
    whichever comes first."""
    import f2l.estimate.latent_joint as lj
    from f2l.estimate.latent import LatentSkyProblem

    monkeypatch.setattr(lj, "_ratio", lambda p, sky, own, g: 10.0)  # every face disagrees with the pair's light
    problems = {i: LatentSkyProblem(_obs(faces[i], str(i)), ae, CFG) for i in (0, 3)}
    g0 = CFG.ground_albedo_init
    own = {i: p.refine_search(p.coarse_scores(g0), g0) for i, p in problems.items()}
    lights = lj._own_lights(problems, own, g0)
    lit = {i: lj._own_sun_lit(problems[i], lights[i]) for i in (0, 3)}
    assert all(0.0 <= v <= 1.0 for v in lit.values()) and lit[0] != lit[3]
    leaves = min(lit, key=lit.get)
    for order in ((0, 3), (3, 0)):
        joint = estimate_joint_latent([_obs(faces[i], str(i)) for i in order], ae, CFG, exposure_group=["a", "b"])
        left = [i for i, s in zip(order, joint.faces) if not s.used]
        assert left == [leaves]
        assert "two faces disagree" in joint.faces[order.index(leaves)].reason
