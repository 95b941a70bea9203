"""``f2l ingest DIR``: a capture tree → ``captures.parquet`` (schema ``captures``).

What a row says about a file, and how it is decided:

* **kind** from the extension: camera RAW (anything LibRaw opens: CR2, CR3, NEF, ARW, DNG, ...),
  ``image`` (JPEG/PNG/TIFF) or ``hdr`` (an already-merged probe: EXR, Radiance ``.hdr``, PFM).
* **metadata**: EXIF of RAW and images through the one reader, :mod:`f2l.io.photo.metadata`
  (same conventions for both: ``timestamp_utc`` is its ``camera_time``, with sub-seconds and
  timezone-aware only when the file records a usable offset; GPS where the file has a usable
  position). RAW through :func:`f2l.io.raw_meta.read_raw_metadata` (levels and CFA from the tags
  of a DNG that states them completely, else one LibRaw decode, because LibRaw reports
  black/white levels and the CFA only after unpacking: a Canon's black level is measured on
  masked pixels); images through :func:`~f2l.io.photo.metadata.read_metadata` (its exifread
  backend: Pillow's EXIF of a PNG decodes the pixels, so a truncated PNG would fail) and Pillow's
  header, EXR through OpenEXR's header, ``.hdr`` through its text header (no pixel decode).
* **session** (one site): each top-level sub-folder of DIR is a session; files directly in DIR
  are split into sessions where consecutive capture times are more than ``session_gap_min``
  apart (capture time from EXIF, else the file's mtime).
* **role**: a folder name on the path inside the session (:data:`ROLE_FOLDERS`, e.g. ``sky/``,
  ``faces/``, ``chart/``, ``probes/``), else the session TOML's ``shots[].role``, else detected:
  ``hdr`` files are probes; frames of the same camera, lens, size and focal length taken within
  ``bracket_gap_s`` of each other with stepped exposures (``t·ISO/N²`` differing) form a
  sky bracket; otherwise a face when the face detector fires on a small preview (the RAW's
  embedded thumbnail, or the image itself), a chart when the chart detector does, else
  ``other``.
* **brackets**: frames of one bracket share ``bracket_id`` (``<session>/<first frame stem>``).
  A bracket never mixes views: frames within ``bracket_gap_s`` of each other are split where the
  session TOML's view (orientation, lens) changes, where an exposure repeats (the sequence
  restarted) and where the capture time jumps (:func:`split_brackets`), so a panoramic head's
  views in one folder become one bracket each.
  In a bracket folder, a run of one frame is ``skipped`` (nothing to merge) and a run that mixes
  cameras or frame sizes is an ``error`` naming both; the rest of the folder is unaffected.
* **session TOML** (``session.toml`` in the session folder, schema ``session``): lens
  (:mod:`f2l.capture.lens`), fall-off, per-shot yaw/pitch/roll and role, probe azimuth; parsed
  and validated once per file into a :class:`~f2l.capture.view_spec.ViewSpec`, stored per row in
  ``view_json`` (a flat-field file as a path relative to the capture root, with its SHA-256). An
  invalid TOML is reported, with its file and key, in the summary (``session_problems``, printed
  by the CLI) and in ``session_problem`` of every row of its session, which is then ingested
  without it. The TOML is read with bounds (:func:`f2l.io.bounded.load_toml`: at most 16 MiB,
  nesting 32 deep, strings of 65,536 characters, no NaN or infinite number), so a hostile file is
  a session problem too, never a crash.
* **hostile input** (each is reported, naming the file and the key, and the rest of the tree is
  ingested):

  - a sky frame whose lens cannot place its view (:func:`f2l.capture.lens.lens_of`:
    missing, inconsistent or implausible values, e.g. a focal length of 1e308 px or a principal
    point far outside the frame) is an ``error`` row, checked on the frame's own size;
  - a file named in the session TOML (a flat field's ``file``) must stay inside the session
    folder: an absolute path, a path with ``..`` that leaves it, or a symlink (the file or a
    folder above it) that resolves outside it makes the rows that use it ``error`` rows and is
    never opened, unless the user passes ``--allow-outside``; a missing or unreadable flat field
    is an ``error`` too. The flat-field file itself gets role ``other`` (role source ``toml``),
    never ``probe``;
  - a ``[[shots]]`` ``files`` glob that matches no file of the session is a warning
    (``warnings`` in the summary, printed by the CLI): the frames it meant get no orientation;
  - a file whose name is not valid UTF-8 is an ``error`` row whose path is the name with the
    undecodable bytes escaped (``\\xff``); it is never opened (rename it to ingest it);
  - a file that cannot be stat'ed (a dangling symlink, a symlink loop) is an ``error`` row;
  - a capture file that is a symbolic link pointing outside the capture tree is an ``error`` row
    naming the link and its target ("symlink points outside the capture tree"), never opened,
    unless the user passes ``--allow-outside``; links within the tree are read as usual. A
    symbolic link to a folder is never descended (:func:`scan`); one that points outside the
    tree is a warning.

Incremental: ``WORK/captures.parquet`` from an earlier run is read first; a file whose relative
path, size and mtime (ns) match a row written by the same :data:`INGEST_VERSION` is not opened
again (no hashing, no decoding, no detection); any change re-reads it. Sessions and brackets are
recomputed from the rows every time (cheap). The table is written atomically.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from f2l.capture.session_toml import outside_target
from f2l.io.photo.metadata import read_metadata

INGEST_VERSION = 3  # 2: session_problem column, brackets split by view, exposure restart and time jump;
# 3: images' EXIF through f2l.io.photo.metadata (sub-seconds, offset and GPS as for RAW)
RAW_EXTENSIONS = {".3fr", ".arw", ".cr2", ".cr3", ".crw", ".dcr", ".dng", ".erf", ".iiq", ".k25",
                  ".kdc", ".mef", ".mos", ".mrw", ".nef", ".nrw", ".orf", ".pef", ".raf", ".raw",
                  ".rw2", ".rwl", ".sr2", ".srf", ".srw", ".x3f"}
IMAGE_EXTENSIONS = {".jpg", ".jpeg", ".png", ".tif", ".tiff"}
HDR_EXTENSIONS = {".exr", ".hdr", ".pfm"}
ROLE_FOLDERS = {  # folder name (lower case) -> role
    **dict.fromkeys(["sky", "skies", "bracket", "brackets", "hdr", "sphere", "spheres", "fisheye",
                     "env", "environment"], "sky_bracket"),
    **dict.fromkeys(["face", "faces", "people", "person", "persons", "portrait", "portraits",
                     "subjects"], "face"),
    **dict.fromkeys(["chart", "charts", "colorchecker", "colourchecker", "calibration", "calib"],
                    "chart"),
    **dict.fromkeys(["probe", "probes", "merged", "lightprobes"], "probe"),
}


@dataclass
class IngestSummary:
    root: str
    table: str
    files: int = 0
    read: int = 0
    reused: int = 0
    by_status: dict = field(default_factory=dict)
    by_role: dict = field(default_factory=dict)
    sessions: int = 0
    brackets: int = 0
    session_problems: list = field(default_factory=list)  # "session: why its session.toml was not used"
    warnings: list = field(default_factory=list)  # "session: what in its session.toml did not apply"
    bracket_list: list = field(default_factory=list)  # one dict per bracket (bracket_summary)

    def to_json(self) -> dict:
        return dict(self.__dict__)


# -- scanning ------------------------------------------------------------------------------------
def kind_of(path: Path) -> str | None:
    ext = path.suffix.lower()
    if ext in RAW_EXTENSIONS:
        return "raw"
    if ext in IMAGE_EXTENSIONS:
        return "image"
    if ext in HDR_EXTENSIONS:
        return "hdr"
    return None


def scan(root: Path, linked_out: list | None = None) -> list[Path]:
    """Capture files under ``root`` (recursive, sorted, hidden files and folders skipped).

    A symbolic link to a folder is never descended (a link out of the tree is not read, a link
    loop is not walked); ``linked_out`` receives (link, resolved target) of each such link that
    points outside ``root``, for a warning. A symbolic link to a file is listed like a file
    (:func:`outside_target` says whether it leaves the tree)."""
    out = []
    base = os.path.realpath(root)
    for dirpath, dirnames, filenames in os.walk(root):  # followlinks=False: folder links not walked
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        if linked_out is not None:
            for d in dirnames:
                p = Path(dirpath) / d
                target = outside_target(base, p) if os.path.islink(p) else None
                if target is not None:
                    linked_out.append((p, target))
        for name in sorted(filenames):
            p = Path(dirpath) / name
            if not name.startswith(".") and kind_of(p) is not None:
                out.append(p)
    return out


# -- metadata per kind ---------------------------------------------------------------------------
def _empty_meta() -> dict:
    return {"camera": "", "lens": None, "width": None, "height": None, "exposure_s": None,
            "f_number": None, "iso": None, "ev100": None, "timestamp_utc": None,
            "focal_length_mm": None, "orientation": 1, "gps_latitude_deg": None,
            "gps_longitude_deg": None, "gps_altitude_m": None, "black_levels": [],
            "white_level": None, "cfa_pattern": None}


def _ev100(exposure_s, f_number, iso):
    if not (exposure_s and f_number and iso):
        return None
    return math.log2(f_number**2 / exposure_s) - math.log2(iso / 100.0)


def _raw_meta(path: Path) -> dict:
    from f2l.io.raw_meta import read_raw_metadata

    m = read_raw_metadata(path)
    out = _empty_meta()
    out.update(camera=m.camera, lens=m.lens, width=m.width, height=m.height,
               exposure_s=m.exposure_s, f_number=m.f_number, iso=m.iso,
               ev100=_ev100(m.exposure_s, m.f_number, m.iso),
               timestamp_utc=m.timestamp.isoformat() if m.timestamp else None,
               focal_length_mm=m.focal_length_mm, orientation=int(m.orientation or 1),
               gps_latitude_deg=m.gps_latitude_deg, gps_longitude_deg=m.gps_longitude_deg,
               gps_altitude_m=m.gps_altitude_m, black_levels=[float(b) for b in m.black_levels],
               white_level=float(m.white_level), cfa_pattern=m.cfa_pattern)
    return out


def _image_meta(path: Path) -> dict:
    from PIL import Image

    out = _empty_meta()
    with Image.open(path) as im:  # header only
        out["width"], out["height"] = int(im.size[0]), int(im.size[1])
    m = read_metadata(path, backend="exifread")  # header only (module docstring)
    out.update(camera=f"{m.make or ''} {m.model or ''}".strip(), lens=m.lens, exposure_s=m.exposure_s,
               f_number=m.f_number, iso=m.iso, ev100=_ev100(m.exposure_s, m.f_number, m.iso),
               timestamp_utc=m.camera_time.isoformat() if m.camera_time else None,
               focal_length_mm=m.focal_length_mm, orientation=m.orientation,
               gps_latitude_deg=m.latitude_deg, gps_longitude_deg=m.longitude_deg, gps_altitude_m=m.altitude_m)
    return out


def _hdr_meta(path: Path) -> dict:
    out = _empty_meta()
    if path.suffix.lower() == ".exr":
        import OpenEXR

        with OpenEXR.File(str(path), header_only=True) as f:
            (x0, y0), (x1, y1) = f.header()["dataWindow"]
        out["width"], out["height"] = int(x1 - x0 + 1), int(y1 - y0 + 1)
        return out
    if path.suffix.lower() == ".pfm":  # "PF" / "Pf", then "W H" (OpenImageIO reads the header only)
        import OpenImageIO as oiio

        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            raise ValueError(f"not a readable PFM file ({oiio.geterror()})")
        out["width"], out["height"] = int(inp.spec().width), int(inp.spec().height)
        inp.close()
        return out
    with open(path, "rb") as fh:  # Radiance: text header, blank line, "-Y H +X W"
        head = fh.read(65536)
    lines = head.split(b"\n")
    if not lines or not lines[0].startswith(b"#?"):
        raise ValueError("not a Radiance HDR file (no #? signature)")
    for i, line in enumerate(lines[1:], 1):
        if not line.strip():
            dims = lines[i + 1].split() if i + 1 < len(lines) else []
            if len(dims) == 4:
                out["height"], out["width"] = int(dims[1]), int(dims[3])
                return out
            break
    raise ValueError("Radiance HDR header has no resolution line")


def read_file_meta(path: Path, kind: str) -> dict:
    """Metadata of one file (raises with a reason on unreadable input)."""
    if path.stat().st_size == 0:
        raise ValueError("empty file (0 bytes)")
    reader = {"raw": _raw_meta, "image": _image_meta, "hdr": _hdr_meta}[kind]
    return reader(path)


# -- role detection by content -------------------------------------------------------------------
def _preview(path: Path, kind: str, max_side: int = 640) -> np.ndarray | None:
    """A small uint8 RGB preview: the RAW's embedded JPEG thumbnail, or the image itself."""
    import io

    from PIL import Image

    if kind == "raw":
        import rawpy

        with rawpy.imread(str(path)) as raw:
            try:
                thumb = raw.extract_thumb()
            except (rawpy.LibRawNoThumbnailError, rawpy.LibRawUnsupportedThumbnailError):
                return None
        if thumb.format != rawpy.ThumbFormat.JPEG:
            return np.ascontiguousarray(thumb.data[..., :3]).astype(np.uint8)
        im = Image.open(io.BytesIO(thumb.data))
    else:
        im = Image.open(path)
        im.draft("RGB", (max_side, max_side))  # JPEG: decode at a reduced scale
    with im:
        im = im.convert("RGB")
        im.thumbnail((max_side, max_side))
        return np.asarray(im)


class ContentRoles:
    """Face / chart detectors for files whose role no folder or TOML gives (loaded lazily)."""

    def __init__(self) -> None:
        self._landmarker = None

    def face(self, preview: np.ndarray) -> bool:
        if self._landmarker is None:
            from f2l.face.landmarker import FaceLandmarker

            self._landmarker = FaceLandmarker()
        return bool(self._landmarker.detect(preview))

    def chart(self, preview: np.ndarray) -> bool:
        from f2l.colour.detect import detect_chart
        from f2l.io.photo import srgb_to_linear

        linear = srgb_to_linear(preview / 255.0).astype(np.float32)
        return detect_chart(preview, linear) is not None

    def __call__(self, path: Path, kind: str) -> str:
        preview = _preview(path, kind)
        if preview is None:
            return "other"
        if self.chart(preview):
            return "chart"
        return "face" if self.face(preview) else "other"


# -- sessions, TOML, brackets --------------------------------------------------------------------
def _session_of(rel: Path) -> str | None:
    """The top-level folder of a relative path, None for files directly in the root."""
    return rel.parts[0] if len(rel.parts) > 1 else None


def _folder_role(rel: Path) -> str | None:
    for part in reversed(rel.parts[1:-1] if len(rel.parts) > 2 else rel.parts[:-1]):
        role = ROLE_FOLDERS.get(part.lower())
        if role:
            return role
    return None


