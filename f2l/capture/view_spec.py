"""The view spec: what a session's ``session.toml`` says about one capture file (its lens,
fall-off and flat field, the tripod head's yaw/pitch/roll, the file's role and the session's
probe azimuth), parsed and validated once at ingest and stored in ``captures.parquet``'s
``view_json`` column.

:meth:`ViewSpec.to_json` and :meth:`ViewSpec.from_json` are the one encoder and decoder of that
column. The text is the JSON object of the keys the TOML gives (``[lens]``, then the first
matching ``[[shots]]`` entry's keys, ``probe_azimuth_deg``; a flat field's ``file`` as recorded by
ingest with its ``sha256`` and, where ``--allow-outside`` allowed it, ``allow_outside``), keys
sorted, every value as written (an integer stays an integer): the text f2l wrote before the spec
existed, so tables written then still load and the merge and sphere cache keys built from the
column do not change.

Validation (:class:`ViewSpecError`, whose message and ``key`` name the key): only the keys above;
every number finite; ``projection``, ``role`` and the fall-off ``model`` and named ``radius`` from
their lists; lens lengths and angles positive; yaw, pitch, roll and probe azimuth within the
``session`` schema's ranges (degrees). Whether the lens can place a frame of a given size (a
plausible focal length, principal point, image circle) depends on the frame:
:func:`f2l.capture.lens.lens_of` checks it, and ingest does for every frame of known size.

>>> spec = ViewSpec.from_json('{"fov_deg": 180, "pitch_deg": 90.0, "projection": "equidistant"}')
>>> spec.lens.fov_deg, spec.pitch_deg, spec.role
(180, 90.0, None)
>>> spec.to_json()
'{"fov_deg": 180, "pitch_deg": 90.0, "projection": "equidistant"}'
>>> try:
...     ViewSpec.from_json('{"projection": "fisheye"}')
... except ViewSpecError as error:
...     print(error.key)
projection
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, fields, replace
from typing import Any, Mapping

__all__ = ["ViewSpec", "LensSpec", "FalloffSpec", "ViewSpecError", "PROJECTIONS", "RADIUS_NAMES",
           "FALLOFF_MODELS", "ROLES", "POSE_KEYS", "POSE_LIMITS_DEG"]

PROJECTIONS = ("equidistant", "equisolid", "rectilinear")
RADIUS_NAMES = ("image_circle", "half_diagonal", "half_width", "half_height")
FALLOFF_MODELS = ("polynomial", "cos4", "flat_field")
ROLES = ("sky_bracket", "face", "chart", "probe", "other")
POSE_LIMITS_DEG = {"yaw_deg": 360.0, "pitch_deg": 90.0, "roll_deg": 180.0, "probe_azimuth_deg": 360.0}
"""The largest |angle| (degrees) of each orientation key, as schema ``session`` bounds it."""
POSE_KEYS = ("yaw_deg", "pitch_deg", "roll_deg")
MAX_COEFFICIENTS = 3
"""At most k1, k2, k3 in ``vignetting`` and a polynomial fall-off's ``coefficients``."""


class ViewSpecError(ValueError):
    """A view description that cannot place its view; the message names the key, ``key`` holds
    it (the top-level key, e.g. ``pitch_deg`` or ``falloff``; "" when none applies)."""

    def __init__(self, message: str, key: str = "") -> None:
        super().__init__(message)
        self.key = key


def _finite(value: Any) -> bool:
    try:
        return math.isfinite(value)
    except OverflowError:  # an integer beyond float's range
        return False


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _positive(value: Any, key: str, where: str | None = None) -> Any:
    if not (_is_number(value) and _finite(value) and value > 0):
        raise ViewSpecError(f"{where or key} must be a positive number, got {value!r}", key)
    return value


def _angle(value: Any, key: str) -> Any:
    if not _is_number(value):
        raise ViewSpecError(f"{key} = {value!r} is not a number", key)
    if not _finite(value):
        raise ViewSpecError(f"{key} = {value} is not a finite angle", key)
    limit = POSE_LIMITS_DEG[key]
    if abs(value) > limit:
        raise ViewSpecError(f"{key} = {value:g} is outside -{limit:g}..{limit:g} degrees", key)
    return value


def _numbers(value: Any, key: str, where: str | None = None, *, min_len: int = 0,
             max_len: int | None = None) -> tuple:
    """A list of finite numbers as a tuple (values as written)."""
    ok = (isinstance(value, (list, tuple)) and min_len <= len(value) <= (max_len or len(value))
          and all(_is_number(v) and _finite(v) for v in value))
    if not ok:
        size = (f"{min_len}" if min_len == max_len else f"at most {max_len}" if max_len
                else f"at least {min_len}")
        raise ViewSpecError(f"{where or key} must be a list of {size} finite numbers, got {value!r}", key)
    return tuple(value)


def _text(value: Any, key: str, where: str | None = None, choices: tuple[str, ...] = ()) -> str:
    if not (isinstance(value, str) and value and (not choices or value in choices)):
        expected = f"one of {', '.join(choices)}" if choices else "a non-empty string"
        raise ViewSpecError(f"{where or key} must be {expected}, got {value!r}", key)
    return value


def _present(obj) -> dict:
    """The fields of a spec dataclass that are given, as JSON data (tuples as lists)."""
    out = {}
    for f in fields(obj):
        value = getattr(obj, f.name)
        if value is None:
            continue
        if isinstance(value, tuple):
            value = list(value)
        elif isinstance(value, FalloffSpec):
            value = value.as_dict()
        out[f.name] = value
    return out


def _table(data: Any, known: set[str], where: str, what: str) -> Mapping:
    """``data`` when it is a mapping of ``known`` keys only (``where``: its key, "" at the top)."""
    if not isinstance(data, Mapping):
        raise ViewSpecError(f"{what}, got {type(data).__name__} {data!r:.60}", where)
    extra = sorted(set(data) - known, key=str)
    if extra:
        raise ViewSpecError(f"unknown key {where + '/' if where else ''}{extra[0]} in the view description "
                            f"(expected {', '.join(sorted(known))})", where or str(extra[0]))
    return data


@dataclass(frozen=True)
class FalloffSpec:
    """A fall-off as described (:mod:`f2l.capture.lens`): ``model``, a polynomial's
    ``coefficients`` and ``radius`` (a name or px), a flat field's ``file`` (relative to the capture
    root once ingest recorded it, with its ``sha256``; ``allow_outside`` True where ingest ran
    with ``--allow-outside`` and the file lies outside)."""

    model: str
    coefficients: tuple[float, ...] | None = None
    radius: str | float | None = None
    file: str | None = None
    sha256: str | None = None
    allow_outside: bool | None = None

    @classmethod
    def from_dict(cls, data: Any) -> FalloffSpec:
        _table(data, {f.name for f in fields(cls)}, "falloff", "falloff must be a table (model = ...)")
        if "model" not in data:
            raise ViewSpecError("falloff needs model = polynomial, cos4 or flat_field", "falloff")
        radius = data.get("radius")
        if radius is not None and not isinstance(radius, str):
            radius = _positive(radius, "falloff", "falloff radius")
        elif radius is not None:
            radius = _text(radius, "falloff", "falloff radius", RADIUS_NAMES)
        allow = data.get("allow_outside")
        if allow is not None and not isinstance(allow, bool):
            raise ViewSpecError(f"falloff allow_outside must be true or false, got {allow!r}", "falloff")
        get = data.get
        return cls(model=_text(get("model"), "falloff", "falloff model", FALLOFF_MODELS),
                   coefficients=None if get("coefficients") is None else _numbers(
                       get("coefficients"), "falloff", "falloff coefficients", max_len=MAX_COEFFICIENTS),
                   radius=radius,
                   file=None if get("file") is None else _text(get("file"), "falloff", "falloff file"),
                   sha256=None if get("sha256") is None else _text(get("sha256"), "falloff", "falloff sha256"),
                   allow_outside=allow)

    def as_dict(self) -> dict:
        return _present(self)


_LENS_POSITIVE = ("focal_length_px", "focal_length_mm", "sensor_width_mm", "fov_deg", "image_circle_radius_px",
                  "max_angle_deg")


@dataclass(frozen=True)
class LensSpec:
    """A lens as described (``session.toml`` ``[lens]``, overridden per ``[[shots]]``; the keys of
    :mod:`f2l.capture.lens`), values as written. :func:`f2l.capture.lens.lens_of` turns it into
    the :class:`~f2l.capture.lens.Lens` of a frame of known size."""

    projection: str | None = None
    colmap_model: str | None = None
    colmap_params: tuple[float, ...] | None = None
    focal_length_px: float | None = None
    focal_length_mm: float | None = None
    sensor_width_mm: float | None = None
    fov_deg: float | None = None
    principal_point_px: tuple[float, float] | None = None
    image_circle_radius_px: float | None = None
    max_angle_deg: float | None = None
    falloff: FalloffSpec | None = None
    vignetting: tuple[float, ...] | None = None

    @classmethod
    def from_dict(cls, data: Mapping) -> LensSpec:
        """The lens keys of ``data`` (other keys are ignored here), validated."""
        get = data.get
        values: dict[str, Any] = {key: _positive(get(key), key) for key in _LENS_POSITIVE if get(key) is not None}
        if get("projection") is not None:
            values["projection"] = _text(get("projection"), "projection", choices=PROJECTIONS)
        if get("colmap_model") is not None:
            if not isinstance(get("colmap_model"), str):
                raise ViewSpecError(f"colmap_model must be a pycolmap model name, got {get('colmap_model')!r}",
                                    "colmap_model")
            values["colmap_model"] = get("colmap_model")
        if get("colmap_params") is not None:
            values["colmap_params"] = _numbers(get("colmap_params"), "colmap_params", min_len=1)
        if get("principal_point_px") is not None:
            values["principal_point_px"] = _numbers(get("principal_point_px"), "principal_point_px",
                                                    "principal_point_px [cx, cy]", min_len=2, max_len=2)
        if get("vignetting") is not None:
            values["vignetting"] = _numbers(get("vignetting"), "vignetting", max_len=MAX_COEFFICIENTS)
        if get("falloff") is not None:
            values["falloff"] = FalloffSpec.from_dict(get("falloff"))
        return cls(**values)

    def as_dict(self) -> dict:
        """The lens keys given, as JSON data (what :func:`f2l.capture.lens.lens_from_view` reads)."""
        return _present(self)

    @property
    def describes_geometry(self) -> bool:
        """Whether a projection or a COLMAP model is given (without one no view is placed)."""
        return self.projection is not None or self.colmap_model is not None


_LENS_KEYS = {f.name for f in fields(LensSpec)}


@dataclass(frozen=True)
class ViewSpec:
    """What the session TOML says about one file: its ``lens``, the tripod head's ``yaw_deg``,
    ``pitch_deg``, ``roll_deg`` (None: not given, 0 when placing), its ``role`` and the session's
    ``probe_azimuth_deg``; values as written (module doc). An empty spec: the TOML says nothing.

    >>> spec = ViewSpec(LensSpec(projection="equidistant", fov_deg=180.0), pitch_deg=90.0)
    >>> ViewSpec.from_json(spec.to_json()) == spec
    True
    >>> spec.pose, spec.pose_deg()
    ({'pitch_deg': 90.0}, {'yaw_deg': 0.0, 'pitch_deg': 90.0, 'roll_deg': 0.0})
    """

    lens: LensSpec = field(default_factory=LensSpec)
    yaw_deg: float | None = None
    pitch_deg: float | None = None
    roll_deg: float | None = None
    role: str | None = None
    probe_azimuth_deg: float | None = None

    @classmethod
    def from_dict(cls, data: Any) -> ViewSpec:
        """The spec of a view description (the session TOML's keys for one file), validated."""
        _table(data, _LENS_KEYS | set(POSE_LIMITS_DEG) | {"role"}, "", "a view description must be a JSON object")
        angles = {key: _angle(data[key], key) for key in POSE_LIMITS_DEG if data.get(key) is not None}
        role = None if data.get("role") is None else _text(data["role"], "role", choices=ROLES)
        return cls(LensSpec.from_dict(data), role=role, **angles)

    @classmethod
    def from_json(cls, text: str | None) -> ViewSpec:
        """Decode a ``view_json`` value ("" or None: the empty spec), validated."""
        if not text:
            return cls()
        try:
            data = json.loads(text)
        except (ValueError, RecursionError) as exc:
            raise ViewSpecError(f"view_json is not JSON ({exc})") from None
        return cls.from_dict(data)

    def as_dict(self) -> dict:
        """The keys given, as JSON data (the lens keys at the top level, as in the TOML)."""
        out = {key: value for key, value in _present(self).items() if key != "lens"}
        return {**self.lens.as_dict(), **out}

    def to_json(self) -> str:
        """The ``view_json`` text: :meth:`as_dict`, keys sorted."""
        return json.dumps(self.as_dict(), sort_keys=True, allow_nan=False)

    @property
    def pose(self) -> dict:
        """The orientation keys given (yaw, pitch, roll in degrees, as written)."""
        return {key: getattr(self, key) for key in POSE_KEYS
                if getattr(self, key) is not None}

    def pose_deg(self) -> dict[str, float]:
        """Yaw, pitch and roll in degrees for placing the view (0 where not given)."""
        return {key: 0.0 if getattr(self, key) is None else float(getattr(self, key))
                for key in POSE_KEYS}

    def placement_key(self) -> str:
        """What places a frame (lens and orientation, without role and probe azimuth) as text:
        frames of one bracket share it."""
        return replace(self, role=None, probe_azimuth_deg=None).to_json()

    def with_flat_field(self, file: str, sha256: str, allow_outside: bool = False) -> ViewSpec:
        """This spec with its fall-off's flat-field ``file`` as ingest records it."""
        falloff = replace(self.lens.falloff, file=file, sha256=sha256, allow_outside=True if allow_outside else None)
        return replace(self, lens=replace(self.lens, falloff=falloff))
