"""Large photos (issue 18): a documented pixel limit checked before decoding, faces detected on a
reduced copy and fitted at full resolution, and memory near the size of the source encoding."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from PIL import Image

import f2l.face.photo as photo_mod
from f2l.face.photo import Photo, PhotoError, load_photo


@pytest.fixture(scope="module")
def astronaut_png(tmp_path_factory) -> Path:
    import skimage.data

    path = tmp_path_factory.mktemp("astro") / "astronaut.png"
    Image.fromarray(skimage.data.astronaut()).save(path)
    return path


def test_rows_equal_the_full_arrays():
    """Photo.rows computes from the rows it is given exactly what the full arrays hold."""
    rng = np.random.default_rng(0)
    for dtype, full in ((np.uint8, 255), (np.uint16, 65535)):
        codes = rng.integers(0, full + 1, size=(23, 31, 3)).astype(dtype)
        codes[3, 4] = full
        codes[5, 6] = 0
        p = Photo(path="x", kind="png", codes=codes, focal_px=10.0, focal_source="default", orientation=1, exif={})
        rows = np.array([0, 3, 5, 22])
        part = p.rows(rows, slice(2, 9))
        np.testing.assert_array_equal(part["linear"], p.linear[rows, 2:9])
        np.testing.assert_array_equal(part["clipped"], p.clipped[rows, 2:9])
        np.testing.assert_array_equal(part["black"], p.black[rows, 2:9])
        np.testing.assert_array_equal(part["display"], p.display[rows, 2:9])
        assert p.clipped[3, 4] and p.black[5, 6] and p.linear.dtype == np.float32


def test_detection_image_is_a_box_reduction():
    codes = np.zeros((40, 60, 3), np.uint8)
    codes[:4, :4] = 200  # one 4 x 4 block
    p = Photo(path="x", kind="png", codes=codes, focal_px=10.0, focal_source="default", orientation=1, exif={})
    small, scale = p.detection_image(15)
    assert small.shape == (10, 15, 3) and scale == 15 / 60
    assert (small[0, 0] == 200).all() and (small[1:, :] == 0).all() and (small[:, 1:] == 0).all()
    same, one = p.detection_image(60)
    assert same is p.display and one == 1.0


def test_photo_beyond_the_limit_is_refused_before_decoding(tmp_path, monkeypatch):
    path = tmp_path / "wide.png"
    Image.new("RGB", (5000, 4000), (90, 120, 150)).save(path)  # 20 MP, a 60 kB file
    with pytest.raises(PhotoError, match=r"5000x4000 = 20 MP, above the 10 MP limit") as exc:
        load_photo(path, max_pixels=10_000_000)
    assert exc.value.path == str(path)
    monkeypatch.setenv("F2L_MAX_PHOTO_PIXELS", "1e7")
    with pytest.raises(PhotoError, match="above the 10 MP limit"):
        load_photo(path)
    monkeypatch.delenv("F2L_MAX_PHOTO_PIXELS")
    assert load_photo(path).shape == (4000, 5000)  # within the default limit (and Pillow's guard off)


def test_batch_goes_on_past_a_refused_photo(tmp_path, astronaut_png):
    photos = tmp_path / "photos"
    photos.mkdir()
    Image.new("RGB", (5000, 4000), (90, 120, 150)).save(photos / "huge.png")
    (photos / "astronaut.png").write_bytes(astronaut_png.read_bytes())
    env = dict(os.environ, F2L_MAX_PHOTO_PIXELS="10000000")
    proc = subprocess.run([sys.executable, "-m", "f2l.cli", "fit-faces", str(photos), "--out", str(tmp_path / "out"),
                           "--json"], capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    rows = {Path(r["source_path"]).name: r for r in pq.read_table(tmp_path / "out" / "status").to_pylist()}
    assert rows["huge.png"]["status"] == "error"
    assert str(photos / "huge.png") in rows["huge.png"]["message"] and "10 MP limit" in rows["huge.png"]["message"]
    assert rows["astronaut.png"]["status"] == "ok"


def test_large_photo_is_detected_on_a_reduced_copy_and_fitted_at_full_resolution(astronaut_png, monkeypatch):
    """The astronaut at 4x (2048 px) with detection capped at 512 px gives the landmarks of the
    512 px original, scaled by 4: the landmark model sees the same pixels (up to the box filter's
    rounding), so they agree to a small fraction of the face (bound: 1% of its width)."""
    from f2l.face.fit import FaceFit, FitOptions, fit_photo_faces
    from f2l.face.landmarker import FaceLandmarker

    big_path = astronaut_png.parent / "astronaut_x4.png"
    Image.open(astronaut_png).resize((2048, 2048), Image.Resampling.NEAREST).save(big_path)
    landmarker = FaceLandmarker()
    options = FitOptions()
    small = fit_photo_faces(load_photo(astronaut_png), landmarker, options)
    monkeypatch.setattr(photo_mod, "DETECTION_MAX_SIDE", 512)
    big = fit_photo_faces(load_photo(big_path), landmarker, options)
    assert len(small) == len(big) == 1 and isinstance(big[0], FaceFit) and isinstance(small[0], FaceFit)
    width = np.ptp(small[0].landmarks[:, 0])
    assert np.abs(big[0].landmarks[:, :2] / 4 - small[0].landmarks[:, :2]).max() < 0.01 * width
    # fitted on the full-resolution pixels: the working crop is sampled from the 2048 px photo
    assert big[0].mask.sum() > 0.9 * small[0].mask.sum()
    np.testing.assert_allclose(np.median(big[0].observed_rgb, 0), np.median(small[0].observed_rgb, 0), rtol=0.05)


def _peak_rss_mib(photos: Path, out: Path) -> float:
    code = ("import resource, subprocess, sys\n"
            f"subprocess.run([sys.executable, '-m', 'f2l.cli', 'fit-faces', {str(photos)!r}, '--out', {str(out)!r},"
            " '--json'], check=True, capture_output=True)\n"
            "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return float(proc.stdout.strip())


def test_memory_of_a_large_photo_without_a_face_stays_near_its_encoding(tmp_path):
    """An 8,000 x 8,000 PNG (192 MB of 8-bit codes) with no face: peak RSS above a run on a small
    photo stays under 2.6 x the codes (Pillow's 4-byte buffer and the codes array, 2.33 x, while
    decoding); a float32 copy of the image alone would be 4 x (the old path: ~6 x)."""
    small, big = tmp_path / "small", tmp_path / "big"
    small.mkdir()
    big.mkdir()
    Image.new("RGB", (256, 256), (90, 120, 150)).save(small / "flat.png")
    Image.new("RGB", (8000, 8000), (90, 120, 150)).save(big / "flat.png")
    base = _peak_rss_mib(small, tmp_path / "o1")
    peak = _peak_rss_mib(big, tmp_path / "o2")
    codes_mib = 8000 * 8000 * 3 / 2**20
    assert peak - base < 2.6 * codes_mib, (base, peak)
    status = pq.read_table(tmp_path / "o2" / "status").to_pylist()
    assert status[0]["status"] == "no_face" and json.loads(status[0]["rejected_json"]) == []
