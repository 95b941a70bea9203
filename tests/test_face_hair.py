"""The hairline band's skin test (f2l.face.hair) and its use in fit_face (FitOptions.hairline)."""

import numpy as np
import pytest

from f2l.face.hair import MIN_REFERENCE, log_chroma, skin_coloured

SKIN_ALBEDO = np.array([0.45, 0.30, 0.22])      # R/G 1.5, B/G 0.73
SUN_RGB = np.array([1.0, 0.95, 0.82])            # a warm sun
SKY_RGB = np.array([0.55, 0.8, 1.25])            # a blue sky
HAIR = {  # linear albedos
    "dark brown": np.array([0.05, 0.03, 0.018]),
    "black": np.array([0.02, 0.02, 0.021]),
    "grey": np.array([0.35, 0.36, 0.37]),
    "blond": np.array([0.40, 0.30, 0.10]),
}


def lit(albedo, xy, rng, noise=0.01):
    """Pixels at image points xy (N, 2) under a sun that lights the right half (x > 50) and a sky
    whose share falls from top to bottom (sunlit skin up to 0.4, below the 0.9 that counts as
    saturated); 1% noise."""
    x, y = xy[:, 0], xy[:, 1]
    sun = np.where(x > 50, 0.45 + 0.003 * x, 0.0)[:, None] * SUN_RGB
    sky = (0.27 - 0.0012 * y)[:, None] * SKY_RGB
    rgb = albedo * (sun + sky)
    return rgb * (1 + noise * rng.standard_normal(rgb.shape))


def pixel_centres(rows):
    y, x = np.meshgrid(np.arange(*rows) + 0.5, np.arange(100) + 0.5, indexing="ij")
    return np.stack([x.ravel(), y.ravel()], 1)


@pytest.fixture
def face():
    """Skin pixels below a band (rows 30-99) and the band's pixels (rows 0-29) on a 100-px-wide face."""
    rng = np.random.default_rng(3)
    skin_xy, band_xy = pixel_centres((30, 100)), pixel_centres((0, 30))
    return rng, skin_xy, lit(SKIN_ALBEDO, skin_xy, rng), band_xy


def test_skin_in_the_band_is_kept_under_sun_and_shadow(face):
    rng, skin_xy, skin_rgb, band_xy = face
    keep = skin_coloured(lit(SKIN_ALBEDO, band_xy, rng), band_xy, skin_rgb, skin_xy)
    assert keep.mean() > 0.97
    # both halves (sunlit and in shadow), whose colours differ by the light's
    assert keep[band_xy[:, 0] > 55].mean() > 0.97 and keep[band_xy[:, 0] < 45].mean() > 0.97
    sunlit, shade = lit(SKIN_ALBEDO, np.array([[90.0, 50]]), rng), lit(SKIN_ALBEDO, np.array([[10.0, 50]]), rng)
    assert np.abs(log_chroma(sunlit) - log_chroma(shade)).max() > 0.3  # a real spread to follow


@pytest.mark.parametrize("name", sorted(HAIR))
def test_hair_in_the_band_is_left_out(face, name):
    rng, skin_xy, skin_rgb, band_xy = face
    keep = skin_coloured(lit(HAIR[name], band_xy, rng), band_xy, skin_rgb, skin_xy)
    assert keep.mean() < 0.03, name


def test_a_fringe_over_part_of_the_band(face):
    rng, skin_xy, skin_rgb, band_xy = face
    fringe = band_xy[:, 0] < 40
    rgb = np.where(fringe[:, None], lit(HAIR["dark brown"], band_xy, rng), lit(SKIN_ALBEDO, band_xy, rng))
    keep = skin_coloured(rgb, band_xy, skin_rgb, skin_xy)
    assert not keep[fringe].any() and keep[~fringe].mean() > 0.97
    # the column next to the fringe mixes hair and skin in a photo: left out too
    assert not keep[(band_xy[:, 0] > 40) & (band_xy[:, 0] < 41)].any()
    assert keep[band_xy[:, 0] > 42].mean() > 0.99
    plain = skin_coloured(rgb, band_xy, skin_rgb, skin_xy, edge=0)
    assert plain[(band_xy[:, 0] > 40) & (band_xy[:, 0] < 41)].all()


def test_clipped_or_saturated_band_pixels_are_kept_on_their_luminance(face):
    """A high sun clips the forehead: its white pixels have no skin colour left, but are bright."""
    rng, skin_xy, skin_rgb, band_xy = face
    white = np.full((len(band_xy), 3), 0.97)
    assert skin_coloured(white, band_xy, skin_rgb, skin_xy).all()
    grey = np.full((len(band_xy), 3), 0.5)  # unsaturated and neutral: not skin where the sun is
    # (in the shade a blue sky makes skin as neutral; there only darkness tells hair from skin)
    assert not skin_coloured(grey, band_xy, skin_rgb, skin_xy)[band_xy[:, 0] > 55].any()
    assert skin_coloured(grey, band_xy, skin_rgb, skin_xy, candidate_clipped=np.ones(len(grey), bool)).all()
    # a clipped pixel does not make its neighbours fail; a dark one is hair even if flagged
    rgb = lit(SKIN_ALBEDO, band_xy, rng)
    rgb[::7] = 0.97
    assert skin_coloured(rgb, band_xy, skin_rgb, skin_xy).mean() > 0.97
    dark = lit(HAIR["black"], band_xy, rng)
    assert not skin_coloured(dark, band_xy, skin_rgb, skin_xy, candidate_clipped=np.ones(len(dark), bool)).any()


def test_too_few_skin_pixels_or_bad_values_keep_nothing(face):
    rng, skin_xy, skin_rgb, band_xy = face
    cand = lit(SKIN_ALBEDO, band_xy, rng)
    n = MIN_REFERENCE - 1
    assert not skin_coloured(cand, band_xy, skin_rgb[:n], skin_xy[:n]).any()
    cand[:5] = np.nan
    cand[5:10, 1] = np.inf
    keep = skin_coloured(cand, band_xy, skin_rgb, skin_xy, edge=0)
    assert not keep[:10].any() and keep[10:].mean() > 0.97
    # non-finite skin pixels are ignored, not propagated
    bad = skin_rgb.copy()
    bad[:100] = np.nan
    assert skin_coloured(cand, band_xy, bad, skin_xy, edge=0)[10:].mean() > 0.97
