"""A render-faces-like folder for the evaluation commands' tests, made without a renderer: one
photo of two people (scikit-image's astronaut and her mirror image) under a known clear sky, its
true probe, the render meta with both true face boxes, and the photo fitted by ``f2l fit-faces``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

CASE = "pbr-group-s0-00001"


def astronaut_pair_render(tmp_path: Path, **meta) -> tuple[Path, Path]:
    """(render folder, fitted shards) of the two-astronaut photo; ``meta`` adds render-meta keys
    (e.g. ``shaded_person=1``). Skips the test where scikit-image is missing."""
    import pytest

    skdata = pytest.importorskip("skimage.data")
    from typer.testing import CliRunner

    from f2l.cli import app
    from f2l.dev.bench_detect import ASTRONAUT_FACE
    from f2l.io.exr import write_exr
    from f2l.lighting.grid import LatLongGrid, direction_from_angles
    from f2l.synth.skies import clear_sky

    render = tmp_path / "render"
    for sub in ("photos", "meta", "probes"):
        (render / sub).mkdir(parents=True)
    a = skdata.astronaut()
    Image.fromarray(np.ascontiguousarray(np.concatenate([a, a[:, ::-1]], axis=1))).save(
        render / "photos" / f"{CASE}.jpg", quality=95)
    grid = LatLongGrid(32, 64)
    sun = direction_from_angles(np.radians(40.0), np.radians(30.0))
    write_exr(render / "probes" / f"{CASE}.exr", clear_sky(grid, np.radians(40.0), np.radians(30.0)).astype(np.float32))
    boxes = [ASTRONAUT_FACE.tolist(), [1024 - ASTRONAUT_FACE[2], ASTRONAUT_FACE[1], 1024 - ASTRONAUT_FACE[0],
                                       ASTRONAUT_FACE[3]]]
    faces = [{"box": [float(v) for v in b], "width_px": float(b[2] - b[0]), "in_frame": True,
              "pose": {"yaw_deg": 0.0}} for b in boxes]
    (render / "meta" / f"{CASE}.json").write_text(json.dumps({
        "face_id": CASE, "framing": "group", "faces": faces, **meta,
        "sky": {"kind": "clear", "sun_direction": [float(v) for v in sun]}}))
    fitted = tmp_path / "fitted"
    res = CliRunner().invoke(app, ["fit-faces", str(render / "photos"), "--out", str(fitted), "--grid", "32x64",
                                   "--json"])
    assert res.exit_code == 0, res.output
    return render, fitted
