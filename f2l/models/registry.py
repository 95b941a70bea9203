"""Discovery of lighting models through the ``f2l.lighting_models`` entry-point group.

Built-in models (``plugins/f2l_builtin_models``) register through the same group as third-party
packages, so there is exactly one path. A plugin that fails to import, or that declares a
capability (``f2l.models.capabilities``) it does not honour, is reported with its name, the
capability and the reason; the other models keep working. Capabilities are checked statically
when the class is loaded and numerically the first time the model is made on a grid size.

A numeric check that passed is remembered across processes (:func:`check_stamp`): a stamp file
named by the SHA-256 of the model's target, grid, its package's source files, f2l's own source
files and the numpy/torch versions, under ``$F2L_CACHE_DIR`` (default
``$XDG_CACHE_HOME/f2l`` or ``~/.cache/f2l``). Any edit to the plugin or to f2l, or another
torch, names another stamp, so the check runs again; a check that fails is never stamped. An
unwritable cache only costs the check again.
"""

from __future__ import annotations

import hashlib
import os
import sys
from dataclasses import dataclass
from functools import lru_cache
from importlib.metadata import entry_points
from pathlib import Path

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


def _entry_points() -> tuple:
    """The group's entry points now installed: (name, value, distribution) per entry (cheap: the
    installed metadata, nothing imported)."""
    return tuple((ep.name, ep.value, ep.dist.name if ep.dist is not None else "?", ep)
                 for ep in entry_points(group=GROUP))


@lru_cache(maxsize=8)
def _discover(installed: tuple) -> dict[str, ModelInfo]:
    found: dict[str, ModelInfo] = {}
    for name, value, package, ep in installed:
        if name in found:  # the same distribution seen twice on sys.path (e.g. editable + build)
            continue
        info = ModelInfo(name=name, target=value, package=package)
        try:
            obj = ep.load()
            if not (isinstance(obj, type) and issubclass(obj, LightingModel)):
                raise TypeError(f"{value} is not a subclass of f2l.models.base.LightingModel")
            missing = sorted(getattr(obj, "__abstractmethods__", ()))
            hint = ""
            if "radiance" in missing and declared(obj):
                hint = " (list the capability mixins before LightingModel in the class's bases)"
            if missing:
                raise TypeError(f"{value} does not implement {', '.join(missing)}{hint}")
            check_class(obj)
            info.capabilities = tuple(declared(obj))
            info.cls = obj
        except Exception as exc:  # noqa: BLE001 - a broken plugin must not break the others
            info.error = f"{type(exc).__name__}: {exc}"
        found[name] = info
    return dict(sorted(found.items()))


def discover() -> dict[str, ModelInfo]:
    """Every model of the group, loaded once per set of installed entry points (a plugin installed
    meanwhile is found on the next call); failures are kept as ``ModelInfo.error``."""
    return dict(_discover(tuple((n, v, p, _EntryPoint(ep)) for n, v, p, ep in _entry_points())))


class _EntryPoint:
    """An entry point compared by (name, value, distribution), so the cache key is stable."""

    def __init__(self, ep) -> None:
        self.ep = ep
        self.key = (ep.name, ep.value, ep.dist.name if ep.dist is not None else "?")

    def load(self):
        return self.ep.load()

    def __eq__(self, other) -> bool:
        return isinstance(other, _EntryPoint) and self.key == other.key

    def __hash__(self) -> int:
        return hash(self.key)


@dataclass(frozen=True)
class ModelSpec:
    """What the registry knows of a model without building it: its name, class, version,
    capabilities, the distribution that provides it and its entry-point target."""

    name: str
    cls: type
    version: str
    capabilities: tuple[str, ...]
    package: str
    target: str


def get(name: str) -> ModelSpec:
    """The :class:`ModelSpec` of the model registered as ``name`` (nothing is built);
    :class:`ModelNotFoundError` for an unknown model or one that failed to load."""
    info = _loaded(name)
    return ModelSpec(name=info.name, cls=info.cls, version=str(info.cls.version), capabilities=info.capabilities,
                     package=info.package, target=info.target)


def _loaded(name: str) -> ModelInfo:
    """The registry entry of ``name``, whose class loaded; :class:`ModelNotFoundError` otherwise."""
    models = discover()
    if name not in models:
        raise ModelNotFoundError(f"unknown lighting model {name!r}; installed: {', '.join(models) or 'none'}")
    info = models[name]
    if not info.ok:
        raise ModelNotFoundError(f"lighting model {name!r} ({info.target}) failed to load: {info.error}")
    return info


def load_model(name: str, grid: LatLongGrid) -> LightingModel:
    """Instantiate the model registered as ``name`` on ``grid``."""
    info = _loaded(name)
    try:
        model = info.cls(grid)
    except Exception as exc:  # e.g. a model's data file (weights, prior) is missing or broken
        raise ModelNotFoundError(f"lighting model {name!r} ({info.target}) failed to initialise: {exc}") from exc
    key = (info.target, info.package, grid.height, grid.width)
    if key not in _CHECKED:
        stamp = check_stamp(info, grid)
        if stamp is None or not stamp.is_file():
            try:
                check_model(model)
            except Exception as exc:  # noqa: BLE001 - whatever a plugin raises, say which one and why
                raise ModelNotFoundError(f"lighting model {name!r} from {info.package} ({info.target}) was "
                                         f"refused: {exc}") from exc
            _write_stamp(stamp)
        _CHECKED.add(key)
    return model


def model_class(name: str) -> type:
    """The class registered as ``name`` (its ``version``, ``name``, capabilities) without building
    it; raises :class:`ModelNotFoundError` as :func:`load_model` does for an unknown model or one
    that failed to load."""
    return _loaded(name).cls


_CHECKED: set[tuple] = set()  # (target, package, H, W) whose capabilities passed check_model
STAMP_DIR = "capability-checks"


def cache_dir() -> Path:
    """f2l's per-user cache: ``$F2L_CACHE_DIR``, else ``$XDG_CACHE_HOME/f2l``, else ``~/.cache/f2l``."""
    env = os.environ.get("F2L_CACHE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "f2l"


@lru_cache(maxsize=64)
def _sources_digest(folder: str) -> str:
    """SHA-256 over the paths and bytes of every ``.py`` file under ``folder`` (sorted)."""
    h = hashlib.sha256()
    root = Path(folder)
    for path in sorted(root.rglob("*.py")):
        try:
            data = path.read_bytes()
        except OSError:
            continue
        h.update(str(path.relative_to(root)).encode() + b"\0" + hashlib.sha256(data).digest())
    return h.hexdigest()


def check_stamp(info: ModelInfo, grid: LatLongGrid) -> Path | None:
    """The stamp file that says ``info``'s class passed :func:`check_model` on ``grid``'s size with
    exactly this code (module docstring); None when its source cannot be located."""
    import numpy
    import torch

    import f2l

    module = sys.modules.get(getattr(info.cls, "__module__", ""), None)
    source = getattr(module, "__file__", None)
    if not source:
        return None
    top = sys.modules.get(info.cls.__module__.split(".")[0])
    top_file = getattr(top, "__file__", None) or source
    folder = Path(top_file).parent if Path(top_file).name == "__init__.py" else Path(source).parent
    parts = [info.target, info.package, f"{grid.height}x{grid.width}", numpy.__version__, torch.__version__,
             _sources_digest(str(folder)), _sources_digest(str(Path(f2l.__file__).parent))]
    digest = hashlib.sha256("\n".join(parts).encode()).hexdigest()
    return cache_dir() / STAMP_DIR / digest


def _write_stamp(stamp: Path | None) -> None:
    if stamp is None:
        return
    try:
        stamp.parent.mkdir(parents=True, exist_ok=True)
        tmp = stamp.with_name(f".{stamp.name}.{os.getpid()}.tmp")
        tmp.write_text("passed\n", encoding="ascii")
        os.replace(tmp, stamp)
    except OSError:
        pass  # an unwritable cache: the check simply runs again next time
