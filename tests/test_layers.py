"""The layers contract (DESIGN: "Repository layout"): a package imports only from layers below it
or from itself, counting imports inside functions too, so no package cycle can hide behind a
deferred import. Layers, lowest first."""

from __future__ import annotations

from collections import defaultdict

from tests.test_plugins import _import_graph

LAYERS = (
    ("lighting",),
    ("io",),
    ("models", "transport"),
    ("face",),
    ("colour",),
    ("capture",),
    ("metrics",),
    ("estimate",),
    ("synth",),
    ("pipeline", "prior", "render", "testing"),
    ("video",),
    ("evaluation",),
    ("report",),
    ("demo", "dev"),
    ("api", "cli"),
)
"""f2l's packages (and top-level modules) by layer. ``face`` (photo decoding, landmarks, the face
fit), ``colour`` (which decodes chart photos with it) and ``capture`` (whose ingest detects faces and
charts to give files a role) sit below ``estimate``;
``synth`` (synthetic faces and skies) above it; the evaluation renders, the prior builder, the build pipeline and
the test fixtures above those; the evaluation harness (render, fit, estimate, score) above them; benchmarks, the Python API and the command line on top."""


def _package(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "f2l"


def _package_edges() -> dict[tuple[str, str], list[str]]:
    edges = defaultdict(list)
    for a, targets in _import_graph().items():
        for b in targets:
            pa, pb = _package(a), _package(b)
            if pa != pb and "f2l" not in (pa, pb):
                edges[(pa, pb)].append(f"{a} -> {b}")
    return edges


def test_every_package_has_a_layer():
    ranked = {p for layer in LAYERS for p in layer}
    packages = {_package(m) for m in _import_graph()} - {"f2l"}
    assert packages <= ranked, f"packages without a layer: {sorted(packages - ranked)}"


def test_no_package_imports_upward_or_sideways():
    rank = {p: i for i, layer in enumerate(LAYERS) for p in layer}
    bad = [f"{pa} ({rank[pa]}) imports {pb} ({rank[pb]}): {', '.join(sorted(ex)[:3])}"
           for (pa, pb), ex in sorted(_package_edges().items()) if rank[pb] >= rank[pa]]
    assert not bad, "\n".join(bad)


def test_the_contract_sees_real_edges():
    edges = _package_edges()
    assert ("estimate", "transport") in edges and ("cli", "estimate") in edges and ("face", "io") in edges
