import json
import subprocess

import numpy as np
import pytest
import torch

from f2l.lighting.grid import LatLongGrid
from f2l.models import discover, load_model
from f2l.models.base import LightingModel
from tests.plugin_helpers import f2l_cmd, make_dist, plugin_env


def test_builtin_models_register_through_entry_points():
    models = discover()
    assert {"sh9", "sh25"} <= set(models)
    assert models["sh9"].package == "f2l"
    grid = LatLongGrid(16, 32)
    sh9 = load_model("sh9", grid)
    sh25 = load_model("sh25", grid)
    assert sh9.num_params == 27 and sh25.num_params == 75
    assert isinstance(sh9, LightingModel)
    rad = sh9.radiance(torch.as_tensor(sh9.initial_points()))
    assert rad.shape == (2, grid.size, 3)
    # the DC-only start is a uniform radiance of 1
    np.testing.assert_allclose(rad[0].numpy(), 1.0, atol=1e-12)


def test_example_plugin_discovered_and_broken_plugin_reported(tmp_path):
    make_dist(tmp_path, "f2l-example-directional", {"directional": "f2l_example_directional:DirectionalAmbient"})
    make_dist(tmp_path, "broken-plugin", {"broken": "no_such_module_xyz:Model"})
    (tmp_path / "half_plugin.py").write_text(
        "from f2l.models.base import LightingModel\n"
        "class Half(LightingModel):\n"
        "    name = 'half'\n"
        "    param_names = ['a']\n"
    )
    make_dist(tmp_path, "half-plugin", {"half": "half_plugin:Half"})
    proc = subprocess.run(f2l_cmd("models", "--json"), env=plugin_env(tmp_path), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    rows = {r["name"]: r for r in json.loads(proc.stdout)}
    assert rows["directional"]["ok"] and rows["directional"]["params"] == 8
    assert rows["directional"]["package"] == "f2l-example-directional"
    assert not rows["broken"]["ok"] and "no_such_module_xyz" in rows["broken"]["error"]
    assert not rows["half"]["ok"] and "does not implement initial_points, radiance" in rows["half"]["error"]
    assert rows["sh9"]["ok"] and rows["sh25"]["ok"]  # the others keep working


def test_unknown_model_message():
    import pytest

    from f2l.models import ModelNotFoundError

    with pytest.raises(ModelNotFoundError, match="unknown lighting model 'nope'.*sh9"):
        load_model("nope", LatLongGrid(8, 16))


def test_a_passed_capability_check_is_remembered_across_processes(tmp_path, monkeypatch):
    """The numeric check runs once per model, grid size and code: a stamp under $F2L_CACHE_DIR
    lets the next process skip it; another cache (or another code) runs it again."""
    import f2l.models.capabilities as capabilities
    import f2l.models.registry as registry
    from f2l.lighting.grid import LatLongGrid

    grid = LatLongGrid(8, 16)
    monkeypatch.setenv("F2L_CACHE_DIR", str(tmp_path / "a"))
    monkeypatch.setattr(registry, "_CHECKED", set())
    calls = []
    real = registry.check_model
    monkeypatch.setattr(registry, "check_model", lambda m: (calls.append(m.name), real(m)))
    registry.load_model("sunsky", grid)
    assert calls == ["sunsky"]
    stamp = registry.check_stamp(registry.discover()["sunsky"], grid)
    assert stamp.is_file() and stamp.parent.parent == tmp_path / "a"
    monkeypatch.setattr(registry, "_CHECKED", set())  # a new process
    registry.load_model("sunsky", grid)
    assert calls == ["sunsky"]
    assert registry.check_stamp(registry.discover()["sunsky"], LatLongGrid(16, 32)) != stamp
    monkeypatch.setenv("F2L_CACHE_DIR", str(tmp_path / "b"))  # nothing remembered there
    monkeypatch.setattr(registry, "_CHECKED", set())

    def refuse(model):
        raise capabilities.CapabilityError("refused on purpose")

    monkeypatch.setattr(registry, "check_model", refuse)
    with pytest.raises(registry.ModelNotFoundError, match="refused on purpose"):
        registry.load_model("sunsky", grid)
    assert not (tmp_path / "b" / registry.STAMP_DIR).exists() or not any((tmp_path / "b" / registry.STAMP_DIR).iterdir())


def test_discovery_happens_once_and_get_builds_nothing(monkeypatch):
    """The registry loads and checks each plugin once per set of installed entry points;
    ``get(name)`` answers with the class, version and capabilities without making a model."""
    from f2l.models import registry

    first = registry.discover()
    calls = []
    monkeypatch.setattr(registry, "check_class", lambda cls: calls.append(cls))
    again = registry.discover()
    assert calls == [] and all(again[k] is first[k] for k in first)  # nothing loaded or checked again

    built = []
    monkeypatch.setattr(registry.LightingModel, "__init__", lambda self, *a, **k: built.append(self))
    spec = registry.get("sunsky")
    assert built == []
    assert spec.cls is first["sunsky"].cls and spec.version == str(first["sunsky"].cls.version)
    assert spec.capabilities == ("compact-sun", "sun-angles") and spec.package == "f2l"
    with pytest.raises(registry.ModelNotFoundError, match="unknown lighting model 'nope'"):
        registry.get("nope")
