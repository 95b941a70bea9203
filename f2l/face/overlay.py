"""Debug overlay for one fitted face: a PNG that people look at to judge a fit.

Four panels side by side, each the working-resolution crop upscaled ``scale``× (nearest):

1. the photo with the mesh wireframe (semi-transparent green) and the landmarks (dots; the 10
   iris landmarks 468–477 in cyan);
2. the normal map, RGB = n · 0.5 + 0.5 (camera frame) on face pixels, dark grey elsewhere;
3. the mask: the photo in greyscale, usable pixels tinted green, excluded pixels tinted by reason
   (:data:`REASON_COLOURS`; unknown reasons grey; a pixel in ``mask`` is shown as usable even if a
   reason flags it, otherwise the first flagging reason in dict order wins);
4. sky visibility through a viridis-like colormap on the ray-traced face pixels (``traced``;
   all face pixels when it is None), dark grey elsewhere.

A caption strip (:data:`CAPTION_H` px) above the panels holds the title and the panel labels; a
footer below holds the mask legend (pixel counts per reason; reasons may overlap) and a colour
bar for the visibility panel. Panels are
:data:`PAD` px apart; :func:`overlay_layout` gives their top-left corners, so crop pixel (r, c)
of panel k covers output rows ``row_k + r*scale ...`` and columns ``col_k + c*scale ...``.
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

__all__ = ["render_overlay", "write_overlay", "render_photo_overlay", "write_photo_overlay", "overlay_layout", "colormap",
           "PANEL_LABELS", "REASON_COLOURS", "CAPTION_H", "PAD", "TINT_ALPHA"]

NUM_LANDMARKS = 478
IRIS_START = 468
CAPTION_H = 30          # caption strip height (title line + panel-label line)
PAD = 4                 # gap around and between panels
LINE_H = 13             # text line height in caption and footer
TINT_ALPHA = 0.55       # mask panel: colour = alpha * tint + (1 - alpha) * grey
PANEL_LABELS = ("photo + mesh", "normals (camera)", "mask", "sky visibility")
BACKGROUND = 24   # grey level of the canvas (caption, gaps, footer)
EMPTY = 48        # grey level of non-face pixels in the normal and visibility panels
TEXT = (235, 235, 235)
USABLE_COLOUR = (0, 255, 0)
UNKNOWN_COLOUR = (160, 160, 160)
REASON_COLOURS = {"features": (255, 0, 0), "border": (255, 150, 0), "hair": (150, 90, 40),
                  "clipped": (255, 0, 255), "black": (0, 90, 255)}
WIRE_COLOUR = (0, 255, 0)
WIRE_ALPHA = 0.4
DOT_COLOUR = (255, 230, 0)
IRIS_COLOUR = (0, 230, 255)
# viridis sampled at 8 evenly spaced stops
_VIRIDIS = np.array([(68, 1, 84), (70, 50, 126), (54, 92, 141), (39, 127, 142),
                     (31, 161, 135), (74, 193, 109), (160, 218, 57), (253, 231, 37)], float)
_LUMA = np.array([0.2126, 0.7152, 0.0722])


def colormap(values: np.ndarray) -> np.ndarray:
    """Map values in [0, 1] to uint8 RGB (…, 3) with a viridis-like ramp (clipped outside)."""
    v = np.clip(np.asarray(values, float), 0.0, 1.0)
    stops = np.linspace(0.0, 1.0, len(_VIRIDIS))
    rgb = np.stack([np.interp(v, stops, _VIRIDIS[:, k]) for k in range(3)], axis=-1)
    return np.rint(rgb).astype(np.uint8)


def overlay_layout(crop_shape: tuple[int, ...], scale: int = 2) -> list[tuple[int, int]]:
    """(row, col) of the top-left output pixel of each of the four panels."""
    width = int(crop_shape[1]) * scale
    return [(CAPTION_H, PAD + k * (width + PAD)) for k in range(4)]


def render_overlay(crop, landmarks_xy, triangles, pixel_rc, normals, mask, excluded,
                   sky_visibility, title: str = "", scale: int = 2,
                   traced: np.ndarray | None = None) -> np.ndarray:
    """Render the four-panel overlay as an (H, W, 3) uint8 image; see the module docstring."""
    crop, lm, tri, rc, nrm, mask, excluded, vis, scale = _validate(
        crop, landmarks_xy, triangles, pixel_rc, normals, mask, excluded, sky_visibility, title, scale)
    if traced is not None:
        traced = np.asarray(traced)
        if traced.dtype != bool or traced.shape != (len(rc),):
            raise ValueError(f"traced: expected ({len(rc)},) bool, got {traced.dtype} {traced.shape}")
    R, C = crop.shape[:2]
    rows, cols = rc[:, 0], rc[:, 1]

    normal_panel = np.full_like(crop, EMPTY)
    normal_panel[rows, cols] = np.rint((np.clip(nrm, -1, 1) * 0.5 + 0.5) * 255).astype(np.uint8)

    vis_panel = np.full_like(crop, EMPTY)
    shown = slice(None) if traced is None else traced
    vis_panel[rows[shown], cols[shown]] = colormap(vis[shown])

    grey = crop.astype(np.float32) @ _LUMA.astype(np.float32)
    mask_panel = np.repeat(grey[..., None], 3, axis=2)
    tint = np.full((len(rc), 3), np.nan, np.float32)
    legend = [("usable", USABLE_COLOUR, int(mask.sum()))]
    unclaimed = ~mask
    for name, flags in excluded.items():
        colour = REASON_COLOURS.get(name, UNKNOWN_COLOUR)
        claim = flags & unclaimed
        tint[claim] = colour
        unclaimed &= ~claim
        legend.append((name, colour, int(flags.sum())))
    tint[mask] = USABLE_COLOUR
    has = ~np.isnan(tint[:, 0])
    base = mask_panel[rows[has], cols[has]]
    mask_panel[rows[has], cols[has]] = TINT_ALPHA * tint[has] + (1 - TINT_ALPHA) * base
    mask_panel = np.rint(mask_panel).astype(np.uint8)

    photo_panel = _draw_mesh(_upscale(crop, scale), lm, tri, scale)
    origins = overlay_layout(crop.shape, scale)
    footer_y = CAPTION_H + R * scale + PAD
    width = origins[-1][1] + C * scale + PAD
    font = _font()
    legend_lines = _legend_rows(legend, font, origins[-1][1] - PAD - PAD)
    height = footer_y + max(1, len(legend_lines)) * LINE_H + PAD

    canvas = np.full((height, width, 3), BACKGROUND, np.uint8)
    for (r0, c0), panel in zip(origins, (photo_panel, _upscale(normal_panel, scale),
                                         _upscale(mask_panel, scale), _upscale(vis_panel, scale))):
        canvas[r0:r0 + R * scale, c0:c0 + C * scale] = panel
    bar_x, bar_w = origins[-1][1] + 10, max(0, C * scale - 24)  # visibility colour bar: "0 [ramp] 1"
    canvas[footer_y + 2:footer_y + 10, bar_x:bar_x + bar_w] = colormap(np.linspace(0, 1, bar_w))

    image = Image.fromarray(canvas)
    draw = ImageDraw.Draw(image)
    draw.text((PAD, 3), title, fill=TEXT, font=font)
    for (_, c0), label in zip(origins, PANEL_LABELS):
        draw.text((c0, 3 + LINE_H), label, fill=TEXT, font=font)
    for i, line in enumerate(legend_lines):
        for x, text, colour in line:
            y = footer_y + i * LINE_H
            draw.rectangle((x, y + 2, x + 7, y + 9), fill=colour)
            draw.text((x + 10, y), text, fill=TEXT, font=font)
    if bar_w:
        draw.text((bar_x - 10, footer_y), "0", fill=TEXT, font=font)
        draw.text((bar_x + bar_w + 2, footer_y), "1", fill=TEXT, font=font)
    return np.array(image)


def write_overlay(path: str | os.PathLike, **kwargs) -> None:
    """Render with :func:`render_overlay` and write a PNG atomically (``<path>.<pid>.tmp`` + rename)."""
    _write_png(path, render_overlay(**kwargs))


KEPT_COLOUR = (60, 220, 90)
REFUSED_COLOUR = (235, 70, 60)


def render_photo_overlay(display: np.ndarray, scale: float, faces: list[tuple], title: str = "") -> np.ndarray:
    """The whole photo with every detected face: ``faces`` holds (box (x0, y0, x1, y1) in photo px,
    label, kept); kept faces are framed green, refused ones red, each labelled (its index and
    face id or refusal reason). ``display`` is the photo (or a reduced copy: photo px × ``scale``
    = its px); a title strip above it names the photo."""
    img = Image.fromarray(np.ascontiguousarray(display)).convert("RGB")
    width = max(1, round(img.width))
    canvas = Image.new("RGB", (width, img.height + LINE_H + 6), (BACKGROUND,) * 3)
    canvas.paste(img, (0, LINE_H + 6))
    draw = ImageDraw.Draw(canvas)
    font = _font()
    draw.text((4, 3), title, fill=(230, 230, 230), font=font)
    line = max(1, round(min(img.width, img.height) / 400))
    for box, label, kept in faces:
        x0, y0, x1, y1 = (float(v) * scale for v in box)
        y0, y1 = y0 + LINE_H + 6, y1 + LINE_H + 6
        colour = KEPT_COLOUR if kept else REFUSED_COLOUR
        draw.rectangle((x0, y0, x1, y1), outline=colour, width=line)
        tw = draw.textlength(label, font=font)
        ty = y0 - LINE_H - 1 if y0 - LINE_H - 1 >= LINE_H + 6 else y1 + 1
        draw.rectangle((x0, ty, x0 + tw + 4, ty + LINE_H), fill=(0, 0, 0))
        draw.text((x0 + 2, ty), label, fill=colour, font=font)
    return np.asarray(canvas)


def write_photo_overlay(path: str | os.PathLike, display: np.ndarray, scale: float, faces: list[tuple],
                        title: str = "") -> None:
    """:func:`render_photo_overlay` written as a PNG atomically."""
    _write_png(path, render_photo_overlay(display, scale, faces, title))


def _write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    path = Path(path)
    tmp = Path(f"{path}.{os.getpid()}.tmp")
    try:
        Image.fromarray(image).save(tmp, format="PNG", compress_level=1)  # fast: ~4x quicker than the default
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@lru_cache(maxsize=1)
def _font():
    return ImageFont.load_default()


def _upscale(img: np.ndarray, scale: int) -> np.ndarray:
    return img if scale == 1 else np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)


def _draw_mesh(panel: np.ndarray, lm: np.ndarray, tri: np.ndarray, scale: int) -> np.ndarray:
    """Wireframe (semi-transparent, overlaps do not stack) and landmark dots, rasterised in numpy."""
    out = panel.copy()
    pts = lm * scale - 0.5  # crop coords (pixel centres at +0.5) -> output pixel indices
    if len(tri):
        e = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1).astype(np.int64)
        e = np.unique(e[:, 0] * NUM_LANDMARKS + e[:, 1])
        p0, p1 = pts[e // NUM_LANDMARKS], pts[e % NUM_LANDMARKS]
        # DDA: one sample per step along the major axis (capped, for landmarks far outside the crop)
        n = np.minimum(np.ceil(np.abs(p1 - p0).max(axis=1)), 4 * sum(out.shape[:2])).astype(np.int64) + 1
        edge = np.repeat(np.arange(len(e)), n)
        t = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(np.maximum(n - 1, 1), n)
        _paint(out, p0[edge] + t[:, None] * (p1 - p0)[edge], WIRE_COLOUR, WIRE_ALPHA, 0)
    _paint(out, pts[:IRIS_START], DOT_COLOUR, 1.0, scale // 2)
    _paint(out, pts[IRIS_START:], IRIS_COLOUR, 1.0, scale // 2)
    return out


def _paint(img: np.ndarray, xy: np.ndarray, colour, alpha: float, radius: int) -> None:
    """Blend ``colour`` into the pixels within ``radius`` (a disc) of the points ``xy`` (x, y), in place."""
    H, W = img.shape[:2]
    offsets = [(dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)
               if dy * dy + dx * dx <= radius * radius]
    centre = np.floor(xy + 0.5).astype(np.int64)
    hit = np.zeros((H, W), bool)
    for dy, dx in offsets:
        x, y = centre[:, 0] + dx, centre[:, 1] + dy
        keep = (x >= 0) & (x < W) & (y >= 0) & (y < H)
        hit[y[keep], x[keep]] = True
    if alpha >= 1.0:
        img[hit] = colour
    else:
        img[hit] = np.rint(alpha * np.asarray(colour, np.float32) + (1 - alpha) * img[hit]).astype(np.uint8)


def _legend_rows(entries, font, max_width: int):
    """Flow (name, colour, count) legend entries into lines of (x, text, colour) within max_width."""
    lines, line, x = [], [], PAD
    for name, colour, count in entries:
        text = f"{name} {count}"
        w = 10 + int(font.getlength(text)) + 8
        if line and x + w > PAD + max_width:
            lines.append(line)
            line, x = [], PAD
        line.append((x, text, colour))
        x += w
    return lines + [line]


def _validate(crop, lm, tri, rc, nrm, mask, excluded, vis, title, scale):
    kind_names = {"u": "uint8", "fiu": "real", "iu": "integer", "f": "floating-point", "b": "bool"}

    def arr(name, value, shape, kinds):
        a = np.asarray(value)
        if a.dtype.kind not in kinds:
            raise ValueError(f"{name}: expected {kind_names[kinds]} values, got dtype {a.dtype}")
        if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
            want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
            raise ValueError(f"{name}: expected shape {want}, got {a.shape}")
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise ValueError(f"{name}: contains NaN or infinite values")
        return a

    crop = arr("crop", crop, (None, None, 3), "u")
    if crop.dtype != np.uint8 or crop.shape[0] == 0 or crop.shape[1] == 0:
        raise ValueError(f"crop: expected a non-empty (R, C, 3) uint8 image, got {crop.dtype} {crop.shape}")
    R, C = crop.shape[:2]
    lm = arr("landmarks_xy", lm, (NUM_LANDMARKS, 2), "fiu").astype(np.float64)
    tri = arr("triangles", tri, (None, 3), "iu")
    if tri.size and (tri.min() < 0 or tri.max() >= NUM_LANDMARKS):
        raise ValueError(f"triangles: indices must lie in [0, {NUM_LANDMARKS}), got [{tri.min()}, {tri.max()}]")
    rc = arr("pixel_rc", rc, (None, 2), "iu").astype(np.int64)
    N = len(rc)
    if N and ((rc < 0).any() or (rc.max(axis=0) >= (R, C)).any()):
        raise ValueError(f"pixel_rc: (row, col) must lie inside the {R}x{C} crop")
    nrm = arr("normals", nrm, (N, 3), "f")
    if N and np.abs(np.linalg.norm(nrm, axis=1) - 1).max() > 1e-3:
        raise ValueError("normals: expected unit vectors (|n| = 1 within 1e-3)")
    mask = arr("mask", mask, (N,), "b")
    vis = arr("sky_visibility", vis, (N,), "f")
    if N and (vis.min() < 0 or vis.max() > 1):
        raise ValueError(f"sky_visibility: values must lie in [0, 1], got [{vis.min():g}, {vis.max():g}]")
    if excluded is None:
        excluded = {}
    if not isinstance(excluded, dict):
        raise ValueError(f"excluded: expected None or a dict of reason -> (N,) bool array, "
                         f"got {type(excluded).__name__}")
    excluded = {str(k): arr(f"excluded[{k!r}]", v, (N,), "b") for k, v in excluded.items()}
    if not isinstance(title, str):
        raise ValueError(f"title: expected str, got {type(title).__name__}")
    if isinstance(scale, bool) or not isinstance(scale, (int, np.integer)) or scale < 1:
        raise ValueError(f"scale: expected an integer >= 1, got {scale!r}")
    return crop, lm, tri, rc, nrm, mask, excluded, vis, int(scale)
