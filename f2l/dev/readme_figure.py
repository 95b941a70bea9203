"""The README's picture: a real photo (scikit-image's public-domain astronaut), the probe f2l
estimates from its face (sunsky), and a diffuse sphere on a plane lit by that probe.
``make readme-figure`` writes ``docs/example.png``."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parents[2] / "docs" / "example.png"


def make_figure(out: Path = OUT) -> Path:
    import tempfile

    from PIL import Image, ImageDraw

    try:
        import skimage.data
    except ImportError as exc:  # scikit-image ships the photo; it is a test extra, not a dependency
        raise RuntimeError("make readme-figure needs scikit-image (pip install 'f2l[test]')") from exc

    import f2l
    from f2l.io.preview import contact_sheet, save_png, tonemap
    from f2l.metrics.scene import render_scene

    photo = skimage.data.astronaut()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "astronaut.png"
        Image.fromarray(photo).save(path)
        (face,) = [f for f in f2l.estimate_photo(path, model="sunsky") if f.ok]
    framed = Image.fromarray(photo)
    ImageDraw.Draw(framed).rectangle(face.face_box_px, outline=(40, 220, 60), width=3)
    image, mask = render_scene(face.probe)
    relit = tonemap(np.where(mask[..., None], image, 0.0))
    sheet = contact_sheet([[("photo (face found)", np.asarray(framed)),
                            (f"estimated probe (sun {face.sun_elevation_deg:.0f}° up)", tonemap(face.probe)),
                            ("an object lit by it", relit)]], cell_height=200)
    save_png(out, sheet)
    return out


if __name__ == "__main__":
    sys.stdout.write(f"wrote {make_figure()}\n")
