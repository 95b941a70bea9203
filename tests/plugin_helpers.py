"""Register plugins the way an installed outside package does: a *.dist-info with entry_points.txt."""

from __future__ import annotations

import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
EXAMPLE_PLUGIN_DIR = REPO / "plugins" / "example_directional"


def make_dist(site: Path, dist_name: str, entry_points: dict[str, str], version: str = "0.1.0") -> Path:
    """Write a minimal installed-distribution record into ``site`` (a directory on sys.path)."""
    info = site / f"{dist_name.replace('-', '_')}-{version}.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist_name}\nVersion: {version}\n")
    lines = ["[f2l.lighting_models]"] + [f"{k} = {v}" for k, v in entry_points.items()]
    (info / "entry_points.txt").write_text("\n".join(lines) + "\n")
    return info


def plugin_env(site: Path) -> dict:
    """Environment for a subprocess that sees ``site`` and the example plugin's source."""
    env = dict(os.environ)
    extra = [str(site), str(EXAMPLE_PLUGIN_DIR)]
    env["PYTHONPATH"] = os.pathsep.join(extra + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    return env


def f2l_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "f2l.cli", *args]
