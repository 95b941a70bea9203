"""Absolute light from a photo's exposure (f2l.io.exposure) and its way into the estimates."""

from __future__ import annotations

import math

import numpy as np
import pytest

from f2l.io.exposure import MIDDLE_GREY, REFLECTED_LIGHT_K, absolute_scale, ev100


def test_the_meter_equation_puts_an_average_scene_at_middle_grey():
    """Sunny 16: f/16, 1/100 s, ISO 100 is EV100 ~14.6; the metered average luminance
    K N^2 / (t S) = 12.5 * 256 * 100 / 100 = 3200 cd/m2 lands at linear 0.18."""
    scale, source = absolute_scale({"exposure_s": 0.01, "f_number": 16.0, "iso": 100.0})
    assert scale * MIDDLE_GREY == pytest.approx(REFLECTED_LIGHT_K * 16.0 ** 2 / (0.01 * 100.0), rel=1e-12)
    assert scale * MIDDLE_GREY == pytest.approx(3200.0)
    assert ev100(0.01, 16.0, 100.0) == pytest.approx(math.log2(25600.0))
    assert "EV100 14.64" in source and "K = 12.5" in source
    # a stop more light to the sensor (twice the time) means half the scene luminance per value
    assert absolute_scale({"exposure_s": 0.02, "f_number": 16.0, "iso": 100.0})[0] == pytest.approx(scale / 2)
    assert absolute_scale({"exposure_s": 0.01, "f_number": 16.0, "iso": 200.0})[0] == pytest.approx(scale / 2)


@pytest.mark.parametrize("exif, words", [
    (None, "EXIF lacks ExposureTime, FNumber, ISOSpeedRatings"),
    ({"exposure_s": 0.01, "f_number": 8.0}, "EXIF lacks ISOSpeedRatings"),
    ({"exposure_s": 0.0, "f_number": 8.0, "iso": 100}, "ExposureTime 0 outside (0, 3600]"),
    ({"exposure_s": float("nan"), "f_number": 8.0, "iso": 100}, "ExposureTime nan"),
    ({"exposure_s": 0.01, "f_number": 1e9, "iso": 100}, "FNumber 1e+09 outside [0.5, 128]"),
    ({"exposure_s": 0.01, "f_number": 8.0, "iso": "abc"}, "ISOSpeedRatings nan"),
])
def test_missing_or_absurd_exposure_leaves_the_probe_relative_and_says_why(exif, words):
    scale, source = absolute_scale(exif)
    assert scale is None and source.startswith("relative") and words in source, source


def test_estimate_writes_the_probe_in_cd_m2_where_the_photo_states_its_exposure(tmp_path):
    """The astronaut with EXIF (1/200 s, f/8, ISO 100) and without: the same estimate, the one
    probe file in cd/m2 (scale 12.5 * 64 / (0.005 * 100 * 0.18) = 8889), the other relative; the
    table and the EXR header say which and why."""
    skdata = pytest.importorskip("skimage.data")
    import json

    import OpenEXR
    import pyarrow.parquet as pq
    from PIL import Image
    from typer.testing import CliRunner

    from f2l.cli import app
    from f2l.io.exr import read_exr

    exif = Image.Exif()
    ifd = exif.get_ifd(0x8769)
    ifd[33434] = 1 / 200  # ExposureTime
    ifd[33437] = 8.0  # FNumber
    ifd[34855] = 100  # ISOSpeedRatings
    Image.fromarray(skdata.astronaut()).save(tmp_path / "with_exif.jpg", quality=95, exif=exif)
    Image.fromarray(skdata.astronaut()).save(tmp_path / "without.jpg", quality=95)
    res = CliRunner().invoke(app, ["estimate", str(tmp_path / "with_exif.jpg"), str(tmp_path / "without.jpg"),
                                   "-m", "sh9", "--out", str(tmp_path / "est"), "--json"])
    assert res.exit_code == 0, res.output
    rows = {r["source_path"].rsplit("/", 1)[-1]: r for r in pq.read_table(tmp_path / "est" / "estimates.parquet").to_pylist()}
    want = 12.5 * 64 / (0.005 * 100 * 0.18)
    assert rows["with_exif.jpg"]["absolute_scale_cd_m2"] == pytest.approx(want, rel=1e-9)
    assert "t = 0.005 s, f/8, ISO 100" in rows["with_exif.jpg"]["absolute_scale_source"]
    assert rows["without.jpg"]["absolute_scale_cd_m2"] is None
    assert "EXIF lacks" in rows["without.jpg"]["absolute_scale_source"]
    absolute = read_exr(tmp_path / "est" / rows["with_exif.jpg"]["probe_path"])
    relative = read_exr(tmp_path / "est" / rows["without.jpg"]["probe_path"])
    np.testing.assert_allclose(absolute, relative * want, rtol=1e-5, atol=1e-3)
    header = OpenEXR.File(str(tmp_path / "est" / rows["with_exif.jpg"]["probe_path"])).header()
    assert header["f2l_units"].startswith("cd/m2") and float(header["f2l_absolute_scale_cd_m2"]) == pytest.approx(want)
    assert json.loads(res.stdout)["ok"] == 2
