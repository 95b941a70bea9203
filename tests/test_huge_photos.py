"""Large photos (issue 18): a documented pixel limit checked before decoding; photos whose long side
exceeds DETECTION_MAX_SIDE are streamed (faces detected on a reduced copy, fitted from a
full-resolution window), with memory near the reduced copy whatever the photo's size."""

from __future__ import annotations

from dataclasses import replace

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from PIL import Image

import f2l.io.photo as photo_mod
from f2l.lighting.grid import LatLongGrid
from f2l.io.photo import Photo, PhotoError, StreamedPhoto, load_photo

needs_streaming = pytest.mark.skipif(not photo_mod._CAN_STREAM_PILLOW, reason="JPEG/PNG streaming needs Linux madvise")


@pytest.fixture(scope="module")
def astronaut() -> np.ndarray:
    import skimage.data

    return skimage.data.astronaut()


@pytest.fixture(scope="module")
def astronaut_png(tmp_path_factory, astronaut) -> Path:
    path = tmp_path_factory.mktemp("astro") / "astronaut.png"
    Image.fromarray(astronaut).save(path)
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
    small, scale, offset = p.detection_image(15)
    assert small.shape == (10, 15, 3) and scale == 1 / 4 and offset == (0.0, 0.0)
    assert (small[0, 0] == 200).all() and (small[1:, :] == 0).all() and (small[:, 1:] == 0).all()
    same, one, zero = p.detection_image(60)
    assert same is p.display and one == 1.0 and zero == (0.0, 0.0)


def _formats(tmp: Path, rgb: np.ndarray) -> dict[str, Path]:
    """The astronaut in every layout the streamed path reads (and a CMYK JPEG, which it does not)."""
    import tifffile

    grey, rgb16 = rgb[..., 1], rgb.astype(np.uint16) * 257 + 3
    files = {}

    def pil(name, im, **kw):
        files[name] = tmp / name
        im.save(files[name], **kw)

    def tif(name, arr, **kw):
        files[name] = tmp / name
        tifffile.imwrite(files[name], arr, **kw)

    pil("rgb.png", Image.fromarray(rgb))
    pil("rgba.png", Image.fromarray(np.dstack([rgb, grey])))
    pil("la.png", Image.fromarray(np.dstack([grey, rgb[..., 0]]), "LA"))
    pil("l.png", Image.fromarray(grey))
    pil("p.png", Image.fromarray(rgb).convert("P", palette=Image.Palette.ADAPTIVE, colors=61))
    pil("i16.png", Image.fromarray(rgb16[..., 0]))
    files["rgb16.png"] = tmp / "rgb16.png"
    import cv2

    cv2.imwrite(str(files["rgb16.png"]), rgb16[..., ::-1])  # Pillow reads its high bytes
    pil("rgb.jpg", Image.fromarray(rgb), quality=90)
    pil("progressive.jpg", Image.fromarray(rgb), quality=90, progressive=True)
    pil("grey.jpg", Image.fromarray(grey), quality=90)
    pil("cmyk.jpg", Image.fromarray(rgb).convert("CMYK"))
    tif("rgb16.tif", rgb16, photometric="rgb")  # uncompressed, one strip: rows read directly
    tif("tiled16.tif", rgb16, photometric="rgb", compression="zlib", predictor=True, tile=(64, 48))
    tif("strips8.tif", rgb, photometric="rgb", compression="zlib", rowsperstrip=37)
    tif("planar8.tif", np.moveaxis(rgb, -1, 0).copy(), photometric="rgb", planarconfig="separate",
        compression="zlib", rowsperstrip=50)
    tif("grey16.tif", rgb16[..., 2], photometric="minisblack", compression="zlib", rowsperstrip=64)
    return files


@needs_streaming
def test_streamed_photo_reads_what_the_whole_decode_holds(tmp_path, astronaut):
    """Streamed (stream=True, whatever the size) and whole decodes agree exactly on every pixel
    read, on the reduced copy (except JPEG, reduced by libjpeg's DCT scaling) and on the camera."""
    rgb = astronaut[:301, :437]  # odd sizes: partial strips, tiles and boxes
    for name, path in _formats(tmp_path, rgb).items():
        whole, streamed = load_photo(path, stream=False), load_photo(path, stream=True)
        assert isinstance(whole, Photo)
        if name == "cmyk.jpg":
            assert isinstance(streamed, Photo)  # not streamable: decoded whole
            continue
        assert isinstance(streamed, StreamedPhoto), name
        assert streamed.shape == whole.shape == (301, 437) and streamed.kind == whole.kind
        assert (streamed.focal_px, streamed.focal_source) == (whole.focal_px, whole.focal_source)
        index = np.array([0, 5, 6, 150, 299, 300])
        for cols in (slice(None), slice(17, 90), slice(400, 437)):
            a, b = whole.rows(index, cols), streamed.rows(index, cols)
            for key in ("linear", "clipped", "black", "display"):
                np.testing.assert_array_equal(a[key], b[key], err_msg=f"{name} {key} {cols}")
        small, scale, offset = streamed.detection_image(100)
        if not name.endswith(".jpg"):
            ref = whole.detection_image(100)
            np.testing.assert_array_equal(small, ref[0], err_msg=name)
            assert (scale, offset) == ref[1:] == (1 / 5, (0.0, 0.0))
        assert streamed.linear.shape == (301, 437, 3)  # whole-image arrays on demand


@needs_streaming
@pytest.mark.parametrize("ext", ["png", "jpg"])
def test_streamed_orientations_map_back_to_the_photo(tmp_path, astronaut, ext):
    """With each EXIF orientation, a streamed photo's windows equal the whole decode's, and a
    reduced pixel p maps to offset + p / scale: PNG exactly (the mean of that box of the oriented
    display), JPEG (DCT-scaled, partial last block) to within a fraction of a reduced pixel: the
    box at the stated offset matches far better than boxes 2 px off."""
    rgb = np.asarray(Image.fromarray(astronaut).resize((515, 389)))
    for orientation in range(1, 9):
        exif = Image.Exif()
        exif[274] = orientation
        path = tmp_path / f"o{orientation}.{ext}"
        Image.fromarray(rgb).save(path, exif=exif, quality=95)
        whole, streamed = load_photo(path, stream=False), load_photo(path, stream=True)
        assert isinstance(streamed, StreamedPhoto) and streamed.orientation == orientation == whole.orientation
        h, w = streamed.shape
        assert (h, w) == whole.shape
        index = np.array([0, 7, 8, 100, h - 1])
        for cols in (slice(13, 77), slice(w - 20, w)):
            np.testing.assert_array_equal(whole.rows(index, cols)["display"], streamed.rows(index, cols)["display"])
        small, scale, (ox, oy) = streamed.detection_image(100)
        f = round(1 / scale)
        display = whole.display.astype(np.float64)

        def box_error(dx: int, dy: int) -> float:
            x0, y0 = int(round(ox)) + dx, int(round(oy)) + dy
            i, j = np.meshgrid(np.arange(2, small.shape[0] - 2), np.arange(2, small.shape[1] - 2), indexing="ij")
            boxes = np.stack([display[y0 + a * f : y0 + (a + 1) * f, x0 + b * f : x0 + (b + 1) * f].mean((0, 1))
                              for a, b in zip(i.ravel(), j.ravel())])
            return float(np.abs(boxes - small[i.ravel(), j.ravel()]).mean())

        if ext == "png":
            assert (ox, oy) == (float(int(ox)), float(int(oy))) and box_error(0, 0) < 0.5 + 1e-9  # rounding only
        else:
            assert box_error(0, 0) < 0.25 * min(box_error(2, 0), box_error(-2, 0), box_error(0, 2), box_error(0, -2))


@needs_streaming
def test_truncated_streamed_photos_are_refused(tmp_path, astronaut):
    for name in ("cut.png", "cut.jpg"):
        full = tmp_path / ("full" + Path(name).suffix)
        Image.fromarray(astronaut).save(full)
        data = full.read_bytes()
        (tmp_path / name).write_bytes(data[: len(data) * 2 // 3])
        with pytest.raises(PhotoError, match="truncated or corrupt") as exc:
            load_photo(tmp_path / name, stream=True)
        assert exc.value.path == str(tmp_path / name)


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
    assert proc.returncode == 4, proc.stderr[-2000:]  # 4: one photo refused, the rest written
    rows = {Path(r["source_path"]).name: r for r in pq.read_table(tmp_path / "out" / "status").to_pylist()}
    assert rows["huge.png"]["status"] == "error"
    assert rows["huge.png"]["message"] == (f"{photos / 'huge.png'}: image is 5000x4000 = 20 MP, above the 10 MP "
                                           "limit (F2L_MAX_PHOTO_PIXELS); not decoded")
    assert rows["astronaut.png"]["status"] == "ok"


@pytest.fixture(scope="module")
def landmarker():
    from f2l.face.landmarker import FaceLandmarker

    return FaceLandmarker()


@needs_streaming
@pytest.mark.parametrize("ext", ["png", "jpg"])
def test_large_photo_is_detected_on_a_reduced_copy_and_fitted_at_full_resolution(
        tmp_path, astronaut_png, landmarker, monkeypatch, ext):
    """The astronaut at 4x (2048 px, nearest neighbour) with detection capped at 512 px (so it is
    streamed) gives the landmarks of the 512 px original, scaled by 4. PNG reduces by a 4 x 4 box,
    which gives the landmark model exactly the original's pixels: the same landmarks (bound
    1e-3 px, for float rounding of the division by the scale). JPEG (quality 95) is reduced by
    libjpeg's 1/4 DCT scaling, nearly the same pixels: bound 0.5% of the face's width, 0.46 px
    (measured 0.08 px at most, 0.02 px median)."""
    from f2l.face.fit import FaceFit, FitOptions, fit_photo_faces

    big_path = tmp_path / f"astronaut_x4.{ext}"
    Image.open(astronaut_png).resize((2048, 2048), Image.Resampling.NEAREST).save(big_path, quality=95)
    # faces from 80 px in the 2048 px photo: detection may reduce it by 4, to the 512 px original,
    # where it looks for faces from 20 px, as the original's own search does
    options = FitOptions(grid=LatLongGrid(8, 16), min_face_px=80)
    small = fit_photo_faces(load_photo(astronaut_png), landmarker, replace(options, min_face_px=20))
    monkeypatch.setattr(photo_mod, "DETECTION_MAX_SIDE", 512)
    photo = load_photo(big_path)
    assert isinstance(photo, StreamedPhoto)
    big = fit_photo_faces(photo, landmarker, options)
    assert len(small) == len(big) == 1 and isinstance(big[0], FaceFit) and isinstance(small[0], FaceFit)
    width = np.ptp(small[0].landmarks[:, 0])
    bound = 1e-3 if ext == "png" else 0.005 * width
    assert np.abs(big[0].landmarks[:, :2] / 4 - small[0].landmarks[:, :2]).max() < bound
    # fitted on the full-resolution pixels: the working crop is sampled from the 2048 px photo
    assert big[0].mask.sum() > 0.9 * small[0].mask.sum()
    np.testing.assert_allclose(np.median(big[0].observed_rgb, 0), np.median(small[0].observed_rgb, 0), rtol=0.05)


@needs_streaming
def test_streamed_fit_equals_the_whole_decode_with_two_faces(tmp_path, astronaut, landmarker, monkeypatch):
    """Two faces in a streamed PNG (one pass reads both windows) give exactly the records of the
    same photo decoded whole: the same reduced copy, hence the same landmarks, and the same
    full-resolution pixels."""
    from f2l.face.fit import FaceFit, FitOptions, fit_photo_faces

    head = astronaut[:300, 100:400]
    two = np.full((600, 600, 3), 128, np.uint8)
    two[:300, :300], two[300:, 300:] = head, head[:, ::-1]  # on a diagonal: rows and columns differ
    path = tmp_path / "two.png"
    Image.fromarray(two).resize((1800, 1800), Image.Resampling.NEAREST).save(path)
    monkeypatch.setattr(photo_mod, "DETECTION_MAX_SIDE", 700)
    options = FitOptions(grid=LatLongGrid(8, 16))  # transport is not what is compared here
    streamed, whole = load_photo(path), load_photo(path, stream=False)
    assert isinstance(streamed, StreamedPhoto)
    a, b = fit_photo_faces(whole, landmarker, options), fit_photo_faces(streamed, landmarker, options)
    assert len(a) == len(b) == 2 and all(isinstance(x, FaceFit) for x in a + b)
    assert len(streamed._windows) == 2  # both read by one pass (prefetch), then used
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.landmarks, y.landmarks)
        np.testing.assert_array_equal(x.observed_rgb, y.observed_rgb)
        np.testing.assert_array_equal(x.mask, y.mask)
        np.testing.assert_array_equal(x.crop_display, y.crop_display)


def _peak_rss_mib(photos: Path, out: Path) -> float:
    code = ("import resource, subprocess, sys\n"
            f"subprocess.run([sys.executable, '-m', 'f2l.cli', 'fit-faces', {str(photos)!r}, '--out', {str(out)!r},"
            " '--json'], check=True, capture_output=True)\n"
            "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return float(proc.stdout.strip())


@needs_streaming
def test_memory_of_a_large_photo_without_a_face_stays_near_its_reduced_copy(tmp_path):
    """A 10,000 x 10,000 PNG with no face (286 MiB of 8-bit codes; Pillow's buffer alone would be
    381 MiB) is streamed: peak RSS of `f2l fit-faces` above a run on a 256 px photo stays under
    96 MiB. The reduced copy (3,333 px square, 32 MiB) and the rows in flight are all it holds
    (measured: +34 MiB; +637 MiB when it was decoded whole into 8-bit codes)."""
    small, big = tmp_path / "small", tmp_path / "big"
    small.mkdir()
    big.mkdir()
    Image.new("RGB", (256, 256), (90, 120, 150)).save(small / "flat.png")
    Image.new("RGB", (10_000, 10_000), (90, 120, 150)).save(big / "flat.png")  # a 0.3 MB file
    base = _peak_rss_mib(small, tmp_path / "o1")
    peak = _peak_rss_mib(big, tmp_path / "o2")
    assert peak - base < 96, (base, peak)
    status = pq.read_table(tmp_path / "o2" / "status").to_pylist()
    assert status[0]["status"] == "no_face" and json.loads(status[0]["rejected_json"]) == []
    assert status[0]["message"] == f"{big / 'flat.png'}: no face detected"
