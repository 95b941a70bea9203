"""Mitsuba 3 scenes for the realistic face renderer: a head under an HDR map or a Hosek–Wilkie sky.

Everything is in f2l's camera frame (``docs/conventions.md``: +Y up, the camera at +Z looking
along −Z, cm). Two kinds of lighting:

- :class:`MapLighting`: a lat-long radiance map in f2l's layout (any size). Mitsuba's ``envmap``
  puts the map's u = 0 at f2l's u = 0.5 (measured: ``tests/test_render.py`` checks a one-texel
  light and a rendered sun-lit face), so the map is handed over rolled by half its width.
- :class:`SunSkyLighting`: Mitsuba's ``sunsky`` (Hosek–Wilkie 2012 sky and a sun disc of
  0.5358°), whose own frame is +Z up (``to_world`` turns it to +Y up; its ``sun_direction`` is
  then in world coordinates). Its sky is evaluated into a map with a lit Lambertian ground below
  the horizon, and its sun, integrated over the disc, becomes a directional light.

:func:`ground_truth_probe` gives the probe a case is judged against, on f2l's grid: the area
average of the map the renderer used, and for the sky model the sun's integrated power in its
texel.

An occluder (``render_head(..., occluders=...)``) is a dark diffuse disc (reflectance
:data:`OCCLUDER_REFLECTANCE`) in the scene: it casts a shadow and is seen by the camera where it is
in the frame (``f2l eval render-faces --shade-one``, :mod:`f2l.render.occluder`).

The integrator is Mitsuba's ``path`` (max depth 6: skin–skin, skin–shoulder bounces);
``max_depth=2`` is direct light only (the "no interreflection" ablation). An ``aov`` pass of depth
gives the head's image mask.

References
----------
- Hosek, Wilkie. "An Analytic Model for Full Spectral Sky-Dome Radiance." ACM Transactions on
  Graphics 31(4) (SIGGRAPH 2012) (the sky of Mitsuba 3's ``sunsky``, used here, not reimplemented).
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from f2l.render.heads import PART_CAVITY, PART_EYE, PART_HAIR, PART_SHIRT, PART_SKIN, Head

__all__ = ["MapLighting", "SunSkyLighting", "RenderSettings", "ground_truth_probe", "render_head"]

SUN_APERTURE_DEG = 0.5358  # Mitsuba's sunsky default: the sun's angular diameter
OCCLUDER_REFLECTANCE = 0.04  # a dark board


def mitsuba():
    """The ``mitsuba`` module in its ``scalar_rgb`` variant (CPU, no LLVM or CUDA needed)."""
    try:
        import mitsuba as mi
    except ImportError as exc:
        from f2l.render import RenderExtraMissing

        raise RenderExtraMissing(exc) from exc

    if mi.variant() is None or not mi.variant().startswith("scalar_rgb"):
        mi.set_variant("scalar_rgb")
    return mi


@dataclass
class MapLighting:
    """A lat-long radiance map (H, W, 3) in f2l's layout, linear Rec.709."""

    radiance: np.ndarray
    name: str = "map"

    def emitters(self, mi) -> dict:
        rolled = np.roll(np.asarray(self.radiance, dtype=np.float32), self.radiance.shape[1] // 2, axis=1)
        return {"sky": {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(rolled))}}


@dataclass
class SunSkyLighting:
    """Hosek–Wilkie sky + sun (Mitsuba ``sunsky``), sun direction in f2l's frame, over a ground.

    Rendered as two emitters: the sky (and the Lambertian ground it and the sun light, ρ_g E_h / π,
    below the horizon) as an ``envmap`` of :attr:`MAP_SHAPE` texels evaluated from ``sunsky``, and
    the sun as a ``directional`` emitter carrying the sun disc's integrated radiance. (A ground
    disk in the scene went black near the horizon: float32 self-intersection kilometres away.)
    """

    sun_direction: np.ndarray
    turbidity: float
    ground_albedo: float
    MAP_SHAPE = (256, 512)

    def _emitter(self, mi, sun_scale=1.0, sky_scale=1.0) -> dict:
        return {"type": "sunsky", "sun_direction": [float(c) for c in self.sun_direction],
                "turbidity": float(self.turbidity), "albedo": float(self.ground_albedo),
                "sun_scale": float(sun_scale), "sky_scale": float(sky_scale),
                "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90)}

    def sun_power(self) -> np.ndarray:
        """∫ L_sun dω over the sun's disc (RGB): the irradiance it gives a surface facing it."""
        if not hasattr(self, "_sun_power"):
            self._sun_power = _sun_power(self, mitsuba())
        return self._sun_power

    def sky_map(self) -> np.ndarray:
        """Sky radiance above the horizon, lit ground below, on a :attr:`MAP_SHAPE` lat-long grid."""
        from f2l.lighting.grid import LatLongGrid

        if hasattr(self, "_sky_map"):
            return self._sky_map
        mi = mitsuba()
        grid = LatLongGrid(*self.MAP_SHAPE)
        h = grid.height
        sky = mi.load_dict(self._emitter(mi, sun_scale=0.0))
        radiance = np.zeros(grid.shape + (3,))
        radiance[: h // 2] = _eval(sky, mi, grid.directions[: h // 2].reshape(-1, 3)).reshape(h // 2, grid.width, 3)
        up = np.clip(grid.directions[: h // 2, :, 1], 0.0, None)
        sky_irradiance = (radiance[: h // 2] * (up * grid.solid_angles[: h // 2])[..., None]).sum(axis=(0, 1))
        sun_irradiance = self.sun_power() * max(float(np.asarray(self.sun_direction)[1]), 0.0)
        radiance[h // 2:] = self.ground_albedo * (sky_irradiance + sun_irradiance) / np.pi
        self._sky_map = radiance
        return radiance

    def emitters(self, mi) -> dict:
        sun = np.asarray(self.sun_direction, dtype=np.float64)
        return {**MapLighting(self.sky_map().astype(np.float32)).emitters(mi),
                "sun": {"type": "directional", "direction": [float(c) for c in -sun],
                        "irradiance": {"type": "rgb", "value": [float(c) for c in self.sun_power()]}}}


def _eval(emitter, mi, directions: np.ndarray) -> np.ndarray:
    si = mi.SurfaceInteraction3f()
    out = np.empty((len(directions), 3))
    for i, d in enumerate(directions):
        si.wi = mi.ScalarVector3f(-d[0], -d[1], -d[2])
        out[i] = emitter.eval(si)
    return out


def _sun_power(lighting: SunSkyLighting, mi, n: int = 48) -> np.ndarray:
    """∫ L_sun dω (RGB) over the sun's disc, on an n × n tangent-plane grid 1.3 × its diameter wide."""
    emitter = mi.load_dict(lighting._emitter(mi, sky_scale=0.0))
    d = np.asarray(lighting.sun_direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    a = np.cross(d, [0.0, 1.0, 0.0] if abs(d[1]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(d, a)
    half = np.radians(SUN_APERTURE_DEG) * 0.65
    t = (np.arange(n) + 0.5) / n * 2 * half - half
    ta, tb = np.meshgrid(t, t, indexing="ij")
    dirs = d + ta[..., None] * a + tb[..., None] * b
    norm = np.linalg.norm(dirs, axis=-1, keepdims=True)
    dirs = (dirs / norm).reshape(-1, 3)
    d_omega = ((2 * half / n) ** 2 / norm[..., 0] ** 3).reshape(-1)  # gnomonic projection's Jacobian
    return (_eval(emitter, mi, dirs) * d_omega[:, None]).sum(axis=0)


def ground_truth_probe(lighting, grid) -> np.ndarray:
    """The lighting as a probe (H, W, 3) float64 on ``grid``: the area average of the map the
    renderer used, plus for the sky model the sun's power in the texel of its direction."""
    from f2l.lighting.resample import resample

    if isinstance(lighting, MapLighting):
        return resample(np.asarray(lighting.radiance, dtype=np.float64), grid.height, grid.width)
    probe = resample(lighting.sky_map(), grid.height, grid.width)
    row, col = grid.direction_to_texel(np.asarray(lighting.sun_direction, dtype=np.float64))
    probe[int(row), int(col)] += lighting.sun_power() / grid.solid_angles[int(row), int(col)]
    return probe


@dataclass
class RenderSettings:
    """Camera, sampling and material switches of one render."""

    width_px: int = 384
    height_px: int = 384
    fov_x_deg: float = 40.0
    camera_distance_cm: float = 60.0
    spp: int = 64
    max_depth: int = 6
    specular: bool = True
    skin_roughness: float = 0.5
    skin_specular: float = 0.45
    seed: int = 0


def _write_ply(path: Path, head: Head, faces_mask: np.ndarray) -> None:
    faces = head.faces[faces_mask]
    used = np.unique(faces)
    remap = np.full(len(head.vertices), -1)
    remap[used] = np.arange(len(used))
    vert = np.concatenate([head.vertices[used], head.normals[used], head.albedo[used]], axis=1).astype("<f4")
    face = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"], face["i"] = 3, remap[faces]
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(used)}\n"
              + "".join(f"property float {p}\n" for p in ("x", "y", "z", "nx", "ny", "nz", "r", "g", "b"))
              + f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vert.tobytes())
        fh.write(face.tobytes())


def _bsdf(kind: str, settings: RenderSettings) -> dict:
    colour = {"type": "mesh_attribute", "name": "vertex_color"}
    if not settings.specular or kind == "diffuse":
        return {"type": "diffuse", "reflectance": colour}
    roughness, specular = {"skin": (settings.skin_roughness, settings.skin_specular), "hair": (0.6, 0.5),
                           "eye": (0.08, 0.5)}[kind]
    return {"type": "principled", "base_color": colour, "roughness": float(roughness),
            "specular": float(specular)}


def _disc(mi, disc: dict) -> dict:
    """A Mitsuba ``disk`` (unit disc in its XY plane, normal +Z) moved to ``disc``'s centre, normal and radius."""
    c = np.asarray(disc["center_cm"], np.float64)
    n = np.asarray(disc["normal"], np.float64)
    up = [0.0, 1.0, 0.0] if abs(n[1]) < 0.9 else [1.0, 0.0, 0.0]
    r = float(disc["radius_cm"])
    to_world = mi.ScalarTransform4f().look_at(origin=c.tolist(), target=(c + n).tolist(), up=up).scale([r, r, 1.0])
    return {"type": "disk", "to_world": to_world,
            "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb",
                                                                                      "value": [OCCLUDER_REFLECTANCE] * 3}}}}


def head_parts(head: Head) -> dict[str, np.ndarray]:
    """The triangles of each material of ``head`` (``skin``, ``hair``, ``eye``, ``diffuse``: shirt
    and cavities), as boolean masks over its faces; :func:`_bsdf` gives each its BSDF."""
    return {"skin": np.isin(head.part, [PART_SKIN]), "hair": head.part == PART_HAIR,
            "eye": head.part == PART_EYE, "diffuse": np.isin(head.part, [PART_SHIRT, PART_CAVITY])}


def sensor_dict(mi, settings: RenderSettings, pixel_format: str = "rgba", crop_px=None,
                sampler: str = "independent") -> dict:
    """The pinhole camera of ``settings`` (at +Z ``camera_distance_cm``, looking at the origin) as a
    Mitsuba dict; ``crop_px`` (x0, y0, x1, y1) renders only that window of the frame; ``sampler``
    a Mitsuba sampler plugin."""
    film = {"type": "hdrfilm", "width": int(settings.width_px), "height": int(settings.height_px),
            "pixel_format": pixel_format, "rfilter": {"type": "gaussian"}}
    if crop_px is not None:
        x0, y0, x1, y1 = (int(v) for v in crop_px)
        film.update(crop_offset_x=x0, crop_offset_y=y0, crop_width=x1 - x0, crop_height=y1 - y0)
    return {"type": "perspective", "fov": float(settings.fov_x_deg), "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, settings.camera_distance_cm],
                                                      target=[0, 0, 0], up=[0, 1, 0]),
            "film": film,
            "sampler": {"type": sampler, "sample_count": int(settings.spp),
                        "seed": int(settings.seed) % (2**31)}}


def render_head(head: Head, lighting, settings: RenderSettings, occluders=()) -> dict:
    """Path-trace ``head`` (already posed) under ``lighting``, with ``occluders``: discs
    ``{"center_cm": (3,), "normal": (3,), "radius_cm": r}`` in the same frame.

    Returns ``{"image": (H, W, 3) float32 linear radiance, "depth_cm": (H, W) float32 (0 where
    the ray leaves the scene), "focal_px": float}``.
    """
    mi = mitsuba()
    scene: dict = {
        "type": "scene",
        "integrator": {"type": "aov", "aovs": "dd:depth",
                       "image": {"type": "path", "max_depth": int(settings.max_depth)}},
        "sensor": sensor_dict(mi, settings, "rgba"),
    }
    scene.update(lighting.emitters(mi))
    with tempfile.TemporaryDirectory() as tmp:
        for kind, mask in head_parts(head).items():
            if mask.any():
                path = Path(tmp) / f"{kind}.ply"
                _write_ply(path, head, mask)
                scene[f"head_{kind}"] = {"type": "ply", "filename": str(path), "bsdf": _bsdf(kind, settings)}
        for i, disc in enumerate(occluders):
            scene[f"occluder_{i}"] = _disc(mi, disc)
        raw = np.array(mi.render(mi.load_dict(scene)), dtype=np.float32)
    focal_px = settings.width_px / (2.0 * np.tan(np.radians(settings.fov_x_deg) / 2.0))
    return {"image": np.clip(raw[..., :3], 0.0, None), "depth_cm": raw[..., -1], "focal_px": float(focal_px)}
