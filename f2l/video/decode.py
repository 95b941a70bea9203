"""Decode a video clip into upright 8-bit RGB frames with their times.

Backend: OpenCV's ``cv2.VideoCapture`` with its bundled FFmpeg (``cv2.CAP_FFMPEG``), the stack's
own decoder (``opencv-contrib-python-headless``); PyAV is not a dependency. The container's
rotation (the MP4/MOV track's display matrix, a phone's "rotate 90") is honoured by FFmpeg's
auto-rotation (``CAP_PROP_ORIENTATION_AUTO``, on by default and set explicitly here):
frames come out upright, and ``VideoInfo.width``/``height`` are the upright frame's. The
rotation found is reported as ``VideoInfo.rotation_deg`` (``CAP_PROP_ORIENTATION_META``,
clockwise degrees the stored frames are turned for display). Checked in
``tests/test_video_decode.py`` on a clip whose track header is given a 90° display matrix.

* :func:`probe_video` — a clip's :class:`VideoInfo` (opens it and decodes its first frame).
* :func:`read_frames` — ``(index, time_s, rgb)`` for frames ``start, start + every, ...`` below
  ``stop``: ``index`` counts decoded frames from 0, ``time_s`` is the frame's presentation time
  (FFmpeg's, falling back to ``index / fps``), ``rgb`` is (H, W, 3) uint8, upright.

Errors: a clip that does not exist, cannot be opened (not a video, no decoder, no video track)
or whose first frame cannot be decoded raises :class:`VideoError` naming the file and the
reason (FFmpeg's own message where it printed one). A frame that fails to decode mid-clip does
not stop the iteration: it is reported as a :class:`DecodeIssue` to ``on_issue`` (default: a
warning in this module's log), and decoding goes on with the next frame that decodes; decoding
that ends well short of the clip's frame count is reported the same way.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

_log = logging.getLogger(__name__)

# consecutive failed grabs tolerated before decoding is given up as ended
MAX_FAILED_GRABS = 8
# a clip that ends more than this many frames short of its announced count is reported
SHORT_END_FRAMES = 2


class VideoError(RuntimeError):
    """A clip that cannot be opened or decoded (the message names the file and the reason)."""


@dataclass(frozen=True)
class VideoInfo:
    """A clip's properties: upright frame size (px), frames per second, frame count (the
    container's, which may be approximate), display rotation (clockwise degrees, already applied
    to decoded frames) and duration in seconds (``frame_count / fps``)."""

    path: Path
    width: int
    height: int
    fps: float
    frame_count: int
    rotation_deg: int
    duration_s: float


@dataclass(frozen=True)
class DecodeIssue:
    """A problem met while decoding: ``index`` the frame index it happened at, ``reason`` what."""

    path: Path
    index: int
    reason: str

    def __str__(self) -> str:
        return f"{self.path}: frame {self.index}: {self.reason}"


def _open(path: str | os.PathLike):
    """An opened ``cv2.VideoCapture`` on ``path`` with auto-rotation on, or :class:`VideoError`."""
    import cv2

    from f2l.io.native_stderr import native_stderr_lines

    p = Path(path)
    if not p.exists():
        raise VideoError(f"{p}: no such file")
    if p.is_dir():
        raise VideoError(f"{p}: is a directory, not a video file")
    try:
        with p.open("rb"):
            pass
    except OSError as exc:
        raise VideoError(f"{p}: cannot read: {exc.strerror or exc}") from exc
    said: list[str] = []
    # FFmpeg and OpenCV print their reasons (e.g. "moov atom not found") to fd 2: keep them
    with native_stderr_lines(lambda line, failed: said.append(line.strip())):
        cap = cv2.VideoCapture(str(p), cv2.CAP_FFMPEG)
        opened = cap.isOpened()
        if opened:
            cap.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)
    if not opened:
        cap.release()
        ffmpeg = [s.split("] ", 1)[-1] for s in said if s.startswith("[") and "] " in s]
        reason = "; ".join(dict.fromkeys(ffmpeg)) or "FFmpeg cannot open it"
        raise VideoError(f"{p}: not a readable video ({reason})")
    return cap


def _info(cap, path: Path) -> VideoInfo:
    import cv2

    fps = float(cap.get(cv2.CAP_PROP_FPS))
    if not math.isfinite(fps) or fps <= 0:
        fps = 0.0
    count = max(0, int(round(cap.get(cv2.CAP_PROP_FRAME_COUNT))))
    rotation = int(round(cap.get(cv2.CAP_PROP_ORIENTATION_META))) % 360
    return VideoInfo(path=path, width=int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
                     height=int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)), fps=fps, frame_count=count,
                     rotation_deg=rotation, duration_s=count / fps if fps > 0 else 0.0)


def probe_video(path: str | os.PathLike) -> VideoInfo:
    """The clip's :class:`VideoInfo`; raises :class:`VideoError` when it cannot be opened or its
    first frame cannot be decoded. The size is that of the decoded (upright) first frame."""
    p = Path(path)
    cap = _open(p)
    try:
        info = _info(cap, p)
        ok, frame = cap.read()
        if not ok or frame is None or frame.size == 0:
            raise VideoError(f"{p}: no frame could be decoded")
        h, w = frame.shape[:2]
        if (w, h) != (info.width, info.height):
            info = VideoInfo(path=p, width=w, height=h, fps=info.fps, frame_count=info.frame_count,
                             rotation_deg=info.rotation_deg, duration_s=info.duration_s)
        return info
    finally:
        cap.release()


def read_frames(path: str | os.PathLike, *, start: int = 0, stop: int | None = None, every: int = 1,
                on_issue: Callable[[DecodeIssue], None] | None = None
                ) -> Iterator[tuple[int, float, np.ndarray]]:
    """Yield ``(index, time_s, rgb)`` for the decoded frames ``start, start + every, ...`` before
    ``stop`` (None: to the end). ``rgb`` is a fresh (H, W, 3) uint8 array, upright. Skipped
    frames are only demuxed and decoded (``grab``), not converted. Raises :class:`VideoError`
    when the clip cannot be opened or yields no frame at all; a frame that fails mid-clip is
    reported to ``on_issue`` (default: logged as a warning) and skipped."""
    import cv2

    if start < 0 or every < 1 or (stop is not None and stop < start):
        raise ValueError(f"need 0 <= start <= stop and every >= 1, got start={start}, stop={stop}, every={every}")
    p = Path(path)
    report = on_issue if on_issue is not None else (lambda issue: _log.warning("%s", issue))
    cap = _open(p)
    try:
        info = _info(cap, p)
        index = -1
        decoded_any = False
        failed = 0
        while stop is None or index + 1 < stop:
            if not cap.grab():
                failed += 1
                # FFmpeg already skips packets it cannot decode; a failed grab is the end of the
                # stream or a run of undecodable data: retry a few times before calling it the end
                if failed <= MAX_FAILED_GRABS and index + 1 < info.frame_count - SHORT_END_FRAMES:
                    continue
                break
            failed = 0
            index = _frame_index(cap, index, info.fps, p, report)
            decoded_any = True
            if index < start or (index - start) % every:
                continue
            ok, bgr = cap.retrieve()
            if not ok or bgr is None or bgr.size == 0:
                report(DecodeIssue(p, index, "the frame could not be decoded (skipped)"))
                continue
            time_s = _time_s(cap, index, info.fps)
            yield index, time_s, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        if not decoded_any:
            raise VideoError(f"{p}: no frame could be decoded")
        end = index + 1
        if stop is None and info.frame_count and end < info.frame_count - SHORT_END_FRAMES:
            report(DecodeIssue(p, end, f"decoding ended after {end} of {info.frame_count} frames "
                                       "(the rest could not be decoded)"))
    finally:
        cap.release()


def _frame_index(cap, previous: int, fps: float, path: Path, report) -> int:
    """The index of the frame just grabbed: the previous one + 1, or further on where its
    presentation time says frames were lost in between (reported)."""
    import cv2

    index = previous + 1
    if fps > 0:
        msec = float(cap.get(cv2.CAP_PROP_POS_MSEC))
        if math.isfinite(msec) and msec > 0:
            by_time = int(round(msec * fps / 1000.0))
            if by_time > index:
                lost = by_time - index
                report(DecodeIssue(path, index, f"{lost} frame{'s' if lost > 1 else ''} could not be "
                                                "decoded (skipped)"))
                index = by_time
    return index


def _time_s(cap, index: int, fps: float) -> float:
    import cv2

    msec = float(cap.get(cv2.CAP_PROP_POS_MSEC))
    if math.isfinite(msec) and (msec > 0 or index == 0):
        return msec / 1000.0
    return index / fps if fps > 0 else float("nan")
