"""RAW-domain HDR merge of an exposure bracket: merge on the Bayer mosaic, then demosaic once.

Units. A frame of exposure factor ``e = t * (ISO / 100) / N**2`` (``= 2**-EV100``) gives per CFA
sample ``x = (raw - black_p) / (white - mean(black)) / e`` (``black_p``: black level of the sample's
2x2 CFA position): radiance in units where 1.0 just reaches white at EV100 = 0 (1 s, f/1, ISO 100),
so a frame of EV100 = v clips at ``x = 2**v``. The output keeps this scale (``scale = 1``); with a
saturation-based ISO (ISO 12232, q = 0.65) a neutral ``x`` is about ``LUMINANCE_CD_M2_PER_UNIT * x``
cd/m2.

Weights, per 2x2 CFA quad (a frame gives all four colours of a quad or none, so no clipped sample
reaches the demosaic outside the saturated-everywhere region): the inverse variance of ``x``,
``w = (e / e_ref)**2 / (s * (ISO / 100) / full_well_e + (read_noise_dn / range)**2)``, ``s`` the
quad's mean normalised signal (a sample's own noisy value would bias the merge low); ``w = 0`` if a
quad sample is at or above ``black + saturation_fraction * (white - black)`` or, except in the
longest exposure, if the quad mean is below ``dark_dn``. ``x = sum(w x) / sum(w)``, negatives -> 0.

Saturated everywhere. Quads clipped in every frame take the shortest frame's values, clipped
samples at exactly ``1 / e_min`` (the most it records); ``saturated`` flags them plus a 1-pixel
border (the demosaic footprint): flagged values are lower bounds, never averages.

Alignment and motion. Frames are merged one at a time into running sums (float32; float64 only for
scalars and the alignment window) while the next two are decoded and normalised in threads, from the middle exposure (the reference) outwards, each
aligned to its already aligned neighbour in exposure (``_estimate_shift``); shifts of at least
``min_shift_px`` (full-resolution pixels) are corrected by bilinear resampling of each CFA plane, the
uncovered border getting no weight. Then each frame is compared with the merge where both are well
exposed: a quad is inconsistent beyond 4 sigma (noise of both) + ``motion_tolerance`` (relative) +
half a quad of misregistration (0.5 x local gradient); a frame with more than ``moved_fraction``
inconsistent quads is "moved" (reported, warned, still merged).

Demosaic: bilinear (:func:`~f2l.io.raw_meta.demosaic_bilinear`), a convex combination;
gradient-corrected kernels (Malvar) overshoot across 1e7-contrast edges (a sun) into negative radiance.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from scipy import fft as sfft

from f2l.io.raw_meta import (  # noqa: F401 (RawFrame, raw_frame: re-exported merge inputs)
    BAYER_PATTERNS, RawFrame, RawMeta, camera_to_rec709, demosaic_bilinear, exif_fields, quad_mean, raw_frame, read_raw,
    read_raw_metadata,
)  # fmt: skip

__all__ = [
    "BracketError", "BracketStart", "NoiseModel", "RawFrame", "FrameInfo", "MergedHDR", "raw_frame", "merge_bracket",
    "LUMINANCE_CD_M2_PER_UNIT",
]  # fmt: skip

LUMINANCE_CD_M2_PER_UNIT = 78.0 / (0.65 * 100.0)
"""ISO 12232 saturation-based speed: L_sat = 78 N^2 / (q ISO t) = 1.2 / e cd/m2 (camera-dependent)."""


class BracketError(ValueError):
    """A bracket cannot be merged (too few frames, mixed cameras or sizes, missing exposure data)."""


@dataclass(frozen=True)
class NoiseModel:
    """Sensor noise for the weights: electrons at white at ISO 100, read noise in DN."""

    full_well_e: float = 20000.0
    read_noise_dn: float = 2.0


@dataclass
class FrameInfo:
    """What the merge did with one frame. ``status``: "reference", "ok" or "moved"; ``shift_px``:
    (rows, cols) of its content relative to the reference, full-resolution pixels (``None``: too
    little well-exposed texture in common with its neighbour to estimate; merged as recorded);
    ``aligned``: a correction was applied; ``used_fraction`` / ``dominant_fraction``: share of
    quads it weighted / weighted most; ``inconsistent_fraction``: see the motion check above."""

    name: str
    exposure_s: float
    f_number: float
    iso: float
    exposure_factor: float
    ev100: float
    status: str = "ok"
    used_fraction: float = 0.0
    dominant_fraction: float = 0.0
    shift_px: tuple[float, float] | None = (0.0, 0.0)
    aligned: bool = False
    inconsistent_fraction: float = 0.0
    moved: bool = False


@dataclass
class MergedHDR:
    """A merged bracket: ``rgb`` (H, W, 3) and ``mosaic`` (H, W) float32 in the module's units (camera
    RGB, or linear Rec.709 when ``colour_space == "rec709"``), H and W the frame size rounded down to
    even; ``saturated`` pixels hold lower bounds. ``status`` is "ok" or "moved". ``rgb`` is the
    bilinear demosaic of ``mosaic``, computed on first use (by whichever thread writes the view)."""

    mosaic: np.ndarray
    saturated: np.ndarray
    saturated_fraction: float
    cfa_pattern: str
    colour_space: str
    min_exposure_factor: float
    reference: str
    frames: list[FrameInfo]
    status: str = "ok"
    warnings: list[str] = field(default_factory=list)
    scale: float = 1.0
    xyz_to_camera: tuple[float, ...] | None = None  # the reference frame's colour matrix (see raw_meta)
    rgb_cache: np.ndarray | None = field(default=None, repr=False)

    @property
    def rgb(self) -> np.ndarray:
        if self.rgb_cache is None:
            self.rgb_cache = demosaic_bilinear(self.mosaic, self.cfa_pattern)
        return self.rgb_cache


def _resolve(item) -> tuple[RawMeta, Callable[[], tuple[RawMeta, np.ndarray]]]:
    """(metadata known before decoding, loader of full metadata and mosaic) for one input."""
    if isinstance(item, RawFrame):
        mosaic = np.asarray(item.mosaic)
        if mosaic.dtype != np.uint16 or mosaic.shape != (item.meta.height, item.meta.width):
            raise BracketError(f"{item.meta.path}: need a uint16 mosaic of its metadata's size, got "
                               f"{mosaic.dtype} {mosaic.shape}")  # fmt: skip
        return item.meta, lambda: (item.meta, mosaic)
    path = os.fspath(item)
    fields = exif_fields(path)  # about 1 ms: exposure and camera for ordering and checks
    if not (fields["exposure_s"] and fields["f_number"] and fields["iso"]):
        fields = {k: getattr(read_raw_metadata(path), k) for k in fields}  # LibRaw's own EXIF parse
    early = RawMeta(path=path, width=0, height=0, black_levels=(0.0,) * 4, white_level=0.0, cfa_pattern="", **fields)
    return early, lambda: read_raw(path, exif=fields)


def _validate(metas: list[RawMeta]) -> None:
    """Checks possible before decoding: frame count, exposure metadata, one camera."""
    if len(metas) < 2:
        names = ", ".join(m.path for m in metas) or "(none)"
        raise BracketError(f"a bracket needs at least 2 frames, got {len(metas)}: {names}")
    for m in metas:
        missing = [k for k in ("exposure_s", "f_number", "iso") if not getattr(m, k)]
        if missing:
            raise BracketError(f"{m.path}: no {'/'.join(missing)} in its metadata; cannot place it on the EV100 scale")
    cameras: dict[str, list[str]] = {}
    for m in metas:
        cameras.setdefault(m.camera, []).append(m.path)
    if len(cameras) > 1:
        parts = [f"{cam or '?'}: {', '.join(p)}" for cam, p in cameras.items()]
        raise BracketError("inconsistent bracket (different cameras): " + "; ".join(parts))


def _check_layout(m: RawMeta, ref: RawMeta | None) -> None:
    """Checks of the decoded sensor layout: a usable 2x2 Bayer mosaic, the same as the reference's."""
    if m.cfa_pattern not in BAYER_PATTERNS:
        raise BracketError(f"{m.path}: unsupported CFA {m.cfa_pattern!r}; need a 2x2 RGB Bayer pattern")
    if m.height < 4 or m.width < 4 or not m.white_level > max(m.black_levels):
        raise BracketError(f"{m.path}: unusable layout {m.width}x{m.height}, levels {m.black_levels}/{m.white_level}")
    if ref is not None and (m.width, m.height, m.cfa_pattern) != (ref.width, ref.height, ref.cfa_pattern):
        raise BracketError(f"inconsistent bracket (size or CFA differ): {m.path} is {m.width}x{m.height} "
                           f"{m.cfa_pattern}, {ref.path} is {ref.width}x{ref.height} {ref.cfa_pattern}")  # fmt: skip


def _processing_order(metas: list[RawMeta]) -> tuple[list[int], dict[int, int | None]]:
    """Middle exposure first, then alternately outwards; each frame's already-merged neighbour."""
    ranked = sorted(range(len(metas)), key=lambda i: metas[i].exposure_factor)
    ref = (len(ranked) - 1) // 2
    neighbour = {ranked[k]: None if k == ref else ranked[k + 1 if k < ref else k - 1] for k in range(len(ranked))}
    return [ranked[k] for k in sorted(range(len(ranked)), key=lambda k: (abs(k - ref), k > ref))], neighbour


def _load_signal(loader: Callable, saturation_fraction: float):
    """Decode one frame and compute its :func:`_signal` (runs in a prefetch thread); the signal
    is ``None`` for a layout that :func:`_check_layout` will refuse."""
    m, mosaic = loader()
    if m.cfa_pattern not in BAYER_PATTERNS or min(m.height, m.width) < 4 or not m.white_level > max(m.black_levels):
        return m, None
    return m, _signal(mosaic, m, m.height // 2, m.width // 2, saturation_fraction)


class BracketStart:
    """A bracket whose decoding has begun: metadata read and checked, processing order fixed, and
    its first ``prefetch`` frames submitted to ``pool`` (decoded and normalised there). Made before
    :func:`merge_bracket` consumes it, e.g. while the previous bracket finishes, so that the
    decoder never idles between brackets; at most ``prefetch`` frames wait in memory. A problem
    found here is kept and raised by :func:`merge_bracket`, attributed to this bracket.
    :meth:`when_all_submitted` registers where to start the next bracket."""

    def __init__(self, frames, pool: ThreadPoolExecutor | None, prefetch: int = 2,
                 saturation_fraction: float = 0.95) -> None:
        self.pool, self.prefetch, self.saturation_fraction = pool, max(0, int(prefetch)), saturation_fraction
        self.on_all_submitted: Callable[[], None] | None = None
        self.error: Exception | None = None
        self.pending: list = []
        self.order: list[int] = []
        self.submitted = 0
        try:
            resolved = [_resolve(f) for f in frames]
            self.metas = [m for m, _ in resolved]
            _validate(self.metas)
            known = [m for m in self.metas if m.width]  # RawFrame inputs: check layouts before any work
            for m in known:
                _check_layout(m, known[0])
        except Exception as exc:  # BracketError / RawError: raised by merge_bracket
            self.error = exc
            return
        self.order, self.neighbour = _processing_order(self.metas)
        self.loaders = [partial(_load_signal, ld, saturation_fraction) for _, ld in resolved]
        self.submitted = 0
        if self.pool is not None:
            self._submit_upto(self.prefetch)

    def when_all_submitted(self, callback: Callable[[], None]) -> None:
        """Run ``callback`` once every frame has been submitted (now, if that is already so, or
        if the bracket failed its checks)."""
        if self.error is not None or self.submitted == len(self.order):
            callback()
        else:
            self.on_all_submitted = callback

    def _submit_upto(self, count: int) -> None:
        while self.submitted < min(count, len(self.order)):
            self.pending.append(self.pool.submit(self.loaders[self.order[self.submitted]]))
            self.submitted += 1
            if self.submitted == len(self.order) and self.on_all_submitted is not None:
                self.on_all_submitted()

    def frames(self):
        """Yield (index, (meta, signal)) in processing order, keeping ``prefetch`` frames ahead."""
        if self.pool is None or self.prefetch == 0:
            yield from ((k, self.loaders[k]()) for k in self.order)
            return
        for j, k in enumerate(self.order):
            self._submit_upto(j + 1 + self.prefetch)
            yield k, self.pending.pop(0).result()

    def cancel(self) -> None:
        """Drop frames decoded ahead but not consumed (the merge failed midway)."""
        for future in self.pending:
            future.cancel()
        self.pending.clear()


def _dilate(mask: np.ndarray) -> np.ndarray:
    """3x3 binary dilation with slices."""
    out = mask.copy()
    out[1:] |= mask[:-1]
    out[:-1] |= mask[1:]
    rows = out.copy()
    out[:, 1:] |= rows[:, :-1]
    out[:, :-1] |= rows[:, 1:]
    return out


def _erode2(mask: np.ndarray) -> np.ndarray:
    """Two 3x3 binary erosions, outside the grid counting as False (the smoothing footprint)."""
    bad = ~mask
    bad[:2], bad[-2:], bad[:, :2], bad[:, -2:] = True, True, True, True
    return ~_dilate(_dilate(bad))


def _sample(img: np.ndarray, d) -> np.ndarray:
    """Bilinear ``img(x + d)`` (rows, cols), edges clamped; keeps the dtype."""
    out = img
    for axis, shift in enumerate(d):
        base, n = math.floor(shift), img.shape[axis]
        frac = img.dtype.type(shift - base)
        idx = np.clip(np.arange(n) + base, 0, n - 1)
        low = np.take(out, idx, axis=axis)
        out = low if frac == 0 else low * (1 - frac) + np.take(out, np.minimum(idx + 1, n - 1), axis=axis) * frac
    return out


def _inside(shape, d) -> np.ndarray:
    """Where ``x + d`` lies inside the grid (no clamped extrapolation)."""
    rows, cols = np.arange(shape[0]) + d[0], np.arange(shape[1]) + d[1]
    return ((rows >= 0) & (rows <= shape[0] - 1))[:, None] & ((cols >= 0) & (cols <= shape[1] - 1))[None, :]


def _smooth(img: np.ndarray) -> np.ndarray:
    """Separable [1, 2, 1] / 4 binomial blur, edges clamped."""
    p = np.pad(img, 1, mode="edge")
    v = p[:-2] + 2 * p[1:-1] + p[2:]
    return (v[:, :-2] + 2 * v[:, 1:-1] + v[:, 2:]) * img.dtype.type(1 / 16)


def _window(y: np.ndarray, lo: float, hi: float, size: int = 128) -> tuple[slice, slice]:
    """The (at most) size x size window of quads with the most unclipped texture (every 8th quad)."""
    h, w = y.shape
    if h <= size and w <= size:
        return slice(0, h), slice(0, w)
    k, n = 8, size // 8
    c = np.log(np.clip(np.nan_to_num(y[::k, ::k], nan=lo, posinf=hi), lo, hi))
    g = np.zeros(c.shape)
    g[:-1] += np.abs(np.diff(c, axis=0))
    g[:, :-1] += np.abs(np.diff(c, axis=1))
    s = np.pad(g.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    nh, nw = min(n, c.shape[0]), min(n, c.shape[1])
    box = s[nh:, nw:] - s[:-nh, nw:] - s[nh:, :-nw] + s[:-nh, :-nw]
    i, j = np.unravel_index(int(np.argmax(box)), box.shape)
    y0, x0 = min(i * k, max(h - size, 0)), min(j * k, max(w - size, 0))
    return slice(y0, y0 + min(size, h)), slice(x0, x0 + min(size, w))


def _estimate_shift(ya: np.ndarray, yb: np.ndarray, lo: float, hi: float) -> tuple[float, float] | None:
    """Translation d (rows, cols, quads) with ya(x) ~ yb(x - d), on quad values clipped to [lo, hi].

    In the most textured 128 x 128 window: candidates zero and the three highest peaks of a
    band-limited phase correlation of the log images; the one with the smallest median relative
    difference over the samples valid under every candidate wins (a moving object can out-peak a
    weakly textured background but not move the median; a smooth gradient such as a sun's aureole
    agrees within any loose tolerance at several shifts, so a count of agreeing samples cannot
    rank them). Then trimmed Gauss-Newton
    (Lucas-Kanade) on the linear images over samples strictly inside (lo, hi) in both (quads
    touching a clipped area jump by a whole quad: no sub-pixel cue). Components within 3 standard
    errors of zero become zero; ``None`` when the error exceeds 0.25 quad or under 16 samples overlap.
    """
    crop = _window(ya, lo, hi)
    ya, yb = (np.nan_to_num(v[crop], nan=lo, posinf=hi) for v in (ya, yb))
    a, b = np.clip(ya, lo, hi) / np.float32(hi), np.clip(yb, lo, hi) / np.float32(hi)
    ch, cw = a.shape
    win = np.outer(np.hanning(ch), np.hanning(cw)).astype(np.float32)
    la, lb = np.log(a), np.log(b)
    cross = sfft.rfft2((la - la.mean()) * win) * np.conj(sfft.rfft2((lb - lb.mean()) * win))
    cross /= np.abs(cross) + 1e-12
    fy, fx = np.fft.fftfreq(ch)[:, None], np.fft.rfftfreq(cw)[None, :]
    corr = sfft.irfft2(cross * np.exp(-(fy**2 + fx**2) / (2 * 0.15**2)), s=(ch, cw))
    a, b = _smooth(a), _smooth(b)
    ok_a, ok_b = _erode2((ya > lo) & (ya < hi)), ((yb > lo) & (yb < hi)).astype(np.float32)

    def valid(d, erode: bool = True) -> np.ndarray:
        ok = (_sample(ok_b, -d) > 0.999) & _inside(b.shape, -d)
        return ok_a & (_erode2(ok) if erode else ok)

    candidates = [np.zeros(2)]
    for _ in range(3):
        iy, ix = np.unravel_index(int(np.argmax(corr)), corr.shape)
        candidates.append(np.array([(iy + ch / 2) % ch - ch / 2, (ix + cw / 2) % cw - cw / 2]))
        corr[np.ix_(np.arange(iy - 2, iy + 3) % ch, np.arange(ix - 2, ix + 3) % cw)] = -np.inf
    common = np.logical_and.reduce([valid(d, erode=False) for d in candidates])
    if np.count_nonzero(common) >= 16:  # rank on the same samples: a shift that merely covers more never wins
        def disagreement(d) -> float:
            bw = _sample(b, -d)[common]
            return float(np.median(np.abs(a[common] - bw) / (a[common] + bw + 1e-12)))

        scores = [disagreement(d) for d in candidates]
        start = candidates[int(np.argmin(scores))]  # first (zero) on ties
    else:
        start = candidates[0]
    d, ok = start.copy(), valid(start)
    if np.count_nonzero(ok) < 16:
        return None
    for _ in range(8):  # minimise sum over ok of (a(x) - b(x - d))^2, residuals beyond 3 sigma trimmed
        bw = _sample(b, -d)
        gy, gx = np.gradient(bw)
        r = a - bw
        med = np.median(r[ok])
        sel = (ok & (np.abs(r - med) <= 3 * 1.4826 * np.median(np.abs(r[ok] - med)) + 1e-12)).astype(np.float32)
        gy, gx = gy * sel, gx * sel
        syy, sxx, syx = float((gy * gy).sum()), float((gx * gx).sum()), float((gy * gx).sum())  # no BLAS threads
        syy, sxx = syy + 1e-6 * (syy + sxx) + 1e-12, sxx + 1e-6 * (syy + sxx) + 1e-12
        by, bx = float((gy * r).sum()), float((gx * r).sum())
        step = -np.array([sxx * by - syx * bx, syy * bx - syx * by]) / (syy * sxx - syx * syx)
        d = d + np.clip(step, -0.5, 0.5)
        if np.abs(d - start).max() > 1.0:
            return float(start[0]), float(start[1])  # refinement left the correlation peak: keep the peak
        if np.abs(step).max() < 1e-3:
            break
    sigma2 = float((sel * r * r).sum()) / max(float(sel.sum()) - 2.0, 1.0)
    se = np.sqrt(sigma2 * np.array([sxx, syy]) / (syy * sxx - syx * syx))
    if se.max() > 0.25:
        return None
    d = np.where(np.abs(d) < 3 * se, 0.0, d)
    return float(d[0]), float(d[1])


def _shift_frame(sig: np.ndarray, clipped: np.ndarray, d):
    """Resample each CFA plane at x + d quads (bilinear); returns signal, clipped and inside masks."""
    out = np.empty_like(sig)
    for a, b in ((0, 0), (0, 1), (1, 0), (1, 1)):
        out[a::2, b::2] = _sample(sig[a::2, b::2], d)
    return out, _sample(clipped.astype(np.float32), d) > 1e-3, _inside(clipped.shape, d)


def _signal(mosaic: np.ndarray, m: RawMeta, h: int, w: int, saturation_fraction: float):
    """DN above black (2h, 2w) float32, per-quad clipped flags and quad mean DN (h, w)."""
    mos = mosaic[: 2 * h, : 2 * w]
    sig = mos.astype(np.float32)
    sig.reshape(h, 2, 2 * w)[...] -= np.tile(np.asarray(m.black_levels, np.float32).reshape(2, 2), (1, w))[None]
    rows = mos.reshape(h, 2, 2 * w)
    pair = np.maximum(rows[:, 0], rows[:, 1])
    sat_dn = min(b + saturation_fraction * (m.white_level - b) for b in m.black_levels)
    return sig, np.maximum(pair[:, 0::2], pair[:, 1::2]) >= sat_dn, quad_mean(sig)


def _per_quad(values: np.ndarray) -> np.ndarray:  # (h, w) -> (h, 1, 2w), broadcasts over (h, 2, 2w) mosaic views
    return np.repeat(values, 2, axis=1)[:, None, :]


def _up(quads: np.ndarray) -> np.ndarray:  # (h, w) -> (2h, 2w)
    return np.repeat(np.repeat(quads, 2, axis=0), 2, axis=1)


def merge_bracket(
    frames: Sequence[str | os.PathLike | RawFrame] | BracketStart,
    *,
    noise: NoiseModel = NoiseModel(),
    saturation_fraction: float = 0.95,
    dark_dn: float | None = None,
    align: bool = True,
    min_shift_px: float = 0.25,
    max_shift_px: float = 32.0,
    motion_tolerance: float = 0.05,
    moved_fraction: float = 0.02,
    to_rec709: bool = False,
    prefetch: int | bool = 2,
) -> MergedHDR:
    """Merge RAW files (paths) or :class:`RawFrame` objects of one bracket (conventions above), or a
    :class:`BracketStart` of them (its pool and ``saturation_fraction`` then apply).

    ``dark_dn`` defaults to 4 read-noise sigmas. ``prefetch``: files decoded ahead in threads
    (``True`` = 1, ``False`` = 0: decode in turn). Raises :class:`BracketError` for fewer than two
    frames, frames from different cameras/sizes/CFA patterns or without exposure metadata, and
    :class:`~f2l.io.raw_meta.RawError` for unreadable files; every message names the files.
    """
    if isinstance(frames, BracketStart):
        return _merge_started(frames, noise, frames.saturation_fraction, dark_dn, align, min_shift_px, max_shift_px,
                              motion_tolerance, moved_fraction, to_rec709)  # fmt: skip
    if int(prefetch) <= 0:
        return _merge_started(BracketStart(frames, None, 0, saturation_fraction), noise, saturation_fraction, dark_dn,
                              align, min_shift_px, max_shift_px, motion_tolerance, moved_fraction, to_rec709)
    with ThreadPoolExecutor(max_workers=int(prefetch)) as pool:
        started = BracketStart(frames, pool, int(prefetch), saturation_fraction)
        return _merge_started(started, noise, saturation_fraction, dark_dn, align, min_shift_px, max_shift_px,
                              motion_tolerance, moved_fraction, to_rec709)


def _merge_started(started: BracketStart, noise, saturation_fraction, dark_dn, align, min_shift_px, max_shift_px,
                   motion_tolerance, moved_fraction, to_rec709) -> MergedHDR:
    """:func:`merge_bracket` of a :class:`BracketStart`."""
    if started.error is not None:
        raise started.error
    try:
        return _merge_frames(started, noise, saturation_fraction, dark_dn, align, min_shift_px, max_shift_px,
                             motion_tolerance, moved_fraction, to_rec709)
    finally:
        started.cancel()


def _merge_frames(started: BracketStart, noise, saturation_fraction, dark_dn, align, min_shift_px, max_shift_px,
                  motion_tolerance, moved_fraction, to_rec709) -> MergedHDR:
    metas, order, neighbour = list(started.metas), started.order, started.neighbour
    factors = [m.exposure_factor for m in metas]
    ref_i, short_i, long_i = order[0], int(np.argmin(factors)), int(np.argmax(factors))
    e_ref, dark = factors[ref_i], (4.0 * noise.read_noise_dn if dark_dn is None else float(dark_dn))
    quads: dict[int, np.ndarray] = {}  # aligned quad estimates of x, for the motion check
    unshifted: dict[int, np.ndarray] = {}  # as recorded, to align the next frames
    shift_q: dict[int, tuple[float, float]] = {}  # shift relative to the reference, quads
    infos = [FrameInfo(m.path, m.exposure_s, m.f_number, m.iso, m.exposure_factor, m.ev100) for m in metas]
    warnings: list[str] = []
    for i, (m, signal) in started.frames():
        _check_layout(m, None if i == ref_i else metas[ref_i])
        metas[i], info = m, infos[i]
        if i == ref_i:
            h, w = m.height // 2, m.width // 2
            num, den = np.zeros((2 * h, 2 * w), np.float32), np.zeros((h, w), np.float32)
            wmax, dominant, sat_all = np.zeros((h, w), np.float32), np.full((h, w), -1, np.int16), np.ones((h, w), bool)
        e, span = m.exposure_factor, m.white_level - float(np.mean(m.black_levels))
        sig, clipped, qdn = signal
        del signal
        y = qdn * np.float32(1.0 / (span * e))
        y[clipped] = np.inf
        inside, unshifted[i], shift_q[i] = None, y, (0.0, 0.0)
        if neighbour[i] is not None and align:
            nb = metas[neighbour[i]]
            lo = 10.0 * dark / span / min(e, nb.exposure_factor)  # SNR of about 20 in the shorter frame
            hi = saturation_fraction * 0.9 / max(e, nb.exposure_factor)
            d = _estimate_shift(y, unshifted[neighbour[i]], lo, hi) if lo < hi / 4 else None
            if d is not None:  # compose with the neighbour's own shift relative to the reference
                d = (d[0] + shift_q[neighbour[i]][0], d[1] + shift_q[neighbour[i]][1])
            info.shift_px = None if d is None else (2 * d[0], 2 * d[1])
            if d is not None and max(abs(d[0]), abs(d[1])) * 2 > max_shift_px:
                warnings.append(f"{m.path}: shift ({2 * d[0]:.1f}, {2 * d[1]:.1f}) px exceeds {max_shift_px:g} px; "
                                "merged as recorded")  # fmt: skip
            elif d is not None:
                shift_q[i] = d
                if max(abs(d[0]), abs(d[1])) * 2 >= min_shift_px:
                    sig, clipped, inside = _shift_frame(sig, clipped, d)
                    info.aligned, qdn = True, quad_mean(sig)
                    y = qdn * np.float32(1.0 / (span * e))
                    y[clipped], y[~inside] = np.inf, np.nan
        quads[i] = y
        sat_all &= clipped if inside is None else (clipped | ~inside)
        invalid = clipped if i == long_i else clipped | (qdn < dark)
        invalid = invalid if inside is None else invalid | ~inside
        var = np.maximum(qdn, 0) * np.float32(m.iso / 100.0 / noise.full_well_e / span)
        wq = np.float32((e / e_ref) ** 2) / (var + np.float32(max((noise.read_noise_dn / span) ** 2, 1e-12)))
        wq[invalid] = 0
        if i == short_i:  # for quads no frame can weight: clipped samples at exactly 1 / e
            fallback = sig * np.float32(1.0 / (span * e))
            fallback[_up(clipped) & (fallback >= saturation_fraction / e)] = 1.0 / e
        rows = sig.reshape(h, 2, 2 * w)
        np.multiply(rows, _per_quad(wq * np.float32(1.0 / (span * e))), out=rows)
        num += sig
        den += wq
        np.putmask(dominant, wq > wmax, i)
        np.maximum(wmax, wq, out=wmax)
        info.used_fraction = float(np.count_nonzero(wq)) / wq.size
        del sig, rows
    zero = den == 0
    rows = num.reshape(h, 2, 2 * w)
    np.divide(rows, _per_quad(np.where(zero, np.float32(1), den)), out=rows)
    if zero.any():
        num[_up(zero)] = fallback[_up(zero)]
    del fallback
    np.maximum(num, 0, out=num)
    merged_var = np.float32(0.25 / e_ref**2) / np.where(zero, np.float32(1), den)  # variance of the quad mean
    _motion(metas, infos, quads, quad_mean(num), merged_var, zero, dark, noise, motion_tolerance, moved_fraction)
    quads.clear(), unshifted.clear()  # before the demosaic: peak memory is then the result plus a mosaic
    rgb, cfa = None, metas[ref_i].cfa_pattern  # demosaiced on first use of MergedHDR.rgb
    saturated = _dilate(_up(sat_all & zero))
    counts = np.bincount(dominant.ravel() + 1, minlength=len(metas) + 1)[1:]
    for i, info in enumerate(infos):
        info.dominant_fraction = float(counts[i]) / dominant.size
        info.status = "moved" if info.moved else ("reference" if i == ref_i else "ok")
        if info.moved:
            warnings.append(f"{info.name}: {100 * info.inconsistent_fraction:.1f}% of well-exposed quads disagree "
                            "with the merge (motion?); frame still merged")  # fmt: skip
    if saturated.any():
        warnings.append(f"{100 * saturated.mean():.3f}% of pixels saturated in every frame; they hold the lower "
                        f"bound 1/e_min = {1 / factors[short_i]:.6g}")  # fmt: skip
    space = "camera"
    if to_rec709 and metas[ref_i].xyz_to_camera is None:
        warnings.append(f"{metas[ref_i].path}: no colour matrix; result left in camera RGB")
    elif to_rec709:
        rgb, space = camera_to_rec709(demosaic_bilinear(num, cfa), metas[ref_i].xyz_to_camera), "rec709"
    return MergedHDR(
        rgb_cache=rgb, mosaic=num, saturated=saturated, saturated_fraction=float(saturated.mean()), cfa_pattern=cfa,
        colour_space=space, min_exposure_factor=factors[short_i], reference=metas[ref_i].path, frames=infos,
        status="moved" if any(f.moved for f in infos) else "ok", warnings=warnings,
        xyz_to_camera=metas[ref_i].xyz_to_camera,
    )  # fmt: skip


def _motion(metas, infos, quads, merged_q, merged_var, zero, dark, noise, tolerance, moved_fraction) -> None:
    """Compare each frame's aligned quad estimate with the merged one: allowed difference is 4 sigma
    (noise of both) + ``tolerance`` (relative) + half a quad of misregistration times the gradient."""
    gy, gx = np.gradient(merged_q)
    sub = (slice(None, None, 2), slice(None, None, 2))  # every other quad each way: a fraction, 4x cheaper
    slack = (0.5 * (np.abs(gy) + np.abs(gx)) + np.float32(tolerance) * merged_q)[sub]
    merged_q, merged_var, zero = merged_q[sub], merged_var[sub], zero[sub]
    for i, (m, info) in enumerate(zip(metas, infos)):
        y, e, span = quads[i][sub], m.exposure_factor, m.white_level - float(np.mean(m.black_levels))
        with np.errstate(invalid="ignore"):
            well = (y >= 2.0 * dark / (span * e)) & (y < np.inf) & ~zero  # NaN (outside) and inf (clipped) fail
            excess = np.abs(y - merged_q)
            excess -= slack
            var = y * np.float32(m.iso / (400.0 * noise.full_well_e * span * e))  # quad-mean variance of y
            var += merged_var + np.float32((noise.read_noise_dn / span) ** 2 / (4.0 * e * e))
            bad = well & (excess > 0) & (excess * excess > 16.0 * var)
        count = int(np.count_nonzero(well))
        info.inconsistent_fraction = float(np.count_nonzero(bad)) / count if count else 0.0
        info.moved = info.inconsistent_fraction > moved_fraction
