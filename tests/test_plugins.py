"""The plugin contract (issue 19): capabilities checked at registration, example plugins installed
the way an outside package is (pip, its own dist-info), their own tests run through f2l's pytest
fixtures, ``f2l bench`` reports a plugin next to the built-ins, the guide's example works as
written, and the estimation core knows no model by name and has no import cycles."""

from __future__ import annotations

import ast
import json
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from f2l.lighting.grid import LatLongGrid
from f2l.models import ModelNotFoundError, discover, load_model
from tests.plugin_helpers import f2l_cmd, make_dist

REPO = Path(__file__).resolve().parents[1]
PLUGINS = ("example_gradient_sun", "example_directional")
GRID = LatLongGrid(32, 64)


@pytest.fixture(scope="module")
def installed_plugins(tmp_path_factory) -> Path:
    """Both example plugins pip-installed (built from their own pyproject.toml) into a folder."""
    target = tmp_path_factory.mktemp("site")
    proc = subprocess.run([sys.executable, "-m", "pip", "install", "-qq", "--no-deps", "--no-build-isolation",
                           "--no-index", "--target", str(target)] + [str(REPO / "plugins" / p) for p in PLUGINS],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert (target / "f2l_example_gradient_sun" / "__init__.py").exists()
    return target


def _env(site: Path) -> dict:
    import os

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(site)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    return env


def test_installed_plugins_listed_with_their_capabilities(installed_plugins):
    proc = subprocess.run(f2l_cmd("models", "--json"), env=_env(installed_plugins), capture_output=True, text=True,
                          timeout=180)
    assert proc.returncode == 0, proc.stderr
    rows = {r["name"]: r for r in json.loads(proc.stdout)}
    assert rows["gradient_sun"]["ok"] and rows["gradient_sun"]["package"] == "f2l-example-gradient-sun"
    assert rows["gradient_sun"]["capabilities"] == ["compact-sun", "sun-angles"]
    assert rows["directional"]["ok"] and rows["directional"]["capabilities"] == []
    assert rows["sunsky"]["capabilities"] == ["compact-sun", "sun-angles"]
    assert rows["ae"]["capabilities"] == ["latent-sky"]
    assert rows["sh9"]["capabilities"] == ["linear"] and rows["sh25"]["capabilities"] == ["linear"]


def test_plugin_own_tests_pass_with_f2l_fixtures(installed_plugins, tmp_path):
    """The plugin's tests, copied out of the repository, see only the installed package and the
    fixtures f2l's pytest11 entry point provides."""
    tests = tmp_path / "plugin_tests"
    shutil.copytree(REPO / "plugins" / "example_gradient_sun" / "tests", tests)
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(tests)],
                          cwd=tmp_path, env=_env(installed_plugins), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert "4 passed" in proc.stdout


def test_bench_reports_a_plugin_next_to_the_builtins(installed_plugins, tmp_path):
    out = tmp_path / "bench"
    proc = subprocess.run(f2l_cmd("dev", "bench", "--faces", "2", "-m", "sunsky", "-m", "gradient_sun", "--grid", "32x64",
                                  "--image-size", "96", "--threads", "1", "--sun-skip-faces", "1", "--out", str(out)),
                          env=_env(installed_plugins), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    bench = json.loads((out / "bench.json").read_text())
    for name in ("sunsky", "gradient_sun"):
        rows = bench["per_face"][name]
        assert len(rows) == 2 and all("error" not in r for r in rows), rows
        assert all(np.isfinite(r["Sun-ang (°)"]) and r["total_s"] > 0 for r in rows)
        assert all("search_s" in r for r in rows)  # both took the compact-sun path (the sun search)
    assert "| gradient_sun | 2 |" in proc.stdout
    # the overcast sun-core table runs for every compact-sun model, the plugin's too
    assert "sunsky on 1 overcast face(s)" in proc.stdout and "gradient_sun on 1 overcast face(s)" in proc.stdout


# -- refused at registration ---------------------------------------------------------------------------
BAD_PLUGINS = '''
import math
import numpy as np
import torch
from f2l.models.base import LightingModel
from f2l.models.capabilities import CompactSun, LatentLayout, LatentSky, LinearRadiance, SunLayout


class _Sun(CompactSun, LightingModel):
    domain = "sky"
    sun_layout = SunLayout(elevation=6, azimuth=7)
    param_names = ["a", "b", "c", "d", "e", "f", "el", "az"]

    def initial_points(self):
        return np.array([[1.0, 1, 1, 5, 5, 5, 0.5, 0.0]])

    def sky(self, params):
        n = self.grid.sky_rows * self.grid.width
        return torch.ones(params.shape[0], n, 3, dtype=torch.float64)


class WeightsInSky(_Sun):
    name = "weights_in_sky"

    def sky(self, params):  # not the unit-weight sky: scales with w_sky
        return super().sky(params) * params[:, :3, None].transpose(1, 2)


class DictLayout(_Sun):
    name = "dict_layout"
    sun_layout = {"sky_rgb": (0, 1, 2), "sun_rgb": (3, 4, 5), "elevation": 6, "azimuth": 7}


class RaisingSky(_Sun):
    name = "raising_sky"

    def sky(self, params):
        raise RuntimeError("cannot evaluate")


class WrongOrder(LightingModel, CompactSun):  # LightingModel's abstract radiance comes first
    name = "wrong_order"
    domain = "sky"
    sun_layout = SunLayout(elevation=6, azimuth=7)
    param_names = ["a", "b", "c", "d", "e", "f", "el", "az"]

    def initial_points(self):
        return np.zeros((1, 8))

    def sky(self, params):
        return torch.ones(params.shape[0], self.grid.sky_rows * self.grid.width, 3, dtype=torch.float64)


class NotLinear(LinearRadiance, LightingModel):
    name = "not_linear"
    domain = "sphere"
    param_names = ["r", "g", "b"]

    def initial_points(self):
        return np.ones((1, 3))

    def linear_basis(self):
        return np.ones((self.grid.size, 1))

    def radiance(self, params):
        return (params[:, None, :] ** 2).expand(-1, self.grid.size, -1)


class NoRoll(LatentSky, LightingModel):
    name = "no_roll"
    domain = "sky"
    latent_layout = LatentLayout(exposure=0, code=slice(1, 3), azimuth=3)
    param_names = ["e", "z1", "z2", "az"]

    def initial_points(self):
        return np.zeros((1, 4))

    def search_codes(self):
        return np.zeros((2, 2))

    def decode_sky(self, codes, azimuth):  # ignores the azimuth
        g = self.grid
        ramp = torch.arange(g.width, dtype=torch.float32).expand(g.sky_rows, -1) + 1
        return ramp.expand(codes.shape[0], 3, -1, -1).clone()

    def radiance(self, params):
        sky = self.decode_sky(params[:, 1:3], params[:, 3]).flatten(2).transpose(1, 2)
        return torch.nn.functional.pad(sky, (0, 0, 0, self.grid.size - sky.shape[1])).to(params.dtype)
'''


@pytest.fixture
def bad_site(tmp_path, monkeypatch):
    (tmp_path / "bad_plugins.py").write_text(BAD_PLUGINS)
    names = ["weights_in_sky", "dict_layout", "raising_sky", "wrong_order", "not_linear", "no_roll"]
    cls = {"weights_in_sky": "WeightsInSky", "dict_layout": "DictLayout", "raising_sky": "RaisingSky",
           "wrong_order": "WrongOrder", "not_linear": "NotLinear", "no_roll": "NoRoll"}
    make_dist(tmp_path, "bad-plugins", {n: f"bad_plugins:{cls[n]}" for n in names})
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path
    sys.modules.pop("bad_plugins", None)


@pytest.mark.parametrize("name, capability, reason", [
    ("weights_in_sky", "compact-sun", "depends on the weights"),
    ("raising_sky", "compact-sun", "checking it raised RuntimeError: cannot evaluate"),
    ("not_linear", "linear", "differs from linear_basis"),
    ("no_roll", "latent-sky", "does not roll the sky"),
])
def test_a_capability_the_model_cannot_honour_is_refused(bad_site, name, capability, reason):
    info = discover()[name]
    assert info.ok and info.package == "bad-plugins"  # the class itself loads
    with pytest.raises(ModelNotFoundError) as err:
        load_model(name, GRID)
    msg = str(err.value)
    assert f"lighting model {name!r} from bad-plugins" in msg and f"capability {capability!r}" in msg, msg
    assert reason in msg, msg
    assert load_model("sunsky", GRID).name == "sunsky"  # the others keep working


def test_static_capability_errors_reported_by_discover(bad_site):
    models = discover()
    assert not models["dict_layout"].ok
    assert "capability 'compact-sun'" in models["dict_layout"].error
    assert "sun_layout must be a f2l.models.capabilities.SunLayout" in models["dict_layout"].error
    assert not models["wrong_order"].ok
    assert "list the capability mixins before LightingModel" in models["wrong_order"].error


# -- the guide's example, as written -------------------------------------------------------------------
def _guide_plugin_source() -> str:
    text = (REPO / "docs" / "plugins.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    source = [b for b in blocks if "class UniformSun(" in b]
    assert len(source) == 1, "docs/plugins.md must hold one UniformSun example"
    return textwrap.dedent(source[0])


def test_guide_example_plugin_works_as_written(tmp_path, monkeypatch):
    from f2l.testing import round_trip

    (tmp_path / "uniform_sun.py").write_text(_guide_plugin_source())
    make_dist(tmp_path, "uniform-sun", {"uniform_sun": "uniform_sun:UniformSun"})
    monkeypatch.syspath_prepend(str(tmp_path))
    try:
        assert discover()["uniform_sun"].capabilities == ("compact-sun", "sun-angles")
        cases = round_trip("uniform_sun", n=2, seed=4, grid=(32, 64), image_size=96)
        assert all(c["sun_angle_deg"] < 6.0 for c in cases), [c["sun_angle_deg"] for c in cases]
    finally:
        sys.modules.pop("uniform_sun", None)


# -- the core stays generic ------------------------------------------------------------------------------
BUILTIN_NAMES = re.compile(r"\b(sunsky|SunSky|sh9|sh25|SH9|SH25|ae|AE|f2l_builtin_models|f2l\.ae|preetham|Preetham|"
                           r"autoencoder)\b", re.I)
UNDECLARED = re.compile(r"\b(hasattr|getattr)\(\s*(self\.)?model\b|\bmodel\._\w")


def test_estimation_core_names_no_model_and_reads_no_undeclared_attribute():
    problems = []
    for path in sorted((REPO / "f2l" / "estimate").glob("*.py")):
        for n, line in enumerate(path.read_text().splitlines(), 1):
            for rx in (BUILTIN_NAMES, UNDECLARED):
                if rx.search(line):
                    problems.append(f"{path.relative_to(REPO)}:{n}: {line.strip()}")
    assert not problems, "\n".join(problems)


def _import_graph() -> dict[str, set[str]]:
    """Module -> the f2l modules it imports (top-level and function-level imports alike)."""
    modules = {}
    for p in (REPO / "f2l").rglob("*.py"):
        parts = list(p.relative_to(REPO).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(parts)] = p

    def resolve(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    graph = {m: set() for m in modules}
    for m, p in modules.items():
        package = m if p.name == "__init__.py" else m.rpartition(".")[0]
        for node in ast.walk(ast.parse(p.read_text())):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([node.module] if node.module else []))
                targets = [f"{base}.{a.name}" for a in node.names]
            for t in targets:
                r = resolve(t)
                if r and r != m and r.startswith("f2l"):
                    graph[m].add(r)
    return graph


def test_f2l_import_graph_has_no_cycles():
    graph = _import_graph()
    assert "f2l.estimate.latent" in graph["f2l.estimate.estimator"]  # the graph sees real edges
    state: dict[str, int] = {}
    cycles = []

    def visit(m: str, path: list[str]) -> None:
        state[m] = 1
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                cycles.append(" -> ".join(path[path.index(n):] + [n]))
            elif n not in state:
                visit(n, path + [n])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_plugin_commands_join_the_cli_and_a_broken_one_says_why(tmp_path):
    """``f2l.command_groups`` (a plugin's own group, as the built-in autoencoder's ``f2l ae``) and
    ``f2l.commands`` (single commands): a plugin's group or command that fails to import is still
    listed and fails with the reason, the rest keep working."""
    import os

    (tmp_path / "cmd_plugin.py").write_text(
        "import typer\n"
        "def hello(name: str = 'sky') -> None:\n    \"\"\"Say hello.\"\"\"\n    print(f'hello {name}')\n"
        "app = typer.Typer(help='Tools of the sky plugin.')\n"
        "@app.command('wave')\ndef wave(times: int = 1) -> None:\n    print('wave ' * times)\n")
    info = tmp_path / "cmd_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: cmd-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[f2l.commands]\nhello = cmd_plugin:hello\nbroken = no_such_mod_q:cmd\n"
                                           "[f2l.command_groups]\nskytools = cmd_plugin:app\n"
                                           "brokengroup = no_such_mod_q:app\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    help_text = subprocess.run(f2l_cmd("--help"), env=env, capture_output=True, text=True, timeout=120).stdout
    assert all(f" {c} " in help_text for c in ("ae", "skytools", "brokengroup", "hello", "broken"))
    assert "ae-corpus" not in help_text  # the old names run, hidden
    proc = subprocess.run(f2l_cmd("skytools", "wave", "--times", "2"), env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "wave wave" in proc.stdout, proc.stderr
    proc = subprocess.run(f2l_cmd("hello", "--name", "sun"), env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "hello sun" in proc.stdout, proc.stderr
    proc = subprocess.run(f2l_cmd("broken"), env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "command 'broken' (no_such_mod_q:cmd) failed to load" in proc.stderr
    proc = subprocess.run(f2l_cmd("brokengroup"), env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "command 'brokengroup' (no_such_mod_q:app) failed to load" in proc.stderr


def test_bench_keeps_going_past_a_refused_or_failing_plugin(bad_site, tmp_path):
    """A refused plugin and one whose sky raises mid-estimate become 'failed' rows naming the
    model and the capability; the built-in model in the same run is benched as usual."""
    (bad_site / "late_fail.py").write_text(
        "import torch\nfrom bad_plugins import _Sun\n"
        "class LateFail(_Sun):\n    name = 'late_fail'\n    calls = 0\n"
        "    def sky(self, params):\n        LateFail.calls += 1\n"
        "        if LateFail.calls > 3:\n            raise RuntimeError('sky exploded')\n"
        "        return super().sky(params)\n")
    make_dist(bad_site, "late-fail", {"late_fail": "late_fail:LateFail"})
    from f2l.dev.bench import run_bench

    try:
        result = run_bench(faces=1, models=["weights_in_sky", "late_fail", "sh9"], out_dir=tmp_path,
                           image_size=48, grid=LatLongGrid(16, 32), threads=1, exact_visibility=False,
                           sun_skip_faces=1)
    finally:
        sys.modules.pop("late_fail", None)
    md = result["markdown"]
    assert "| weights_in_sky | 0 | failed: lighting model 'weights_in_sky' from bad-plugins" in md
    assert "capability 'compact-sun'" in md
    assert ("| late_fail | 0 | failed: late_fail (late_fail:LateFail, capabilities: compact-sun, sun-angles): "
            "RuntimeError: sky exploded") in md
    assert "| sh9 | 1 |" in md and set(result["summary"]) == {"sh9"}
