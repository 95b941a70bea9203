"""Discovery of lighting models through the ``f2l.lighting_models`` entry-point group.

Built-in models (``plugins/f2l_builtin_models``) register through the same group as third-party
packages, so there is exactly one path. A plugin that fails to import, or that declares a
capability (``f2l.models.capabilities``) it does not honour, is reported with its name, the
capability and the reason; the other models keep working. Capabilities are checked statically
when the class is loaded and numerically the first time the model is made on a grid size.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib.metadata import entry_points

from f2l.lighting.grid import LatLongGrid
from f2l.models.base import LightingModel
from f2l.models.capabilities import check_class, check_model, declared

GROUP = "f2l.lighting_models"


class ModelNotFoundError(KeyError):
    """A model that is not installed, failed to load, or was refused (the message says which)."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


@dataclass
class ModelInfo:
    name: str
    target: str  # "module:attr"
    package: str  # distribution providing it
    cls: type | None = None
    error: str | None = None
    capabilities: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        return self.cls is not None


def discover() -> dict[str, ModelInfo]:
    """Load every entry point of the group; failures are kept as ModelInfo.error."""
    found: dict[str, ModelInfo] = {}
    for ep in entry_points(group=GROUP):
        if ep.name in found:  # the same distribution seen twice on sys.path (e.g. editable + build)
            continue
        package = ep.dist.name if ep.dist is not None else "?"
        info = ModelInfo(name=ep.name, target=ep.value, package=package)
        try:
            obj = ep.load()
            if not (isinstance(obj, type) and issubclass(obj, LightingModel)):
                raise TypeError(f"{ep.value} is not a subclass of f2l.models.base.LightingModel")
            missing = sorted(getattr(obj, "__abstractmethods__", ()))
            hint = ""
            if "radiance" in missing and declared(obj):
                hint = " (list the capability mixins before LightingModel in the class's bases)"
            if missing:
                raise TypeError(f"{ep.value} does not implement {', '.join(missing)}{hint}")
            check_class(obj)
            info.capabilities = tuple(declared(obj))
            info.cls = obj
        except Exception as exc:  # noqa: BLE001 - a broken plugin must not break the others
            info.error = f"{type(exc).__name__}: {exc}"
        found[ep.name] = info
    return dict(sorted(found.items()))


def load_model(name: str, grid: LatLongGrid) -> LightingModel:
    """Instantiate the model registered as ``name`` on ``grid``."""
    models = discover()
    if name not in models:
        raise ModelNotFoundError(f"unknown lighting model {name!r}; installed: {', '.join(models) or 'none'}")
    info = models[name]
    if not info.ok:
        raise ModelNotFoundError(f"lighting model {name!r} ({info.target}) failed to load: {info.error}")
    try:
        model = info.cls(grid)
    except Exception as exc:  # e.g. a model's data file (weights, prior) is missing or broken
        raise ModelNotFoundError(f"lighting model {name!r} ({info.target}) failed to initialise: {exc}") from exc
    key = (info.target, info.package, grid.height, grid.width)
    if key not in _CHECKED:
        try:
            check_model(model)
        except Exception as exc:  # noqa: BLE001 - whatever a plugin raises, say which one and why
            raise ModelNotFoundError(f"lighting model {name!r} from {info.package} ({info.target}) was refused: "
                                     f"{exc}") from exc
        _CHECKED.add(key)
    return model


_CHECKED: set[tuple] = set()  # (target, package, H, W) whose capabilities passed check_model
