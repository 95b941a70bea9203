"""The Python API (f2l.api): the README's example runs as written; in memory it gives what
`f2l estimate photo.jpg` writes."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import f2l

README = Path(__file__).resolve().parents[1] / "README.md"


@pytest.fixture(scope="module")
def photos(tmp_path_factory):
    import cv2
    import skimage.data

    folder = tmp_path_factory.mktemp("api")
    img = skimage.data.astronaut()
    Image.fromarray(img).save(folder / "photo.jpg", quality=92)
    Image.fromarray(cv2.GaussianBlur(img, (0, 0), 4.0)).save(folder / "soft.png")
    Image.fromarray(skimage.data.coffee()).save(folder / "coffee.png")
    return folder


@pytest.fixture(scope="module")
def estimates(photos):
    return f2l.estimate_photo(photos / "photo.jpg", model="sunsky")


def test_readme_example_runs_as_written(photos, monkeypatch, capsys):
    block = re.search(r"```python\n(.*?)```", README.read_text(), re.S).group(1)
    assert "f2l.estimate_photo(\"photo.jpg\"" in block and len(block.strip().splitlines()) <= 6
    monkeypatch.chdir(photos)
    exec(compile(block, "README.md", "exec"), {})
    assert capsys.readouterr().out.startswith("0 ok ")
    assert f2l.load_probe(photos / "probe-0.exr").shape == (64, 128, 3)


def test_one_face_with_a_probe_and_a_sun(estimates):
    (face,) = estimates
    assert face.ok and face.model == "sunsky" and face.face_index == 0
    assert face.probe.shape == (64, 128, 3) and face.probe.dtype == np.float32 and np.isfinite(face.probe).all()
    assert np.linalg.norm(face.sun_direction) == pytest.approx(1.0, abs=1e-6)
    assert -90 <= face.sun_elevation_deg <= 90 and -180 <= face.sun_azimuth_deg <= 180
    assert {"turbidity", "kappa", "sun_elevation_rad", "sun_azimuth_rad"} <= set(face.params)
    # sun_direction is the elevation profile's posterior mean over its pinned refits (10, 25, ... 85°), the
    # parameters are its best refit's: they agree to within the pins' spacing
    assert face.sun_elevation_deg == pytest.approx(np.degrees(face.params["sun_elevation_rad"]), abs=15.0)
    assert face.units.startswith("relative")  # the photo has no EXIF exposure
    x0, y0, x1, y1 = face.face_box_px
    assert 150 < x0 < x1 < 350 and 0 < y0 < y1 < 250


def test_the_api_gives_what_the_cli_writes(photos, estimates, tmp_path):
    from typer.testing import CliRunner

    from f2l.cli import app

    res = CliRunner().invoke(app, ["estimate", str(photos / "photo.jpg"), "-m", "sunsky", "--out", str(tmp_path), "--json"])
    assert res.exit_code == 0, res.output
    (written,) = sorted((tmp_path / "probes" / "sunsky").glob("*.exr"))
    np.testing.assert_array_equal(f2l.load_probe(written), estimates[0].probe)


def test_a_refused_face_has_its_reason_and_no_probe(photos, tmp_path):
    (face,) = f2l.estimate_photo(photos / "soft.png")
    assert face.status == "blurred" and not face.ok and face.probe is None and face.sun_direction is None
    assert "blur index" in face.message and face.face_box_px is not None
    with pytest.raises(ValueError, match="no probe"):
        face.save_exr(tmp_path / "x.exr")


def test_a_photo_without_a_face_gives_none_and_bad_input_raises(photos, tmp_path):
    from f2l.io.photo.core import PhotoError
    from f2l.models.registry import ModelNotFoundError

    assert f2l.estimate_photo(photos / "coffee.png") == []
    (tmp_path / "bad.jpg").write_bytes(b"not a photo")
    with pytest.raises(PhotoError, match="bad.jpg"):
        f2l.estimate_photo(tmp_path / "bad.jpg")
    with pytest.raises(ModelNotFoundError):
        f2l.estimate_photo(photos / "photo.jpg", model="no-such-model")
    with pytest.raises(ValueError, match="nothing.exr"):
        f2l.load_probe(tmp_path / "nothing.exr")


def test_the_readme_figure_is_made_from_a_real_estimate(tmp_path):
    from f2l.dev.readme_figure import make_figure

    out = make_figure(tmp_path / "example.png")
    sheet = np.asarray(Image.open(out))
    assert sheet.ndim == 3 and sheet.shape[0] > 200 and sheet.shape[1] > 600
    assert (Path(__file__).resolve().parents[1] / "docs" / "example.png").is_file()


def test_the_faces_of_one_photo_share_one_light_unless_asked_not_to(tmp_path):
    import skimage.data

    a = skimage.data.astronaut()
    Image.fromarray(np.ascontiguousarray(np.concatenate([a, a[:, ::-1]], axis=1))).save(tmp_path / "two.jpg",
                                                                                       quality=92)
    together = f2l.estimate_photo(tmp_path / "two.jpg", model="sh9")
    assert [f.status for f in together] == ["ok", "ok"] and {f.group_size for f in together} == {2}
    assert np.array_equal(together[0].probe, together[1].probe) and together[0].face_box_px != together[1].face_box_px
    alone = f2l.estimate_photo(tmp_path / "two.jpg", model="sh9", joint=False)
    assert {f.group_size for f in alone} == {1} and not np.array_equal(alone[0].probe, alone[1].probe)
