"""Which faces share a joint estimate's light (:mod:`f2l.estimate.joint`): the tests that leave a face
out, for compact-sun models (docs/experiments/joint_estimate.md).

Faces that disagree (one in another's shadow, under a hat, lit by a reflector) are found in four
ways:

1. A face's ``agreement`` is its relative residual under a light (one free scale per channel) over
   its residual under the best light of its own sun search, in the search's metric
   (``sun_search.relative_residual``). Before any fit, with three faces or more, every face's own
   best light is tried on every face; the light most faces agree with (within the limit,
   ``DISAGREE_RATIO`` by default) decides who joins (:func:`consensus`): a shaded face cannot pull
   the fit's sun away first. Where no light suits two faces (``joint_common.CONSENSUS_MIN_VOTES``), none leaves before the fit.
2. After each fit, while the worst face's agreement with the fitted light exceeds the limit, it is
   left out and the rest are fitted afresh. Two faces that disagree have no majority: each keeps
   its own light (the darker one leaves the group; with no photo-mates to compare their darkness,
   as in a session's one face a photo, the one whose own best sun lights less of it, :func:`own_sun_lit`).
3. A face that shows none of the joint light's sun while a photo-mate shows it
   (``sun_search.sun_seen``: its shading fitted as free multiples of the light's sky part and sun
   part; below ``SUN_SEEN_MIN`` of the sun where the sun makes ``SUN_SHARE_MIN`` of its shading)
   is left out: a face in an occluder's shadow is lit by the sky alone. So is a face that shows less
   than ``SUN_SEEN_RELATIVE`` x the median of its photo-mates' sun seen (that median counted up to 1)
   while it reads darker than ``DIM_RATIO`` x their albedo (:func:`sees_less_sun`): neither sign
   alone tells shade from a darker skin or a face turned from the sun; together they find the shaded
   faces the absolute limit misses (a sun that carries a third of the light, a board that grazes).
4. A face far darker than its photo's other faces under the joint light (albedo below
   ``DARK_RATIO`` x their median) is left out too: under the group's sun a face in shade reads as
   a much darker skin.

:func:`leaving` applies 2-4 to one fit; the estimate (f2l.estimate.joint) refits without the face
it names. ``fit`` below is the joint fit's summary (``params``, ``albedo`` and ``problems``, the
fitted faces' :class:`~f2l.estimate.problem.FaceProblem`).
"""

from __future__ import annotations

import numpy as np
import torch

from f2l.estimate import sun_search
from f2l.estimate.config import EstimatorConfig
from f2l.estimate import joint_common
from f2l.estimate.joint_common import DARK_RATIO, SUN_SEEN_MIN, SUN_SEEN_PEER, SUN_SHARE_MIN, darkness
from f2l.estimate.problem import FaceProblem
from f2l.lighting.grid import LatLongGrid

__all__ = ["agreements", "consensus", "face_scores", "leaving", "own_sun_lit", "sees_less_sun", "sees_no_sun", "shared_setup",
           "sun_seen_of"]


def leaving(fit, active: list[int], groups, agreement: dict[int, float], seen: dict[int, tuple[float, float]],
            limit: float) -> tuple[int | None, str, dict[int, float]]:
    """Tests 2-4 (module docstring) on one fit of the ``active`` faces (``groups``: each face's
    photo): (the face to leave, why, each active face's darkness); (None, "", darkness) when
    every face stays. ``agreement`` and ``seen``: :func:`agreements` and :func:`sun_seen_of`."""
    shade = darkness({i: fit.albedo[j] for j, i in enumerate(active)}, {i: int(groups[i]) for i in active},
                     gloss=fit.problems[0].gloss)
    worst = max(active, key=lambda i: agreement.get(i, 0.0))
    if agreement.get(worst, 0.0) > limit:
        if len(active) == 2:  # no majority: each face keeps its own light (the darker one leaves)
            a, b = active
            if abs(shade[a] - shade[b]) > 1e-9:
                worst = min(active, key=lambda i: shade[i])
            else:  # no photo-mates to compare with (one face a photo): the one that sees its sun less
                lit = {i: own_sun_lit(fit.problems[j]) for j, i in enumerate(active)}
                worst = min(active, key=lambda i: lit[i])
            return worst, (f"the group's two faces disagree (residual {max(agreement[a], agreement[b]):.2f}x its own "
                           f"best, limit {limit:.2f}): each keeps its own estimate"), shade
        return worst, (f"disagrees with the group's light: residual {agreement[worst]:.2f}x its own best "
                       f"(limit {limit:.2f}); left out"), shade
    blind = sees_no_sun(seen, active, groups)
    if blind is not None:
        return blind, (f"shows {seen[blind][0]:.2f} of the group's sun where the sun makes {seen[blind][1]:.0%} of "
                       f"its shading under the group's light (limit {SUN_SEEN_MIN:.2f}), as a face in shade does; "
                       "left out"), shade
    dim = sees_less_sun(seen, shade, active, groups)
    if dim is not None:
        face, mates = dim
        return face, (f"shows {seen[face][0]:.2f} of the group's sun, {seen[face][0] / mates:.2f}x its photo-mates' "
                      f"median (limit {joint_common.SUN_SEEN_RELATIVE:.2f}), and reads {shade[face]:.2f}x their albedo "
                      f"(limit {joint_common.DIM_RATIO:.2f}), as a face in shade does; left out"), shade
    worst = min(active, key=lambda i: shade[i])
    if shade[worst] >= DARK_RATIO:
        return None, "", shade
    return worst, (f"too dark for the group's light: its albedo is {shade[worst]:.2f}x its photo's other faces' "
                   f"median (limit {DARK_RATIO:.2f}), as a face in shade is; left out"), shade


def agreements(problems: dict[int, FaceProblem], fit, cfg: EstimatorConfig) -> dict[int, float]:
    """Each face's agreement with the fit's light (module docstring): {face index: ratio} for the
    faces the fit used (by their index in ``fit``) and every other problem given. Compact-sun
    models only; empty for others."""
    light = _search_light(fit)
    if light is None:
        return {}
    texel, m_unit, w_sky, w_sun = light
    return {i: _ratio(p, texel, m_unit, w_sky, w_sun, cfg) for i, p in problems.items()}


def sun_seen_of(problems: dict[int, FaceProblem], fit, cfg: EstimatorConfig) -> dict[int, tuple[float, float]]:
    """Each face's (seen, share) of the fit's sun (``sun_search.sun_seen``), for every problem
    given; empty for models without a compact sun."""
    light = _search_light(fit)
    if light is None:
        return {}
    texel, m_unit, w_sky, w_sun = light
    return {i: sun_search.sun_seen(p.hybrid.t_blk.numpy(), p.g.numpy(), p.transport.columns, p.target.numpy(),
                                   p.grid, texel, m_unit, _e_blocks(p), cfg.ground_albedo_init, w_sky, w_sun)
            for i, p in problems.items()}


def sees_no_sun(seen: dict[int, tuple[float, float]], active: list[int], groups) -> int | None:
    """The face that shows least of the group's sun (``SUN_SEEN_MIN``, where the sun makes
    ``SUN_SHARE_MIN`` of its shading) while a face of its photo shows ``SUN_SEEN_PEER`` of it;
    None if none. A light whose sun no face shows is the light's fault, not a face's."""
    told = [i for i in active if i in seen and seen[i][1] >= SUN_SHARE_MIN]
    blind = [i for i in told if seen[i][0] < SUN_SEEN_MIN
             and any(seen[j][0] >= SUN_SEEN_PEER for j in told if j != i and groups[j] == groups[i])]
    return min(blind, key=lambda i: seen[i][0]) if blind else None


def own_sun_lit(p: FaceProblem) -> float:
    """The share of the face's pixels that the sun of its own best search light faces (n · d > 0;
    0 where its best light has no sun): how well the face sees the sun it reads. Of two faces that
    disagree with no photo-mates to compare their darkness, the one that sees its sun less leaves."""
    from f2l.estimate.uncertainty import lit_fraction

    sc = face_scores(p, shared_setup(p), p.cfg)
    flat = int(np.argmin(sc.total))
    if float(sc.sky_total.min()) < float(sc.total.flat[flat]):
        return 0.0
    texel = int(sc.texels[flat // sc.total.shape[1]])
    return lit_fraction(p.transport.normals, p.grid.directions_flat[texel])


def sees_less_sun(seen: dict[int, tuple[float, float]], shade: dict[int, float], active: list[int],
                  groups) -> tuple[int, float] | None:
    """The face that shows least of the group's sun relative to its photo-mates, where it shows
    below ``SUN_SEEN_RELATIVE`` x their median (counted up to ``SUN_SEEN_MATES_CAP``) and reads below
    ``DIM_RATIO`` x their albedo (``shade``: :func:`~f2l.estimate.joint_common.darkness`), with that
    median; None if none (constants of :mod:`f2l.estimate.joint_common`). Mates that show no sun
    between them (median 0) tell nothing."""
    found = []
    for i in active:
        if i not in seen or not np.isfinite(seen[i][0]) or shade.get(i, 1.0) >= joint_common.DIM_RATIO:
            continue
        mates = [seen[j][0] for j in active if j != i and j in seen and groups[j] == groups[i] and np.isfinite(seen[j][0])]
        if not mates or float(np.median(mates)) <= 0.0:
            continue
        median = min(float(np.median(mates)), joint_common.SUN_SEEN_MATES_CAP)
        if seen[i][0] < joint_common.SUN_SEEN_RELATIVE * median:
            found.append((seen[i][0] / median, i, median))
    if not found:
        return None
    _, face, median = min(found)
    return face, median


def _search_light(fit):
    """The fit's light in the search's terms: (sun texel, unit sky block means (nb, 3), w_sky,
    w_sun); None for models without a compact sun."""
    first = fit.problems[0]
    if first.hybrid is None:
        return None
    model = first.model
    with torch.no_grad():
        sky, w_sky, _ = model.light_parts(torch.as_tensor(fit.params[None]))
        m_unit, _ = first.hybrid.sky_summary(sky, first.e_sky)
    w_sun = fit.params[list(model.sun_layout.sun_rgb)]
    texel = _nearest_texel(first.grid, model.sun_direction(fit.params))
    return texel, m_unit[0].numpy(), w_sky[0].numpy(), w_sun


def shared_setup(p: FaceProblem):
    """The sun search's candidates (``FaceProblem.search_setup``), made once for the faces of one
    grid, model and config and kept on the first problem that asks."""
    if getattr(p, "_setup", None) is None:
        p._setup = p.search_setup()
    return p._setup


def face_scores(p: FaceProblem, setup, cfg: EstimatorConfig):
    """The face's search scores (``FaceProblem.search_scores``), computed once per problem."""
    if getattr(p, "_scores", None) is None:
        p._scores = p.search_scores(setup, cfg.ground_albedo_init)
    return p._scores


def consensus(problems: dict[int, FaceProblem], active: list[int], cfg: EstimatorConfig,
               limit: float) -> dict[int, float] | None:
    """Each face's ratio under the light most faces agree with, before any joint fit; None when no
    light is agreed by two faces (each face's best light suits it alone: nothing to side with).

    Every face's own best light of the search (sun texel, sky shape and psi, or the sun-less sky)
    is tried on every face (``sun_search.relative_residual`` over the face's own best residual):
    the light under which most faces stay within ``limit`` wins (ties: the lower mean ratio). A
    face in another's shadow cannot pull the joint fit's sun away before it is found. Where every
    light keeps only its own face, the lowest mean ratio would pick a compromise (often a shaded
    face's sun-less sky, which no sunlit face's light suits) and leave out every other face, so none
    leaves here and the fitted tests decide."""
    setup = shared_setup(problems[active[0]])
    texels, _, sky_blocks, _ = setup
    lights = {}
    for i in active:
        sc = face_scores(problems[i], setup, cfg)
        flat = int(np.argmin(sc.total))
        k, shape = divmod(flat, sc.total.shape[1])
        if float(sc.sky_total.min()) < float(sc.total.flat[flat]):
            k, shape = divmod(int(np.argmin(sc.sky_total)), sc.total.shape[1])
            lights[i] = (int(texels[k]), sky_blocks[k, shape], sc.sky_psi[k, shape], np.zeros(3))
        else:
            lights[i] = (int(texels[k]), sky_blocks[k, shape], sc.psi_sky[k, shape], sc.psi_sun[k, shape])
    ratio = {}
    for i in active:
        texel, blocks, w_sky, w_sun = lights[i]
        ratio[i] = {j: _ratio(problems[j], texel, blocks, w_sky, w_sun, cfg) for j in active}
    votes = {i: sum(r <= limit for r in ratio[i].values()) for i in active}
    best = min(active, key=lambda i: (-votes[i], float(np.mean(list(ratio[i].values())))))
    return ratio[best] if votes[best] >= joint_common.CONSENSUS_MIN_VOTES else None


def _ratio(p: FaceProblem, texel: int, sky_block_means, w_sky, w_sun, cfg: EstimatorConfig) -> float:
    """The face's relative residual under one light over its own best's (``_own_best``)."""
    rel = sun_search.relative_residual(p.hybrid.t_blk.numpy(), p.g.numpy(), p.transport.columns, p.target.numpy(),
                                       p.grid, texel, np.asarray(sky_block_means), _e_blocks(p), cfg.ground_albedo_init,
                                       np.asarray(w_sky), np.asarray(w_sun))
    return rel / max(_own_best(p, cfg), 1e-12)


def _nearest_texel(grid: LatLongGrid, direction: np.ndarray) -> int:
    """The sky texel whose direction is nearest to ``direction`` (kept above the horizon row)."""
    d = np.asarray(direction, np.float64)
    lu = grid.sky_rows * grid.width
    return int(np.argmax(grid.directions_flat[:lu] @ d))


def _e_blocks(p: FaceProblem) -> np.ndarray:
    nb = p.hybrid.t_blk.shape[1]
    return np.bincount(p.hybrid.block_of, weights=p.e_sky.numpy(), minlength=nb)


def _own_best(p: FaceProblem, cfg: EstimatorConfig) -> float:
    """The face's residual under the best light of its own sun search (relative, as
    ``sun_search.relative_residual``), computed once per problem."""
    s = face_scores(p, shared_setup(p), cfg)
    return min(float(s.total.min()), float(s.sky_total.min())) / max(s.yy, 1e-300)
