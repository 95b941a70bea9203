"""Tests for the face-fit debug overlay (f2l.face.overlay): pixel values per panel, PNG round trip, validation."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from f2l.face.overlay import (CAPTION_H, EMPTY, PAD, IRIS_COLOUR, REASON_COLOURS, TINT_ALPHA, USABLE_COLOUR,
                              UNKNOWN_COLOUR, colormap, overlay_layout, render_overlay, write_overlay)

SIZE, SCALE, GREY = 64, 2, 100
LO, HI, MID = 16, 48, 32  # face pixels: rows/cols [LO, HI); normals +Z left of MID, +X right
# mask rows: [16, 24) usable, then 4 rows each of these reasons, then [44, 48) excluded with no reason
BANDS = {"features": 24, "border": 28, "clipped": 32, "black": 36, "weird": 40}


def _inputs(**overrides):
    crop = np.full((SIZE, SIZE, 3), GREY, np.uint8)
    g = np.linspace(8, 56, 22)
    gx, gy = np.meshgrid(g, g)
    landmarks = np.stack([gx.ravel(), gy.ravel()], axis=1)[:478]
    tris = []
    for r in range(6):  # a 7x7-vertex patch of the landmark grid, two triangles per cell
        for c in range(6):
            a, b, d, e = r * 22 + c, r * 22 + c + 1, (r + 1) * 22 + c, (r + 1) * 22 + c + 1
            tris += [(a, b, d), (b, e, d)]
    rr, cc = np.mgrid[LO:HI, LO:HI]
    rc = np.stack([rr.ravel(), cc.ravel()], axis=1)
    rows, cols = rc[:, 0], rc[:, 1]
    normals = np.where((cols < MID)[:, None], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    mask = rows < 24
    excluded = {name: (rows >= start) & (rows < start + 4) for name, start in BANDS.items()}
    vis = (cols >= MID).astype(np.float64)
    kw = dict(crop=crop, landmarks_xy=landmarks, triangles=np.array(tris), pixel_rc=rc, normals=normals,
              mask=mask, excluded=excluded, sky_visibility=vis, title="synthetic face", scale=SCALE)
    kw.update(overrides)
    return kw


def _px(img, panel, r, c, scale=SCALE):
    r0, c0 = overlay_layout((SIZE, SIZE, 3), scale)[panel]
    return img[r0 + r * scale + scale // 2, c0 + c * scale + scale // 2].astype(int)


@pytest.fixture(scope="module")
def image():
    return render_overlay(**_inputs())


def test_shape_and_layout(image):
    assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
    origins = overlay_layout((SIZE, SIZE, 3), SCALE)
    assert len(origins) == 4 and all(r == CAPTION_H for r, _ in origins)
    assert image.shape[1] == origins[-1][1] + SIZE * SCALE + PAD
    assert [c for _, c in origins] == [PAD + k * (SIZE * SCALE + PAD) for k in range(4)]
    assert image.shape[0] > CAPTION_H + SIZE * SCALE
    assert image[: CAPTION_H - 2].max() > 200  # caption text was drawn


def test_photo_panel_mesh_and_landmarks(image):
    assert np.array_equal(_px(image, 0, 0, 0), [GREY] * 3)  # corner: no mesh, no landmark
    assert np.array_equal(_px(image, 0, 63, 63), [GREY] * 3)
    r0, c0 = overlay_layout((SIZE, SIZE, 3), SCALE)[0]
    panel = image[r0:r0 + SIZE * SCALE, c0:c0 + SIZE * SCALE].astype(int)
    greenish = (panel[..., 1] > panel[..., 0] + 40) & (panel[..., 1] > panel[..., 2] + 40)
    assert greenish.sum() > 100  # wireframe lines
    assert (panel == IRIS_COLOUR).all(axis=-1).any()  # iris dots in their own colour


def test_normal_panel(image):
    assert np.array_equal(_px(image, 1, 30, 20), [128, 128, 255])  # +Z
    assert np.array_equal(_px(image, 1, 30, 40), [255, 128, 128])  # +X
    assert np.array_equal(_px(image, 1, 5, 5), [EMPTY] * 3)              # not a face pixel


def test_mask_panel(image):
    def blend(colour):
        return np.rint(TINT_ALPHA * np.array(colour) + (1 - TINT_ALPHA) * GREY).astype(int)

    assert np.abs(_px(image, 2, 20, 30) - blend(USABLE_COLOUR)).max() <= 1
    for name, start in BANDS.items():
        expected = blend(REASON_COLOURS.get(name, UNKNOWN_COLOUR))
        assert np.abs(_px(image, 2, start + 1, 30) - expected).max() <= 1, name
    assert np.abs(_px(image, 2, 45, 30) - GREY).max() <= 1  # excluded, no reason given
    assert np.abs(_px(image, 2, 5, 5) - GREY).max() <= 1    # not a face pixel


def test_mask_wins_over_reason_and_first_reason_wins():
    kw = _inputs()
    rows = kw["pixel_rc"][:, 0]
    kw["excluded"] = {"border": rows < 28, "features": rows < 48}  # border also flags usable rows
    img = render_overlay(**kw)
    blend = lambda col: TINT_ALPHA * np.array(col) + (1 - TINT_ALPHA) * GREY  # noqa: E731
    assert np.abs(_px(img, 2, 20, 30) - blend(USABLE_COLOUR)).max() <= 1
    assert np.abs(_px(img, 2, 25, 30) - blend(REASON_COLOURS["border"])).max() <= 1
    assert np.abs(_px(img, 2, 30, 30) - blend(REASON_COLOURS["features"])).max() <= 1


def test_visibility_panel(image):
    v0, v1 = _px(image, 3, 30, 20), _px(image, 3, 30, 40)
    assert np.array_equal(v0, colormap(0.0)) and np.array_equal(v1, colormap(1.0))
    assert np.abs(v0 - v1).sum() > 100
    assert np.array_equal(_px(image, 3, 5, 5), [EMPTY] * 3)


def test_visibility_panel_greys_untraced_pixels():
    kw = _inputs()
    traced = kw["pixel_rc"][:, 0] < 30  # rows >= 30 were not ray-traced
    img = render_overlay(**kw, traced=traced)
    assert np.array_equal(_px(img, 3, 20, 40), colormap(1.0))
    assert np.array_equal(_px(img, 3, 40, 40), [EMPTY] * 3)
    assert np.array_equal(_px(img, 3, 40, 20), [EMPTY] * 3)
    with pytest.raises(ValueError, match="traced"):
        render_overlay(**kw, traced=traced[:-1])


def test_scale_one_and_no_exclusions():
    img = render_overlay(**_inputs(scale=1, excluded=None, title=""))
    assert np.array_equal(_px(img, 1, 30, 40, scale=1), [255, 128, 128])
    assert np.array_equal(_px(img, 2, 30, 30, scale=1), [GREY] * 3)  # not usable, no reason: plain grey


def test_write_overlay_round_trip(tmp_path, image):
    path = tmp_path / "face.png"
    write_overlay(path, **_inputs())
    with Image.open(path) as im:
        assert im.format == "PNG"
        assert np.array_equal(np.asarray(im.convert("RGB")), image)
    assert [p.name for p in tmp_path.iterdir()] == ["face.png"]  # no temporary left behind


def test_write_overlay_bad_input_leaves_nothing(tmp_path):
    with pytest.raises(ValueError, match="scale"):
        write_overlay(tmp_path / "face.png", **_inputs(scale=0))
    assert list(tmp_path.iterdir()) == []


def _n(kw):
    return len(kw["pixel_rc"])


@pytest.mark.parametrize("name, value", [
    ("crop", lambda kw: kw["crop"].astype(np.float32)),
    ("crop", lambda kw: kw["crop"][..., 0]),
    ("landmarks_xy", lambda kw: kw["landmarks_xy"][:477]),
    ("landmarks_xy", lambda kw: np.full((478, 2), np.nan)),
    ("triangles", lambda kw: kw["triangles"].astype(float)),
    ("triangles", lambda kw: np.array([[0, 1, 478]])),
    ("pixel_rc", lambda kw: kw["pixel_rc"] + 40),
    ("pixel_rc", lambda kw: kw["pixel_rc"].astype(float)),
    ("normals", lambda kw: kw["normals"][:-1]),
    ("normals", lambda kw: kw["normals"] * 2),
    ("mask", lambda kw: kw["mask"].astype(int)),
    ("sky_visibility", lambda kw: kw["sky_visibility"] + 0.5),
    ("sky_visibility", lambda kw: np.full(_n(kw), np.nan)),
    ("excluded", lambda kw: [kw["mask"]]),
    ("excluded", lambda kw: {"border": kw["mask"][:-1]}),
    ("title", lambda kw: 3),
    ("scale", lambda kw: 0),
    ("scale", lambda kw: 1.5),
])
def test_bad_inputs_raise_value_error(name, value):
    kw = _inputs()
    kw[name] = value(kw)
    with pytest.raises(ValueError, match=name):
        render_overlay(**kw)


@pytest.mark.parametrize("size, scale", [(1, 1), (4, 1), (7, 3)])
def test_tiny_crops_render(size, scale):
    kw = _inputs(crop=np.zeros((size, size, 3), np.uint8), pixel_rc=np.array([[0, 0]]),
                 normals=np.array([[0.0, 1.0, 0.0]]), mask=np.array([True]), excluded={"odd": np.array([True])},
                 sky_visibility=np.array([0.5]), scale=scale)
    img = render_overlay(**kw)
    origins = overlay_layout((size, size, 3), scale)
    assert img.shape[1] == origins[-1][1] + size * scale + PAD
    assert np.array_equal(img[origins[1]], [128, 255, 128])  # +Y normal at crop pixel (0, 0)
