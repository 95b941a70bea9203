"""f2l from Python: a photo in, a probe per face out, in memory (Jupyter, Blender, Nuke).

    import f2l
    for face in f2l.estimate_photo("portrait.jpg", model="sunsky"):
        print(face.status, face.sun_elevation_deg, face.sun_azimuth_deg)
        if face.ok:
            face.save_exr(f"probe-{face.face_index}.exr")

:func:`estimate_photo` runs what ``f2l estimate photo.jpg`` runs (the default pipeline's fit-faces
and transport parameters, the model's default estimator settings, the sun prior from EXIF time and
GPS where present), without writing anything. :func:`load_probe` reads a probe that f2l or anyone
wrote (EXR, Radiance HDR, PFM, float TIFF). Probes are lat-long arrays (H, W, 3) float32, linear
Rec.709, row 0 the zenith and the centre column the camera's viewing direction
(docs/conventions.md); in cd/m² where the photo's EXIF gives its exposure, else relative to the
photo's linear values (``FaceEstimate.units`` says which).
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["FaceEstimate", "estimate_photo", "load_probe"]


@dataclass(frozen=True)
class FaceEstimate:
    """One face of a photo and its light. ``status`` is ``"ok"``, a refusal of the face
    (``too_small``, ``cut_off``, ``blurred``, ``profile``, ``clipped``, ``too_few_pixels``) or
    ``bad_face``/``error``; ``message`` says why. ``probe`` is None unless ``ok``."""

    source_path: str
    face_index: int
    model: str
    status: str
    message: str
    probe: np.ndarray | None = None
    sun_direction: np.ndarray | None = None
    params: dict = field(default_factory=dict)
    albedo: tuple[float, float, float] | None = None
    units: str = ""
    face_box_px: tuple[float, float, float, float] | None = None
    group_size: int = 1  # faces of the photo that shared the light (joint=True); 1: the face alone
    agreement: float | None = None  # how well the face agrees with the shared light (1 = fully)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def sun_elevation_deg(self) -> float | None:
        """Elevation of the sun above the horizon (degrees), where the model has a sun."""
        if self.sun_direction is None:
            return None
        return math.degrees(math.asin(float(np.clip(self.sun_direction[1], -1.0, 1.0))))

    @property
    def sun_azimuth_deg(self) -> float | None:
        """Azimuth of the sun (degrees, 0 = toward the camera's viewing direction -Z, +90 = +X)."""
        if self.sun_direction is None:
            return None
        x, _, z = (float(v) for v in self.sun_direction)
        return math.degrees(math.atan2(x, -z))

    def save_exr(self, path: str | os.PathLike) -> Path:
        """Write the probe as a float32 EXR (atomic); returns the path. ValueError when not ``ok``."""
        from f2l.io.exr import write_exr

        if self.probe is None:
            raise ValueError(f"{self.source_path} face {self.face_index}: no probe ({self.status}: {self.message})")
        write_exr(path, self.probe, metadata={"f2l_model": self.model, "f2l_source": str(self.source_path),
                                              "f2l_units": self.units,
                                              "f2l_convention": "latlong,+Y up,centre=-Z"})
        return Path(path)


def load_probe(path: str | os.PathLike) -> np.ndarray:
    """A probe file as (H, W, 3) float32 (EXR, Radiance HDR, PFM, float TIFF); ValueError naming
    the file when it cannot be read."""
    from f2l.io.probe_io import read_hdr_image

    return read_hdr_image(path)


def estimate_photo(path: str | os.PathLike, model: str = "sunsky", *,
                   min_face_px: float | None = None, joint: bool = True) -> list[FaceEstimate]:
    """Every face of one photo (JPEG, PNG, TIFF or camera RAW), each with the light ``model``
    estimates from it, in the detector's order (module doc). With ``joint`` the faces share one
    light (f2l.estimate.joint; a face that disagrees keeps its own, and its message says why);
    ``joint=False`` estimates each face alone. A photo that cannot be read raises
    :class:`f2l.io.photo.core.PhotoError` (a ValueError naming it); an unknown model raises
    :class:`f2l.models.registry.ModelNotFoundError`. A photo without a face gives an empty list."""
    from f2l.face.fit import FaceFit, face_record, fit_photo_faces, landmark_box
    from f2l.face.landmarker import FaceLandmarker
    from f2l.io.photo import load_photo
    from f2l.models.registry import model_class
    from f2l.pipeline.faces import fit_options
    from f2l.pipeline.spec import load_pipeline

    model_class(model)  # an unknown model fails before any work
    spec = load_pipeline()
    fit = dict(spec.params("fit-faces"))
    if min_face_px is not None:
        fit["min_face_px"] = float(min_face_px)
    options = fit_options(fit, spec.params("transport"), (spec.grid_height, spec.grid_width))
    photo = load_photo(path)
    out, fitted = [], []
    for found in fit_photo_faces(photo, FaceLandmarker(), options):
        if not isinstance(found, FaceFit):
            out.append(FaceEstimate(str(path), found.face_index, model, found.reason, found.message,
                                    face_box_px=found.box))
            continue
        record = face_record(found, photo, f"{Path(path).stem}-{found.face_index}", options,
                             source_path=str(path))
        fitted.append((len(out), record, landmark_box(found.landmarks)))
        out.append(None)
    shared = _estimate_together([r for _, r, _ in fitted], model) if joint and len(fitted) > 1 else {}
    for slot, record, box in fitted:
        together = shared.get(record.face_id)
        out[slot] = _estimate(record, model, box) if together is None else dataclasses.replace(
            together, face_box_px=tuple(box))
    return out


def _estimate_together(records, model_name: str) -> dict[str, FaceEstimate]:
    """The faces that share the joint light, by face id (the others are left to :func:`_estimate`)."""
    from f2l.estimate.config import EstimatorConfig
    from f2l.estimate.joint import JointUnsupported, estimate_joint
    from f2l.estimate.observation import EstimationError, FaceObservation
    from f2l.estimate.record import _get_model, capture_sun_prior, record_absolute_scale
    from f2l.lighting.grid import LatLongGrid
    from f2l.models.capabilities import SunAngles

    cfg = EstimatorConfig()
    grid = LatLongGrid(records[0].grid_height, records[0].grid_width)
    model = _get_model(model_name, grid)
    if cfg.sun_prior_from_capture and isinstance(model, SunAngles):
        prior, _ = capture_sun_prior(records[0], cfg.sun_prior_sigma_rad)
        cfg = cfg if prior is None else dataclasses.replace(cfg, sun_elevation_prior=prior)
    observations = [FaceObservation(r.normals, r.observed_rgb, r.mask, r.visibility_bits, grid, r.face_id, r.points)
                    for r in records]
    try:
        joint = estimate_joint(observations, model, cfg, pixel_rc=[r.pixel_rc for r in records])
    except (JointUnsupported, EstimationError):
        return {}
    result, (scale, _) = joint.result, record_absolute_scale(records[0])
    probe = result.probe if scale is None else (result.probe * scale).astype(np.float32)
    used = sum(s.used for s in joint.faces)
    out = {}
    for record, share in zip(records, joint.faces):
        if not share.used:
            continue
        out[record.face_id] = FaceEstimate(
            source_path=record.source_path, face_index=record.face_index, model=model_name, status="ok",
            message=f"one light for {used} of {len(records)} faces", probe=np.asarray(probe, np.float32),
            sun_direction=None if result.sun_direction is None else np.asarray(result.sun_direction, float),
            params=dict(zip(result.param_names, (float(v) for v in result.params))),
            albedo=tuple(float(v) for v in share.albedo), group_size=len(records), agreement=share.agreement,
            units="relative: the photo's linear values (1 = full scale)" if scale is None else "cd/m2")
    return out


def _estimate(record, model_name: str, box) -> FaceEstimate:
    """One record's estimate in memory (what :func:`f2l.estimate.record.estimate_record` writes)."""
    from f2l.estimate.config import EstimatorConfig
    from f2l.estimate.record import estimate_in_memory

    result, scale, _, status, message, _ = estimate_in_memory(record, model_name, EstimatorConfig())
    base = dict(source_path=record.source_path, face_index=record.face_index, model=model_name,
                face_box_px=tuple(box))
    if result is None:
        return FaceEstimate(status=status, message=message, **base)
    probe = result.probe if scale is None else (result.probe * scale).astype(np.float32)
    return FaceEstimate(
        status="ok", message=message, probe=np.asarray(probe, np.float32),
        sun_direction=None if result.sun_direction is None else np.asarray(result.sun_direction, float),
        params=dict(zip(result.param_names, (float(v) for v in result.params))),
        albedo=tuple(float(v) for v in result.albedo),
        units="relative: the photo's linear values (1 = full scale)" if scale is None else "cd/m2", **base)
