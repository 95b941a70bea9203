"""Real outdoor HDR maps for the realistic face renderer (``f2l eval render-faces``).

The maps are ten CC0 lat-long EXRs of the npm package ``@pmndrs/assets`` 1.7.0
(``hdri/NAME.exr.js``: ``export default 'data:application/exr;base64,…'``; 512 × 256, half float,
DWAB-compressed). :func:`import_pmndrs` decodes them once into ``f2l/render/data/hdri/NAME.exr``
(float32, ZIP) and they ship with f2l; nothing is fetched at run time. DWAB is lossy: around each
sun its 8 × 8 cosine blocks ring, with negative texels down to −0.3 × the peak.
:func:`repair_ringing` replaces each ringing patch by its surroundings' level plus its positive
part scaled so that the patch keeps its signed energy Σ L dω (clamping alone would add the
positive side lobes' energy). Re-create them with
``make hdri-import`` (``npm pack @pmndrs/assets@1.7.0``).

Two sets: :data:`OUTDOOR_MAPS`, the seven that ``make eval-real`` draws from (its tuning part has
chosen f2l's defaults), and :data:`HELD_OUT_MAPS`, the package's three other outdoor daylight maps
(``city``: overcast, buildings; ``sunrise``: a field, sun at 8°; ``sunset``: a square by the
water, sun at 3°), which no default was chosen on (``make eval-real-heldout``). The package's
other maps are interiors or night.

Their lat-long layout is f2l's (``docs/conventions.md``): row 0 is the zenith, the sky is the
upper half. Their azimuth origin is arbitrary, and the renderer turns each map by a random angle
about +Y anyway (:func:`f2l.lighting.grid.rotate_y`).
"""

from __future__ import annotations

import base64
import tarfile
import tempfile
from importlib import resources
from pathlib import Path

import numpy as np

__all__ = ["HELD_OUT_MAPS", "MAP_SETS", "OUTDOOR_MAPS", "PMNDRS_VERSION", "hdri_path", "import_pmndrs", "load_map",
           "repair_ringing"]

PMNDRS_VERSION = "1.7.0"
# The outdoor daylight maps of the package: the evaluation's seven, and three held out from every
# choice of f2l's defaults (module docstring).
OUTDOOR_MAPS = ("bridge", "dawn", "esplanade", "forest", "park", "sky", "venice")
HELD_OUT_MAPS = ("city", "sunrise", "sunset")
MAP_SETS = {"eval": OUTDOOR_MAPS, "held-out": HELD_OUT_MAPS}


def hdri_path(name: str) -> Path:
    """Path of the shipped map ``name`` (one of :data:`OUTDOOR_MAPS` or :data:`HELD_OUT_MAPS`)."""
    known = OUTDOOR_MAPS + HELD_OUT_MAPS
    if name not in known:
        raise ValueError(f"unknown HDR map {name!r}; one of {', '.join(known)}")
    return Path(str(resources.files("f2l.render").joinpath("data", "hdri", f"{name}.exr")))


def load_map(name: str) -> np.ndarray:
    """The shipped map ``name`` as (256, 512, 3) float32 linear radiance, f2l's lat-long layout."""
    from f2l.io.exr import read_exr

    path = hdri_path(name)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing; run `make hdri-import` to re-create the shipped maps")
    return read_exr(path)


def decode_js_module(text: str, source: str = "<js>") -> bytes:
    """The EXR bytes of a ``@pmndrs/assets`` module (a base64 data URL as its default export)."""
    marker = "base64,"
    start = text.find(marker)
    if start < 0:
        raise ValueError(f"{source}: no base64 data URL")
    payload = text[start + len(marker):]
    end = min((i for i in (payload.find("'"), payload.find('"'), payload.find("`")) if i >= 0), default=-1)
    if end < 0:
        raise ValueError(f"{source}: unterminated data URL")
    return base64.b64decode(payload[:end], validate=True)


def repair_ringing(image: np.ndarray, negative_below: float = -1e-3, grow: int = 2) -> np.ndarray:
    """Remove DWAB's ringing around bright sources, keeping each patch's energy (see module doc).

    A patch is a connected set of texels within ``grow`` texels of a negative one (luminance below
    ``negative_below``). Per channel: level b = 25th percentile of the patch's outer ring (≥ 0),
    out = b + s·max(L − b, 0) with s ≥ 0 chosen so Σ out·dω = Σ L·dω (s = 0 if that is below b's).
    Texels outside patches are clamped at 0. Returns float32 (H, W, 3).
    """
    from scipy import ndimage

    from f2l.lighting.grid import LatLongGrid

    img = np.nan_to_num(np.asarray(image, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    h, w = img.shape[:2]
    d_omega = LatLongGrid(h, w).solid_angles[:, :, None]
    negative = img.mean(axis=-1) < negative_below
    patches, n = ndimage.label(ndimage.binary_dilation(negative, iterations=grow))
    out = np.clip(img, 0.0, None)
    for k in range(1, n + 1):
        inside = patches == k
        ring = ndimage.binary_dilation(inside) & ~inside
        level = np.clip(np.percentile(img[ring], 25, axis=0), 0.0, None) if ring.any() else np.zeros(3)
        values, weights = img[inside], d_omega[inside]
        energy = (values * weights).sum(axis=0)
        excess = np.clip(values - level, 0.0, None)
        excess_energy = (excess * weights).sum(axis=0)
        scale = np.where(excess_energy > 0, np.clip(energy - level * weights.sum(), 0.0, None)
                         / np.maximum(excess_energy, 1e-300), 0.0)
        out[inside] = level + excess * scale
    return out.astype(np.float32)


def import_pmndrs(package: Path, out_dir: Path, names=OUTDOOR_MAPS + HELD_OUT_MAPS) -> list[Path]:
    """Decode ``hdri/NAME.exr.js`` of an unpacked ``@pmndrs/assets`` (a folder or its ``npm pack``
    tarball) into float32 ZIP EXRs ``out_dir/NAME.exr``; returns the written paths."""
    from f2l.io.exr import read_exr, write_exr

    package, out_dir = Path(package), Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    with tempfile.TemporaryDirectory() as tmp:
        root = package
        if package.is_file():
            with tarfile.open(package) as tar:
                tar.extractall(tmp, filter="data")
            root = Path(tmp) / "package"
        for name in names:
            js = root / "hdri" / f"{name}.exr.js"
            raw = Path(tmp) / f"{name}.exr"
            raw.write_bytes(decode_js_module(js.read_text(), str(js)))
            image = repair_ringing(read_exr(raw))
            target = out_dir / f"{name}.exr"
            write_exr(target, image.astype(np.float32),
                      {"f2l_source": f"@pmndrs/assets {PMNDRS_VERSION} hdri/{name}.exr.js (CC0-1.0)"})
            written.append(target)
    return written
