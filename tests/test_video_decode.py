"""Decoding clips (f2l.video.decode): frames, times, rotation metadata, and clear errors.

Clips are written here with OpenCV's ``VideoWriter`` (MPEG-4 part 2 in MP4, MJPEG in AVI). The
rotated clip is an MP4 whose track header (``tkhd``) is given the display matrix of a phone's
portrait clip ("rotate 90": shown turned 90° clockwise), patched in place.
"""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from f2l.video.decode import DecodeIssue, VideoError, VideoInfo, probe_video, read_frames

FPS = 25.0


def write_video(path: Path, frames_rgb, fps: float = FPS, fourcc: str = "mp4v") -> Path:
    """Write RGB uint8 frames (all one size) with OpenCV (``mp4v`` → .mp4, ``MJPG`` → .avi)."""
    frames_rgb = list(frames_rgb)
    h, w = frames_rgb[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (w, h))
    assert writer.isOpened(), path
    for rgb in frames_rgb:
        writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def marked_frames(n: int, h: int = 96, w: int = 128):
    """Frame i: grey level 12 i, a red block in the top-left corner (orientation mark)."""
    out = []
    for i in range(n):
        f = np.full((h, w, 3), 12 * i, np.uint8)
        f[:24, :32] = (255, 0, 0)
        out.append(f)
    return out


def set_display_rotation(path: Path, out: Path, a: int, b: int, c: int, d: int) -> Path:
    """Copy an MP4 with its (one) track header's display matrix set to [[a, b], [c, d]] (16.16)."""
    data = bytearray(path.read_bytes())
    i = data.find(b"tkhd")
    assert i > 0
    version = data[i + 4]
    # tkhd: version/flags, times + track id + reserved + duration (20 or 32 bytes), 8 reserved,
    # layer, alternate group, volume, 2 reserved, then the 3x3 matrix
    off = i + 8 + (32 if version == 1 else 20) + 8 + 8
    assert struct.unpack(">9i", data[off:off + 36])[0] == 1 << 16  # identity before
    data[off:off + 36] = struct.pack(">9i", a << 16, b << 16, 0, c << 16, d << 16, 0, 0, 0, 1 << 30)
    out.write_bytes(bytes(data))
    return out


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return write_video(tmp_path_factory.mktemp("clips") / "marked.mp4", marked_frames(12))


def test_probe_reports_size_rate_count_and_duration(clip):
    info = probe_video(clip)
    assert isinstance(info, VideoInfo)
    assert (info.width, info.height, info.frame_count, info.rotation_deg) == (128, 96, 12, 0)
    assert info.fps == pytest.approx(FPS)
    assert info.duration_s == pytest.approx(12 / FPS)
    assert info.path == Path(clip)


def test_frames_come_in_order_with_their_times_and_content(clip):
    frames = list(read_frames(clip))
    assert [i for i, _, _ in frames] == list(range(12))
    np.testing.assert_allclose([t for _, t, _ in frames], np.arange(12) / FPS, atol=1e-6)
    for i, _, rgb in frames:
        assert rgb.dtype == np.uint8 and rgb.shape == (96, 128, 3)
        assert abs(float(rgb[48:, 64:].mean()) - 12 * i) < 5  # the frame's own grey level
        red = rgb[:24, :32].mean((0, 1))
        assert red[0] > 200 and red[1] < 60 and red[2] < 60  # RGB order, not OpenCV's BGR


def test_start_stop_and_every_pick_frames(clip):
    picked = list(read_frames(clip, start=2, stop=11, every=3))
    assert [i for i, _, _ in picked] == [2, 5, 8]
    np.testing.assert_allclose([t for _, t, _ in picked], np.array([2, 5, 8]) / FPS, atol=1e-6)
    assert [abs(float(rgb[48:, 64:].mean()) - 12 * i) < 5 for i, _, rgb in picked] == [True] * 3
    with pytest.raises(ValueError):
        next(read_frames(clip, every=0))


def test_a_clip_with_rotation_metadata_comes_out_upright(clip, tmp_path):
    """Display matrix [[0, 1], [-1, 0]] (a phone held upright): shown turned 90° clockwise, so
    the stored 128×96 frames come out 96×128 with the top-left mark at the top right."""
    rotated = set_display_rotation(Path(clip), tmp_path / "portrait.mp4", 0, 1, -1, 0)
    info = probe_video(rotated)
    assert info.rotation_deg == 90
    assert (info.width, info.height) == (96, 128)
    stored = marked_frames(12)
    for i, _, rgb in read_frames(rotated):
        assert rgb.shape == (128, 96, 3)
        upright = np.rot90(stored[i], k=-1)  # clockwise
        assert np.abs(rgb.astype(int) - upright).mean() < 4, i
        mark, corner = rgb[:32, -24:].mean((0, 1)), rgb[:32, :24].mean((0, 1))  # the 24×32 mark, turned
        assert mark[0] > 200 and mark[1] < 60 and abs(corner[0] - corner[1]) < 10


@pytest.mark.parametrize("make,reason", [
    (lambda d: d / "missing.mp4", "no such file"),
    (lambda d: d, "directory"),
    (lambda d: (d / "notes.mp4").write_text("not a video") and d / "notes.mp4", "not a readable video"),
    (lambda d: (d / "empty.mp4").write_bytes(b"") or d / "empty.mp4", "not a readable video"),
])
def test_unreadable_files_give_an_error_naming_the_file_and_reason(tmp_path, make, reason):
    path = make(tmp_path)
    with pytest.raises(VideoError) as exc:
        probe_video(path)
    assert str(path) in str(exc.value) and reason in str(exc.value)
    with pytest.raises(VideoError) as exc:
        next(read_frames(path))
    assert str(path) in str(exc.value) and reason in str(exc.value)


def test_a_truncated_mp4_says_what_ffmpeg_found(clip, tmp_path):
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(Path(clip).read_bytes()[:300])  # moov (the index) is written last: gone
    with pytest.raises(VideoError, match="moov atom not found") as exc:
        probe_video(cut)
    assert str(cut) in str(exc.value)


def test_a_frame_that_fails_mid_clip_is_reported_and_the_rest_decode(tmp_path):
    """An MJPEG clip whose 11th frame's JPEG data is blanked: frames 0-9 and 11-19 come out with
    their own indices, times and content; frame 10 is reported, nothing raises."""
    path = write_video(tmp_path / "clip.avi", marked_frames(20), fourcc="MJPG")
    data = bytearray(path.read_bytes())
    soi = [i for i in range(len(data) - 2) if data[i] == 0xFF and data[i + 1] == 0xD8 and data[i + 2] == 0xFF]
    assert len(soi) == 20
    n = soi[11] - soi[10] - 8  # its whole JPEG (the next chunk's 8-byte header kept)
    data[soi[10]:soi[10] + n] = bytes(n)
    broken = tmp_path / "broken.avi"
    broken.write_bytes(bytes(data))
    issues: list[DecodeIssue] = []
    frames = list(read_frames(broken, on_issue=issues.append))
    assert [i for i, _, _ in frames] == [i for i in range(20) if i != 10]
    np.testing.assert_allclose([t for _, t, _ in frames], [i / FPS for i, _, _ in frames], atol=1e-6)
    assert all(abs(float(rgb[48:, 64:].mean()) - 12 * i) < 5 for i, _, rgb in frames)
    assert [(issue.index, issue.path) for issue in issues] == [(10, broken)]
    assert "could not be decoded" in str(issues[0]) and str(broken) in str(issues[0])
