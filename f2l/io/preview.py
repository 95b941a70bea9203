"""Display copies of HDR images: tone mapping, PNG writing, labelled contact sheets.

Previews are for people only and are never read back as inputs. Tone mapping: linear RGB is
multiplied by ``2 ** exposure_ev`` or, without an exposure, by ``0.8 / p`` where p is the given
percentile of Rec.709 luminance Y = 0.2126 R + 0.7152 G + 0.0722 B; then clipped to [0, 1],
encoded with the sRGB transfer function (colour-science) and rounded to uint8.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from PIL import Image, ImageDraw, ImageFont

from f2l.io.atomic import atomic_path

__all__ = ["REC709_LUMA", "auto_exposure_scale", "tonemap", "probe_preview", "save_png", "contact_sheet"]

REC709_LUMA = np.array([0.2126, 0.7152, 0.0722])
"""Rec.709 / sRGB relative luminance weights (sum to 1)."""

_TARGET = 0.8  # the chosen luminance percentile maps to this linear value


def _as_rgb_float(hdr: np.ndarray) -> np.ndarray:
    x = np.asarray(hdr, dtype=np.float64)
    if x.ndim == 2:
        x = np.repeat(x[:, :, None], 3, axis=2)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) or (H, W) image, got shape {np.shape(hdr)}")
    # NaN and -inf become 0 (black); +inf stays and clips to white.
    return np.nan_to_num(x, nan=0.0, neginf=0.0, posinf=np.inf)


def auto_exposure_scale(hdr: np.ndarray, percentile: float = 99.0) -> float:
    """Linear scale mapping the ``percentile`` of finite luminance to 0.8 (1.0 if all dark).

    Falls back to the maximum luminance when the percentile is zero (e.g. a dark sky with a
    tiny sun), so any positive content stays visible.
    """
    x = _as_rgb_float(hdr)
    lum = x @ REC709_LUMA
    lum = lum[np.isfinite(lum)]
    if lum.size == 0:
        return 1.0
    ref = float(np.percentile(lum, percentile))
    if not ref > 0.0:
        ref = float(lum.max())
    return _TARGET / ref if ref > 0.0 else 1.0


def srgb_encode(v: np.ndarray) -> np.ndarray:
    """The sRGB OETF (IEC 61966-2-1) of linear values in [0, 1], float64; equal to colour-science's
    ``cctf_encoding(v, function="sRGB")`` (tests/test_preview.py), written out because importing
    colour-science costs about a second, most of a cold ``f2l estimate`` on one photo."""
    v = np.asarray(v, np.float64)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(np.maximum(v, 0.0031308), 1.0 / 2.4) - 0.055)


def tonemap(hdr: np.ndarray, exposure_ev: float | None = None, percentile: float = 99.0) -> np.ndarray:
    """Tone-map linear HDR (H, W, 3) or (H, W) to sRGB uint8 (H, W, 3).

    ``exposure_ev`` given: scale = 2 ** exposure_ev. Otherwise scale = 0.8 / (percentile of
    Rec.709 luminance). Then clip(scale * x, 0, 1) -> sRGB OETF -> round(255 v). NaN -> 0.
    """
    x = _as_rgb_float(hdr)
    scale = 2.0 ** float(exposure_ev) if exposure_ev is not None else auto_exposure_scale(x, percentile)
    with np.errstate(invalid="ignore", over="ignore"):
        v = np.clip(x * scale, 0.0, 1.0)
    v = np.nan_to_num(v, nan=0.0)  # inf * 0 scale
    encoded = srgb_encode(v)
    return np.clip(np.rint(encoded * 255.0), 0, 255).astype(np.uint8)


def probe_preview(
    probe: np.ndarray, exposure_ev: float | None = None, percentile: float = 99.0, scale: int = 1
) -> np.ndarray:
    """Tone-mapped uint8 preview of a lat-long probe, optionally enlarged ``scale`` x (nearest).

    Pass a fixed ``exposure_ev`` to compare several probes on the same exposure.
    """
    img = tonemap(probe, exposure_ev=exposure_ev, percentile=percentile)
    if int(scale) != scale or scale < 1:
        raise ValueError(f"scale must be a positive integer, got {scale!r}")
    if scale > 1:
        img = np.repeat(np.repeat(img, int(scale), axis=0), int(scale), axis=1)
    return img


def _check_uint8_image(image: np.ndarray, what: str) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f"{what}: expected a uint8 image, got {img.dtype}")
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] in (1, 3, 4))):
        raise ValueError(f"{what}: expected (H, W), (H, W, 3) or (H, W, 4), got {img.shape}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    return img


def save_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write a uint8 image as PNG atomically (temp file in the same directory + os.replace)."""
    path = Path(path)
    img = _check_uint8_image(image, str(path))
    with atomic_path(path) as tmp:
        Image.fromarray(np.ascontiguousarray(img)).save(tmp, format="PNG")


def _font() -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    return ImageFont.load_default()


def _label_height(font) -> int:
    return int(font.getbbox("Ag|")[3]) + 2


def _fit_height(img: np.ndarray, height: int) -> Image.Image:
    pil = Image.fromarray(np.ascontiguousarray(img)).convert("RGB")
    h, w = img.shape[:2]
    width = max(1, int(round(w * height / h)))
    if (width, height) == (w, h):
        return pil
    resample = Image.Resampling.NEAREST if height > h else Image.Resampling.LANCZOS
    return pil.resize((width, height), resample=resample)


def contact_sheet(
    rows: list[list[tuple[str, np.ndarray]]], cell_height: int = 128, pad: int = 4
) -> np.ndarray:
    """Grid of labelled tiles on white, returned as uint8 (H, W, 3).

    Each tile is resized to ``cell_height`` keeping its aspect ratio (nearest when enlarging)
    with its label drawn above it in PIL's default font. Column j is as wide as its widest tile
    or label; sheet size = (pad + n_rows (label_h + cell_height + pad),
    pad + sum_j (col_width_j + pad)).
    """
    if cell_height < 1 or pad < 0:
        raise ValueError(f"cell_height must be >= 1 and pad >= 0, got {cell_height}, {pad}")
    if not rows or not any(rows):
        raise ValueError("contact_sheet needs at least one tile")
    font = _font()
    label_h = _label_height(font)
    tiles = [
        [(str(label), _fit_height(_check_uint8_image(img, f"tile {label!r}"), cell_height)) for label, img in row]
        for row in rows
    ]
    n_cols = max(len(row) for row in tiles)
    col_w = [0] * n_cols
    for row in tiles:
        for j, (label, tile) in enumerate(row):
            col_w[j] = max(col_w[j], tile.width, int(np.ceil(font.getlength(label))))
    width = pad + sum(w + pad for w in col_w)
    height = pad + len(tiles) * (label_h + cell_height + pad)
    sheet = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    y = pad
    for row in tiles:
        x = pad
        for j, (label, tile) in enumerate(row):
            draw.text((x, y), label, fill=(0, 0, 0), font=font)
            sheet.paste(tile, (x, y + label_h))
            x += col_w[j] + pad
        y += label_h + cell_height + pad
    return np.asarray(sheet, dtype=np.uint8).copy()
