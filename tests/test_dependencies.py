"""Issue 18: what f2l/ and plugins/ import is what pyproject.toml declares, and nothing more.

Every top-level module imported anywhere under f2l/ and plugins/ (found by walking the AST, so
imports inside functions count too) is mapped to the distributions that provide it in the test
environment; one of them must be in [project].dependencies, or, for an import that is optional
by design, in the extra named in OPTIONAL_IMPORTS. Declared dependencies that nothing imports
must be listed in NOT_IMPORTED with a reason.
"""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())
OWN = {"f2l", "f2l_builtin_models", "f2l_example_directional", "f2l_example_gradient_sun"}

# Optional by design: imported only inside a function, in a try that turns the ImportError into
# an error naming the extra. Module -> the [project.optional-dependencies] extra declaring it.
OPTIONAL_IMPORTS = {"ray": "ray",  # f2l estimate --executor ray (f2l/estimate/ray_executor.py)
                    # f2l render-faces (f2l/render/): the path tracer, the heads, and anny's kernel
                    # library (imported to quiet its start-up banner)
                    "mitsuba": "render", "anny": "render", "warp": "render",
                    # f2l scale-report --build: its face photos are scikit-image's astronaut
                    "skimage": "test"}

# Files only pytest loads (f2l's pytest11 fixtures for plugin authors, the example plugins' tests):
# their imports may come from the "test" extra.
def _pytest_loaded(path: str) -> bool:
    return path.endswith("pytest_plugin.py") or "/tests/" in path


# Declared dependencies that no file imports by name, and why.
NOT_IMPORTED: dict[str, str] = {}


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _names(requirements: list[str]) -> set[str]:
    return {_norm(re.split(r"[\s<>=!~;\[(]", r, maxsplit=1)[0]) for r in requirements}


def _sources() -> list[Path]:
    return sorted(p for root in ("f2l", "plugins") for p in (REPO / root).rglob("*.py"))


def _imports(tree: ast.AST):
    """(top-level module name, node) for every absolute import in the tree."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name.split(".")[0], node
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.module.split(".")[0], node


def _imported() -> dict[str, set[str]]:
    """Top-level module name -> the files importing it."""
    found: dict[str, set[str]] = {}
    for path in _sources():
        for module, _ in _imports(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            found.setdefault(module, set()).add(str(path.relative_to(REPO)))
    return found


def _owners() -> dict[str, set[str]]:
    """Top-level module -> normalised names of the installed distributions providing it. Besides
    ``packages_distributions()`` (top_level.txt or the RECORD's packages), each distribution's
    single-file modules (e.g. OpenEXR's ``OpenEXR.cpython-311-x86_64-linux-gnu.so``)."""
    owners = {k: {_norm(d) for d in v} for k, v in metadata.packages_distributions().items()}
    for dist in metadata.distributions():
        for f in dist.files or ():
            if len(f.parts) == 1 and f.name.endswith((".py", ".so", ".pyd")):
                owners.setdefault(f.name.split(".")[0], set()).add(_norm(dist.metadata["Name"]))
    return owners


def _third_party(imported: dict[str, set[str]]) -> dict[str, set[str]]:
    return {m: f for m, f in imported.items()
            if m not in OWN and m not in sys.stdlib_module_names and m != "__future__"}


def test_imports_are_declared():
    declared = _names(PYPROJECT["project"]["dependencies"])
    extras = {k: _names(v) for k, v in PYPROJECT["project"].get("optional-dependencies", {}).items()}
    owners = _owners()
    problems = []
    for module, files in sorted(_third_party(_imported()).items()):
        dists = owners.get(module, set())
        where = ", ".join(sorted(files))
        if not dists:
            problems.append(f"{module} (imported by {where}) is not installed in the test environment")
        elif not dists & declared:
            extra = OPTIONAL_IMPORTS.get(module) or ("test" if all(map(_pytest_loaded, files)) else None)
            if extra is None or not dists & extras.get(extra, set()):
                problems.append(f"{module} ({', '.join(sorted(dists))}) imported by {where} is not declared"
                                + (f" in the extra {extra!r}" if extra else ""))
    assert not problems, "undeclared imports:\n" + "\n".join(problems)


def test_declared_dependencies_are_imported():
    owners = _owners()
    used = set().union(*(owners.get(m, set()) for m in _third_party(_imported())))
    declared = _names(PYPROJECT["project"]["dependencies"])
    unused = declared - used - set(NOT_IMPORTED)
    assert not unused, f"declared dependencies that nothing under f2l/ or plugins/ imports: {sorted(unused)}"
    stale = set(NOT_IMPORTED) - declared
    assert not stale, f"NOT_IMPORTED lists packages that are not declared: {sorted(stale)}"
    for extra in set(OPTIONAL_IMPORTS.values()):
        assert extra in PYPROJECT["project"].get("optional-dependencies", {}), extra


def _guarded(node: ast.AST, parents: dict[ast.AST, ast.AST]) -> bool:
    """Inside a function, within the body of a try that catches ImportError."""
    in_try = in_function = False
    child, node = node, parents.get(node)
    while node is not None:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            in_function = True
        if isinstance(node, ast.Try) and child in node.body:
            caught = {n.id for h in node.handlers if h.type is not None
                      for n in ast.walk(h.type) if isinstance(n, ast.Name)}
            in_try |= bool(caught & {"ImportError", "ModuleNotFoundError", "Exception"})
        child, node = node, parents.get(node)
    return in_try and in_function


def test_optional_imports_are_guarded():
    """An extra's module is never needed to import f2l or to run a command that does not use it."""
    problems = []
    for path in _sources():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        parents = {c: p for p in ast.walk(tree) for c in ast.iter_child_nodes(p)}
        for module, node in _imports(tree):
            if module in OPTIONAL_IMPORTS and not _guarded(node, parents):
                problems.append(f"{path.relative_to(REPO)}:{node.lineno}: import {module} is not inside a "
                                "function's try/except ImportError")
    assert not problems, "\n".join(problems)


def test_capture_bench_child_needs_no_extra():
    """`f2l bench-capture`'s timing child (a script in a string) imported pandas, which no plain
    install has: its unconditional imports are declared dependencies or f2l itself."""
    from f2l.dev import bench_capture as bench

    declared = _names(PYPROJECT["project"]["dependencies"])
    owners = _owners()
    tree = ast.parse(bench._CHILD)
    problems = []
    for node in tree.body:  # top level only: a guarded import (try/except ImportError) is optional
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            for module, _ in _imports(node):
                if module in OWN or module in sys.stdlib_module_names:
                    continue
                if not owners.get(module, set()) & declared:
                    problems.append(module)
    assert not problems, f"bench-capture's child imports undeclared modules: {problems}"


def test_ray_executor_without_the_extra_fails_cleanly(small_shards, tmp_path):
    """A plain install has no Ray: `--executor ray` names the extra to install, without a traceback."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['ray'] = None; sys.argv = ['f2l'] + sys.argv[1:]; "
            "from f2l.cli import main; main()")
    proc = subprocess.run([sys.executable, "-c", code, "estimate", str(small_shards), "-m", "sh9", "--out",
                           str(tmp_path / "est"), "--executor", "ray", "--json"], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "pip install 'f2l[ray]'" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.parametrize("missing", ["mitsuba", "anny"])
def test_render_faces_without_the_extra_fails_cleanly(tmp_path, missing):
    """A plain install has no renderer: `f2l render-faces` names the extra, without a traceback."""
    import subprocess
    import sys

    code = (f"import sys; sys.modules[{missing!r}] = None; sys.argv = ['f2l'] + sys.argv[1:]; "
            "from f2l.cli import main; main()")
    proc = subprocess.run([sys.executable, "-c", code, "eval", "render-faces", "--out", str(tmp_path / "pbr"), "--n", "1"],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "pip install 'f2l[render]'" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "pbr").exists()
