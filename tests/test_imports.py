"""The modules' roles show in their imports: no two voxtool modules import each other (a package's
__init__ that imports its own submodules lazily aside). grid <-> ground and sources.rosbag <->
sources.bag1_linear did: the ground model builds on the grid, and both bag readers on the bag
limits module."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "voxtool"


def _imports() -> dict[str, set[str]]:
    modules = {".".join(f.relative_to(ROOT.parent).with_suffix("").parts): f for f in ROOT.rglob("*.py")
               if f.name != "__init__.py"}
    graph = {}
    for name, path in modules.items():
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):  # function-level imports too
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("voxtool"):
                deps.add(node.module)
                deps.update(f"{node.module}.{a.name}" for a in node.names)
            elif isinstance(node, ast.Import):
                deps.update(a.name for a in node.names if a.name.startswith("voxtool"))
        graph[name] = deps & set(modules)
    return graph


def test_no_two_modules_import_each_other():
    graph = _imports()
    assert len(graph) > 50 and "voxtool.ground" in graph["voxtool.clean"] | graph["voxtool.io.export"]
    circles = sorted((a, b) for a in graph for b in graph[a] if a < b and a in graph[b])
    assert circles == []
