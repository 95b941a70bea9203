"""The skin's glossy highlight of a whole probe (f2l.evaluation.highlight) and the ideal photo with gloss."""

from types import SimpleNamespace

import numpy as np
import pytest

from f2l.lighting.grid import LatLongGrid
from f2l.evaluation.highlight import Gloss, glossy_highlight
from f2l.evaluation.photo_residual import IDEAL_PEAK, ideal_photo
from f2l.synth.render import make_synthetic_set

GRID = LatLongGrid(64, 128)
FACING = np.array([[0.0, 0.0, 1.0]])  # a pixel straight ahead of the camera, facing it
AHEAD = np.array([[0.0, 0.0, -50.0]])


def _all_visible(n_pixels: int = 1) -> np.ndarray:
    return np.packbits(np.ones((n_pixels, GRID.size), bool), axis=1, bitorder="little")


def test_white_furnace_gives_the_microfacet_albedo():
    """Under a uniform unit probe the highlight is the BRDF's directional albedo: a Fresnel-1
    mirror-like lobe keeps ~99% at roughness 0.3 and ~92% at 0.5 (single-scattering GGX loses
    energy as it roughens), skin's F0 = 0.028 gives 2-3%, F0 = 0 only the grazing Fresnel tail."""
    white = np.ones(GRID.shape + (3,))
    bits = _all_visible()
    mirror_03 = glossy_highlight(FACING, AHEAD, bits, GRID, white, 0.3, 1.0)[0]
    mirror_05 = glossy_highlight(FACING, AHEAD, bits, GRID, white, 0.5, 1.0)[0]
    skin = glossy_highlight(FACING, AHEAD, bits, GRID, white, 0.5, 0.028)[0]
    assert np.allclose(mirror_03, mirror_03[0]) and 0.97 < mirror_03[0] <= 1.005
    assert 0.88 < mirror_05[0] < mirror_03[0]
    assert 0.02 < skin[0] < 0.035
    assert 0.0 <= glossy_highlight(FACING, AHEAD, bits, GRID, white, 0.3, 0.0)[0, 0] < 1e-4


def test_linear_in_the_probe_zero_when_hidden_and_peaked_at_the_mirror_direction():
    rng = np.random.default_rng(0)
    probe = rng.uniform(0.0, 2.0, GRID.shape + (3,))
    bits = _all_visible()
    once = glossy_highlight(FACING, AHEAD, bits, GRID, probe, 0.4, 0.04)
    assert np.allclose(glossy_highlight(FACING, AHEAD, bits, GRID, 3.0 * probe, 0.4, 0.04), 3.0 * once)
    hidden = np.zeros_like(bits)
    assert np.all(glossy_highlight(FACING, AHEAD, hidden, GRID, probe, 0.4, 0.04) == 0.0)
    # one bright texel: at the mirror direction of the view (here the view itself, +Z) against 40 deg off
    def spot(direction):
        p = np.zeros(GRID.shape + (3,))
        r, c = GRID.direction_to_texel(np.asarray(direction, float)[None])
        p[r[0], c[0]] = 1.0
        return glossy_highlight(FACING, AHEAD, bits, GRID, p, 0.3, 0.028)[0, 0]
    off = [np.sin(np.radians(40.0)), 0.0, np.cos(np.radians(40.0))]
    assert spot([0.0, 0.0, 1.0]) > 20.0 * spot(off) > 0.0


def test_bad_inputs_are_rejected():
    bits = _all_visible()
    with pytest.raises(ValueError, match="grid"):
        glossy_highlight(FACING, AHEAD, bits, GRID, np.ones((8, 16, 3)), 0.5, 0.03)
    with pytest.raises(ValueError, match="roughness"):
        glossy_highlight(FACING, AHEAD, bits, GRID, np.ones(GRID.shape + (3,)), 0.0, 0.03)


def test_the_ideal_photo_with_gloss_adds_the_highlight_at_the_photos_exposure():
    """The glossy ideal photo is the plain one plus exposure x highlight (uncoloured by the skin),
    at the same IDEAL_PEAK normalisation."""
    grid = LatLongGrid(32, 64)
    f = next(iter(make_synthetic_set(1, grid, seed=3, image_size=96, overcast_fraction=0.0, threads=1)))
    record = SimpleNamespace(face_id="f0", grid_height=grid.height, grid_width=grid.width, normals=f.normals,
                             observed_rgb=f.observed_rgb, mask=f.mask, visibility_bits=f.visibility_bits,
                             points=f.points)
    truth = np.asarray(f.gt_probe, np.float64)
    mask = np.asarray(f.mask, bool)
    plain = ideal_photo(record, truth, threads=1).astype(np.float64)[mask]
    albedo = tuple(float(c) for c in np.asarray(f.albedo).reshape(-1, 3).mean(0))
    glossy = ideal_photo(record, truth, threads=1, gloss=Gloss(0.4, 0.04, albedo)).astype(np.float64)[mask]
    assert glossy.max() == pytest.approx(IDEAL_PEAK, rel=1e-6)
    # glossy = a * plain + b * highlight with the same a, b in R, G and B: one exposure for both, and
    # the highlight has the light's colour, not the skin's
    highlight = glossy_highlight(np.asarray(f.normals)[mask], np.asarray(f.points)[mask],
                                 np.asarray(f.visibility_bits)[mask], grid, truth, 0.4, 0.04)
    design = np.stack([plain.ravel(), highlight.ravel()], 1)
    (a, b), *_ = np.linalg.lstsq(design, glossy.ravel(), rcond=None)
    assert a > 0 and b > 0
    assert np.abs(design @ [a, b] - glossy.ravel()).max() < 1e-5
    assert np.median(b * highlight[:, 0] / (a * plain.sum(1) / 3)) > 0.005  # not a negligible addition
