"""Streamed decoding of large JPEG, PNG and TIFF photos (:class:`StreamedPhoto`).

A photo whose long side exceeds ``f2l.io.photo.DETECTION_MAX_SIDE`` is never held whole: faces
are detected on a reduced decode (JPEG: libjpeg's DCT scaling through ``Image.draft``; PNG:
Pillow's own decoder run row block by row block into an anonymous mapping whose finished rows are
box-reduced and released; TIFF: strips or tiles one band at a time, or direct row reads when
uncompressed), and face fitting reads only the full-resolution window around each face. Details,
limits and measurements: :mod:`f2l.io.photo` and ``docs/large_photos.md``.
"""

from __future__ import annotations

import contextlib
import math
import mmap
import struct
import sys
import zlib
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from f2l.io.photo.core import Photo, PhotoError, _BoxReducer, _box_factor, _code_planes, _no_pillow_bomb_guard, _orient
from f2l.io.photo.exif import _pillow_metadata
from f2l.io.photo.metadata import PhotoMetadata


# JPEG/PNG input is handed to Pillow's decoder in pieces of this size; between pieces the rows it
# has finished are consumed and their memory released. Deflate expands at most 1,032-fold (JPEG
# less), ~1,400-fold into Pillow's 4-byte pixels: the rows in flight stay within ~25 MB.
STREAM_CHUNK_BYTES = 16384
# Pillow modes streamed, with their bytes per pixel in Pillow's image memory.
_STREAM_MODES = {"RGB": 4, "RGBA": 4, "LA": 4, "L": 1, "P": 1, "I;16": 2}
_STREAM_DECODE_ERRORS = (OSError, SyntaxError, ValueError, EOFError, IndexError, struct.error, zlib.error)
# Streaming JPEG/PNG needs anonymous private mappings whose pages can be given back (madvise).
_CAN_STREAM_PILLOW = (sys.platform.startswith("linux") and hasattr(mmap, "MAP_ANONYMOUS")
                      and hasattr(mmap, "MADV_DONTNEED") and hasattr(mmap.mmap, "madvise"))


class _StreamUnavailable(Exception):
    """This photo cannot be streamed here: decode it whole."""


class _StopDecode(Exception):
    """The rows that were asked for have been read."""


class _Window:
    """Collects rows ``r0:r1``, columns ``c0:c1`` of rows fed in order."""

    def __init__(self, r0: int, r1: int, c0: int, c1: int):
        self.r0, self.r1, self.c0, self.c1 = r0, r1, c0, c1
        self.out: np.ndarray | None = None

    def __call__(self, start: int, codes: np.ndarray) -> None:
        lo, hi = max(start, self.r0), min(start + len(codes), self.r1)
        if hi <= lo:
            return
        if self.out is None:
            self.out = np.zeros((self.r1 - self.r0, self.c1 - self.c0, 3), codes.dtype)
        self.out[lo - self.r0 : hi - self.r0] = codes[lo - start : hi - start, self.c0 : self.c1]


class _ReduceTo:
    """A consumer box-reducing a stored image to a long side <= ``max_side`` (:class:`_BoxReducer`
    from the top-left corner); its size (and a decoder's own scale) is told by ``begin``."""

    def __init__(self, max_side: int):
        self.max_side = int(max_side)

    def begin(self, width: int, height: int, scale: int = 1) -> None:
        self.scale, self.f = scale, _box_factor(height, width, self.max_side)
        self.reducer = _BoxReducer(self.f, (0, 0), (height // self.f, width // self.f))

    def __call__(self, r0: int, codes: np.ndarray) -> None:
        self.reducer(r0, codes)

    def result(self) -> _Reduced:
        return _Reduced(self.reducer.out, self.scale * self.f, self.max_side)


@dataclass
class _Reduced:
    """A reduced copy in the stored frame: pixel j covers stored pixels [j f, (j + 1) f)."""

    image: np.ndarray  # (m_rows, m_cols, 3) uint8
    factor: int
    max_side: int


def _oriented_axes(orientation: int) -> tuple[tuple[int, bool], tuple[int, bool]]:
    """For the oriented rows and columns: (the stored axis they run along, reversed or not)."""
    probe = _orient(np.arange(6).reshape(2, 3), orientation)
    origin, down, right = (divmod(int(v), 3) for v in (probe[0, 0], probe[1, 0], probe[0, 1]))
    row_axis = 0 if down[0] != origin[0] else 1
    return ((row_axis, down[row_axis] < origin[row_axis]),
            (1 - row_axis, right[1 - row_axis] < origin[1 - row_axis]))


def _palette_lut(im) -> np.ndarray:
    """(256, 3) uint8 RGB of a P image's palette, read without loading the image."""
    rawmode, data = im.palette.getdata()
    if rawmode not in ("RGB", "RGBA", "RGBX"):
        raise _StreamUnavailable(f"palette mode {rawmode}")
    pal = np.frombuffer(data, np.uint8)
    pal = pal[: len(pal) // len(rawmode) * len(rawmode)].reshape(-1, len(rawmode))[:256, :3]
    lut = np.zeros((256, 3), np.uint8)
    lut[: len(pal)] = pal
    return lut


def _pillow_rows_rgb(raw: np.ndarray, mode: str, width: int, lut) -> np.ndarray:
    """(n, W, 3) codes of rows of Pillow's image memory (a view for the 4-byte modes)."""
    n = len(raw)
    if _STREAM_MODES[mode] == 4:  # RGB(X), RGBA and LA (stored L, L, L, A): the first three bytes
        return raw.reshape(n, width, 4)[..., :3]
    if mode == "P":
        return lut[raw]
    grey = raw.view("<u2").astype(np.uint16) if mode == "I;16" else raw
    return np.repeat(grey[..., None], 3, axis=-1)


def _pillow_scan(path: str, consume, stop: int | None = None, draft: int | None = None,
                 want_tags: bool = False) -> PhotoMetadata | None:
    """Decode a JPEG or PNG with Pillow's own decoder, row block by row block.

    The decoder writes into an anonymous private mapping of the image's size, fed
    ``STREAM_CHUNK_BYTES`` of input at a time; between pieces, the rows it has finished are
    passed to ``consume(first_row, codes)`` ((n, W, 3) uint8/uint16, stored frame, valid during
    the call) and their pages given back, so only the rows in flight are ever resident. A row is
    finished once a later one has been written (rows are written whole and in order): the RGB
    unpacker sets every pixel's fourth byte to 255 on fresh (zero) pages, and other modes get a
    pseudo-random 4-byte guard at the end of each row first (data equal to the guard only delays
    a row). Stops after row ``stop``. ``draft`` (JPEG): decode at 1/draft scale (libjpeg's DCT
    scaling). ``consume.begin(width, height, scale)`` is called first when it exists. Returns the
    metadata (``want_tags``: read after decoding; a PNG may keep its EXIF after the pixels)."""
    from PIL import Image

    with _no_pillow_bomb_guard(), Image.open(path) as im:
        if draft:
            im.draft(im.mode, (im.size[0] // draft, im.size[1] // draft))
        mode, (w, h) = im.mode, im.size
        if (mode not in _STREAM_MODES or len(im.tile) != 1 or im.info.get("interlace")
                or getattr(im, "is_animated", False) or not _CAN_STREAM_PILLOW):
            raise _StreamUnavailable(f"{im.format} {mode}")
        stride = w * _STREAM_MODES[mode]
        try:
            lut = _palette_lut(im) if mode == "P" else None
            flags = mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | getattr(mmap, "MAP_NORESERVE", 0)
            mm = mmap.mmap(-1, stride * h, flags=flags)  # address space; pages only as written
            im.im = Image.core.map_buffer(mm, (w, h), "raw", 0, (mode, stride, 1))
        except (AttributeError, TypeError, ValueError, OSError) as e:
            raise _StreamUnavailable(str(e)) from e
        if hasattr(consume, "begin"):
            consume.begin(w, h, im.decoderconfig[0] if draft and im.decoderconfig else 1)
        raw = np.frombuffer(mm, np.uint8).reshape(h, stride)
        tail = raw[:, stride - 4 :]
        if mode == "RGB":
            guard = None
        else:
            guard = np.random.default_rng(h).integers(0, 256, size=(h, 4), dtype=np.uint8)
            tail[:] = guard
        done = 0

        def written(r: int) -> bool:
            return bool(tail[r, 3]) if guard is None else bool((tail[r] != guard[r]).any())

        def frontier() -> int:  # first row not known to be finished
            if done >= h or not written(done):
                return done
            lo, step = done, 1
            while True:
                hi = lo + step
                if hi >= h:
                    hi = h
                    break
                if not written(hi):
                    break
                lo, step = hi, step * 2
            while hi - lo > 1:
                mid = (lo + hi) // 2
                lo, hi = (mid, hi) if written(mid) else (lo, mid)
            return lo  # the last written row may still be in the decoder's hands: not yet

        def flush(final: bool = False) -> None:
            nonlocal done
            end = h if final else frontier()
            if end > done:
                consume(done, _pillow_rows_rgb(raw[done:end], mode, w, lut))
                a = done * stride // mmap.PAGESIZE * mmap.PAGESIZE
                b = len(mm) if final else end * stride // mmap.PAGESIZE * mmap.PAGESIZE
                if b > a:
                    mm.madvise(mmap.MADV_DONTNEED, a, b - a)
                done = end
            if stop is not None and done >= stop:
                raise _StopDecode

        read = im.load_read if hasattr(im, "load_read") else im.fp.read

        def load_read(n: int) -> bytes:
            flush()
            return read(n)

        im.load_read = load_read
        im.decodermaxblock = STREAM_CHUNK_BYTES
        tags = None
        try:
            try:
                im.load()
                flush(final=True)
            except _StopDecode:
                pass
            except _STREAM_DECODE_ERRORS as e:
                raise PhotoError(path, f"truncated or corrupt {im.format} ({e})") from e
            if want_tags:
                tags = _pillow_metadata(im)
        finally:
            del raw, tail
            im.close()  # releases Pillow's view of the mapping
            with contextlib.suppress(BufferError):
                mm.close()
    return tags


class _PillowSource:
    """A streamed JPEG or PNG (:func:`_pillow_scan`)."""

    def __init__(self, path: str, kind: str):
        self.path, self.kind = path, kind

    def reduce(self, max_side: int) -> tuple[_Reduced, PhotoMetadata | None]:
        """The reduced copy (JPEG: libjpeg's DCT scaling by the power of two <= 8 that brings the
        long side nearest to ``max_side``, then a box; PNG: a box over every row) and the metadata."""
        draft = None
        if self.kind == "jpeg":
            from PIL import Image

            with _no_pillow_bomb_guard(), Image.open(self.path) as im:
                f = _box_factor(im.size[1], im.size[0], max_side)
            draft = next((s for s in (2, 4) if s >= f), 8) if f > 1 else None
        reducer = _ReduceTo(max_side)
        tags = _pillow_scan(self.path, reducer, draft=draft, want_tags=True)
        return reducer.result(), tags

    def scan(self, consume, start: int = 0, stop: int | None = None) -> None:
        _pillow_scan(self.path, consume, stop=stop)


class _TiffSource:
    """A streamed 8/16-bit integer TIFF: rows read directly when the data is uncompressed and
    contiguous, otherwise one band of strips or tiles (all planes) decoded at a time."""

    def __init__(self, path: str):
        self.path = path

    def reduce(self, max_side: int) -> tuple[_Reduced, PhotoMetadata | None]:
        import tifffile

        with tifffile.TiffFile(self.path) as tf:
            page = tf.pages[0]
            width, height = int(page.imagewidth), int(page.imagelength)
        reducer = _ReduceTo(max_side)
        reducer.begin(width, height)
        self.scan(reducer)
        return reducer.result(), None

    def scan(self, consume, start: int = 0, stop: int | None = None) -> None:
        import tifffile

        with tifffile.TiffFile(self.path) as tf:
            page, fh = tf.pages[0], tf.filehandle
            h, w, spp = int(page.imagelength), int(page.imagewidth), int(page.samplesperpixel)
            stop = h if stop is None else min(int(stop), h)
            dtype = np.dtype(page.dtype).newbyteorder(tf.byteorder)
            if page.is_contiguous and (page.planarconfig == 1 or spp == 1):
                row_bytes = w * spp * dtype.itemsize
                step = max(1, (1 << 24) // row_bytes)
                for r0 in range(start, stop, step):
                    n = min(step, stop - r0)
                    fh.seek(page.dataoffsets[0] + r0 * row_bytes)
                    data = fh.read(n * row_bytes)
                    if len(data) < n * row_bytes:
                        raise PhotoError(self.path, "truncated TIFF (image data runs past the end of the file)")
                    consume(r0, _tiff_rgb(np.frombuffer(data, dtype).reshape(n, w, spp)))
                return
            band = int(page.tilelength if page.is_tiled else min(page.rowsperstrip, h))
            planes = spp if page.planarconfig == 2 and spp > 1 else 1
            bands, across = math.ceil(h / band), (math.ceil(w / page.tilewidth) if page.is_tiled else 1)
            if len(page.dataoffsets) != planes * bands * across:
                raise _StreamUnavailable("unexpected segment layout")
            args = {"_fullsize": bool(page.is_tiled)}
            if page.compression in (6, 7, 34892, 33007):  # JPEG
                args.update(jpegtables=page.jpegtables, jpegheader=page.jpegheader)
            for b in range(start // band, math.ceil(stop / band)):
                r0 = b * band
                n = min(band, h - r0)
                rows = np.zeros((n, w, spp), dtype.newbyteorder("="))
                for p in range(planes):
                    for t in range(across):
                        index = (p * bands + b) * across + t
                        if not page.databytecounts[index]:
                            continue
                        fh.seek(page.dataoffsets[index])
                        segment, at, _ = page.decode(fh.read(page.databytecounts[index]), index, **args)
                        if segment is None:
                            continue
                        c0 = int(at[3])
                        seg = segment[0, :n, : w - c0]
                        rows[:, c0 : c0 + seg.shape[1], p : p + seg.shape[2]] = seg
                consume(r0, _tiff_rgb(rows))


def _tiff_rgb(arr: np.ndarray) -> np.ndarray:
    """(n, W, 3) native-order codes of (n, W, S) TIFF samples, as :func:`_from_array` takes them."""
    arr = arr.astype(arr.dtype.newbyteorder("="), copy=False)
    return arr[..., :3] if arr.shape[-1] >= 3 else np.repeat(arr[..., :1], 3, axis=-1)


class StreamedPhoto:
    """A large photo read on demand (module docstring): what face fitting uses of :class:`Photo`
    (``shape``, :meth:`detection_image`, :meth:`rows`, the camera fields) without holding the
    photo; its whole-image arrays decode it whole on first use."""

    def __init__(self, path: str, kind: str, source, stored_shape: tuple[int, int], orientation: int,
                 reduced: _Reduced, whole):
        self.path, self.kind, self.orientation = path, kind, orientation
        self._source, self._stored_shape, self._reduced, self._whole_loader = source, stored_shape, reduced, whole
        self._windows: dict = {}
        self.focal_px, self.focal_source, self.exif = 0.0, "default", {}

    @property
    def shape(self) -> tuple[int, int]:
        (row_axis, _), _ = _oriented_axes(self.orientation)
        h, w = self._stored_shape
        return (h, w) if row_axis == 0 else (w, h)

    def detection_image(self, max_side: int) -> tuple[np.ndarray, float, tuple[float, float]]:
        """As :meth:`Photo.detection_image`; the reduction runs in the stored frame from its
        top-left corner, so with a flipped orientation (and for JPEG's DCT scaling, whose last
        block may be partial) the offset is not zero."""
        if self._reduced.max_side != int(max_side):
            self._reduced = self._source.reduce(max_side)[0]
        red = self._reduced
        offset = []
        for axis, flipped in _oriented_axes(self.orientation):
            n, m = self._stored_shape[axis], red.image.shape[axis]
            offset.append(float(n - red.factor * m) if flipped else 0.0)
        return _orient(red.image, self.orientation), 1.0 / red.factor, (offset[1], offset[0])

    def rows(self, index: np.ndarray, cols: slice = slice(None)) -> dict:
        """As :meth:`Photo.rows`: reads the full-resolution window spanning the rows and columns
        asked for (one pass over the file, unless :meth:`prefetch` read it)."""
        index = np.asarray(index, np.int64)
        h, w = self.shape
        col_index = np.arange(w)[cols]
        if len(index) == 0 or len(col_index) == 0:
            return _code_planes(np.zeros((len(index), len(col_index), 3), np.uint8))
        box = (int(index.min()), int(index.max()) + 1, int(col_index.min()), int(col_index.max()) + 1)
        held = self._holding(box)
        if held is None:
            self.prefetch([box])
            held = box
        return _code_planes(self._windows[held][index - held[0]][:, col_index - held[2]])

    def _holding(self, box) -> tuple | None:
        """The key of a window read before that contains ``box`` (r0, r1, c0, c1), or None."""
        r0, r1, c0, c1 = box
        for key in self._windows:
            if key[0] <= r0 and r1 <= key[1] and key[2] <= c0 and c1 <= key[3]:
                return key
        return None

    def ensure_window(self, box) -> None:
        """Read the window ``box`` unless a window read before contains it (the faces of a photo
        are prefetched in one pass; a single face's window is read here, once)."""
        if self._holding(tuple(int(v) for v in box)) is None:
            self.prefetch([box])

    def prefetch(self, boxes) -> None:
        """Read the full-resolution windows ``(r0, r1, c0, c1)`` (oriented rows and columns) in one
        pass over the file, replacing those read before."""
        self._windows = {}
        boxes = list(dict.fromkeys(tuple(int(v) for v in box) for box in boxes))
        if not boxes:
            return
        windows = [_Window(*self._stored_box(*box)) for box in boxes]

        def consume(start: int, codes: np.ndarray) -> None:
            for window in windows:
                window(start, codes)

        self._source.scan(consume, start=min(w.r0 for w in windows), stop=max(w.r1 for w in windows))
        for box, window in zip(boxes, windows):
            if window.out is None:
                raise PhotoError(self.path, f"rows {window.r0}..{window.r1} could not be read")
            self._windows[box] = _orient(window.out, self.orientation)

    def _stored_box(self, r0: int, r1: int, c0: int, c1: int) -> tuple[int, int, int, int]:
        """The stored-frame rows and columns of an oriented window."""
        stored = [(0, 0), (0, 0)]
        for (axis, flipped), (a, b) in zip(_oriented_axes(self.orientation), ((r0, r1), (c0, c1))):
            n = self._stored_shape[axis]
            stored[axis] = (n - b, n - a) if flipped else (a, b)
        return (*stored[0], *stored[1])

    @cached_property
    def whole(self) -> Photo:
        """The photo decoded whole (:class:`Photo`), for callers that need every pixel."""
        return self._whole_loader()

    codes = property(lambda self: self.whole.codes)
    masks = property(lambda self: self.whole.masks)
    linear = property(lambda self: self.whole.linear)
    display = property(lambda self: self.whole.display)
    clipped = property(lambda self: self.whole.clipped)
    black = property(lambda self: self.whole.black)
