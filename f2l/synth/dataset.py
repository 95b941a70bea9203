"""``f2l eval synth``: synthetic face records with ground-truth probes, written as shards.

Each face is rendered by :func:`f2l.synth.render.make_synthetic_set` (deterministic from the seed)
and stored as a :class:`f2l.io.shards.FaceRecord` plus two side files: the ground-truth probe
(``probes/<face_id>.exr``, float32, same units as the observed pixels) and the 8-bit photo
(``photos/<face_id>.png``), which is also the record's ``source_path``.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from f2l.io.progress import Progress, ProgressCallback
from f2l.lighting.grid import LatLongGrid


def face_id_for(seed: int, index: int) -> str:
    return f"synth-s{seed}-{index:05d}"


SYNTH_FOCAL_LENGTH_MM = 50.0


def camera_exif(focal_px: float):
    """EXIF that records the synthetic pinhole: FocalLength 50 mm and the FocalPlaneXResolution
    (pixels per mm, unit 4 = mm) that makes it ``focal_px`` pixels, as a camera would."""
    from fractions import Fraction

    from PIL import Image
    from PIL.TiffImagePlugin import IFDRational

    exif = Image.Exif()
    exif[0x010F] = "f2l"  # Make
    exif[0x0110] = "synthetic pinhole"  # Model
    ifd = exif.get_ifd(0x8769)
    focal = Fraction(SYNTH_FOCAL_LENGTH_MM).limit_denominator(1000)
    per_mm = Fraction(focal_px / SYNTH_FOCAL_LENGTH_MM).limit_denominator(100000)
    ifd[0x920A] = IFDRational(focal.numerator, focal.denominator)  # FocalLength
    ifd[0xA20E] = IFDRational(per_mm.numerator, per_mm.denominator)  # FocalPlaneXResolution
    ifd[0xA210] = 4  # FocalPlaneResolutionUnit: mm
    return exif


def write_synthetic_shards(
    out: Path,
    n: int = 12,
    seed: int = 0,
    grid: LatLongGrid = LatLongGrid(),
    *,
    noise_sigma: float = 0.002,
    progress: ProgressCallback | None = None,
    records_per_shard: int = 64,
    capture_meta: bool = False,
    **render_options,
) -> dict:
    """Render ``n`` faces into the shard directory ``out``; returns a summary dict.

    ``render_options`` go to :func:`f2l.synth.render.make_synthetic_set` (image_size,
    overcast_fraction, specular, visibility_method, threads, albedo, sun_elevation_range_deg,
    features, gloss: False, the default, renders Lambertian skin, True glossy skin drawn per face);
    the sensor noise defaults to 0.002 here, as a photo has some. The noise is added to the
    linear image before it is sRGB-encoded and rounded to 8 bits, and the records' observed
    pixels are the decoded 8-bit codes. ``capture_meta`` gives each clear-sky record a
    ``meta["capture"]`` (time and place, ``f2l.io.capture.capture_for_elevation``) at which the
    real sun stood at the synthetic sun's elevation, for the estimator's sun prior. ``progress``: a
    callback told of each face written (:mod:`f2l.io.progress`).
    """
    from f2l.io.shards import FaceRecord, ShardWriter
    from f2l.io.side_files import write_side_photo, write_side_probe
    from f2l.io.capture import capture_for_elevation, capture_to_meta
    from f2l.synth.render import make_synthetic_set

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    pixels = []
    faces = make_synthetic_set(n, grid, seed, noise_sigma=noise_sigma, **render_options)
    bar = Progress(progress, "synth", "face", n)
    kinds = {"clear": 0, "overcast": 0}
    with ShardWriter(out, records_per_shard=records_per_shard, overwrite=True) as writer:
        for i, face in enumerate(faces):
            face_id = face_id_for(seed, i)
            probe_rel = write_side_probe(out, face_id, face.gt_probe)
            photo_rel = write_side_photo(out, face_id, face.photo_srgb,
                                         exif=camera_exif(face.meta["focal_px"]))
            meta = dict(face.meta)
            meta["albedo"] = [float(v) for v in face.albedo]
            sun_elevation_deg = meta.get("sky", {}).get("sun_elevation_deg")
            if capture_meta and sun_elevation_deg is not None:
                meta.update(capture_to_meta(capture_for_elevation(math.radians(sun_elevation_deg))))
            kinds[meta.get("sky", {}).get("kind", "clear")] = kinds.get(meta.get("sky", {}).get("kind", "clear"), 0) + 1
            writer.write(
                FaceRecord(
                    face_id=face_id, source_path=photo_rel, face_index=0,
                    image_height=face.photo_srgb.shape[0], image_width=face.photo_srgb.shape[1],
                    pixel_rc=face.pixel_rc, points=face.points, normals=face.normals,
                    observed_rgb=face.observed_rgb, mask=face.mask, grid_height=grid.height,
                    grid_width=grid.width, visibility_bits=face.visibility_bits,
                    visibility_method=face.visibility_method, gt_probe_path=probe_rel,
                    photo_path=photo_rel, meta=meta,
                )
            )
            pixels.append(face.num_pixels)
            bar.advance()
    elapsed = time.perf_counter() - t0
    return {
        "out": str(out),
        "faces": len(pixels),
        "skies": kinds,
        "grid": f"{grid.height}x{grid.width}",
        "face_pixels_mean": float(np.mean(pixels)) if pixels else 0.0,
        "elapsed_s": round(elapsed, 3),
        "seconds_per_face": round(elapsed / max(1, len(pixels)), 3),
    }
