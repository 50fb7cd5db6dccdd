"""The add-on's modules import each other without a cycle (checked on the source with ``ast``, without
Blender). Its size limits are checked with the engine's in test_architecture.py."""
from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ADDON = REPO / "addon"


def addon_imports(path: Path, modules: set[str]) -> set[str]:
    """The add-on modules (by file stem) that ``path`` imports anywhere in it, in a function or not."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            if node.level == 1 and node.module:
                out.add(node.module.split(".")[0])
            elif node.level == 1:
                out |= {alias.name for alias in node.names}
            elif node.module and node.module.split(".")[0] == "fourlegs_addon":
                parts = node.module.split(".")
                out |= {parts[1]} if len(parts) > 1 else {alias.name for alias in node.names}
        elif isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                if parts[0] == "fourlegs_addon" and len(parts) > 1:
                    out.add(parts[1])
    return {m for m in out if m in modules and m != path.stem}


def import_graph(folder: Path) -> dict[str, set[str]]:
    files = {p.stem: p for p in sorted(folder.glob("*.py"))}
    return {name: addon_imports(path, set(files)) for name, path in files.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str]:
    """One import cycle as [a, b, ..., a], or [] when the graph has none (depth-first search)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: finished
    path: list[str] = []

    def visit(node: str) -> list[str]:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        path.pop()
        state[node] = 2
        return []

    for node in sorted(graph):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return []


def test_the_addon_import_graph_has_no_cycle():
    graph = import_graph(ADDON)
    assert {"operators", "prepare", "jobs", "importer"} <= set(graph)
    assert "jobs" in graph["prepare"] and "jobs" in graph["query_ops"]  # one job runner, used by both
    assert find_cycle(graph) == []


def test_the_cycle_check_finds_a_cycle_through_an_import_inside_a_function(tmp_path):
    """A check that cannot fail proves nothing: two modules importing each other, one of them lazily."""
    (tmp_path / "operators.py").write_text("from . import importer, prepare\n", encoding="utf-8")
    (tmp_path / "prepare.py").write_text("def run():\n    from .operators import _err\n", encoding="utf-8")
    (tmp_path / "importer.py").write_text("import numpy\nfrom fourlegs_addon import convert\n", encoding="utf-8")
    graph = import_graph(tmp_path)
    assert graph == {"importer": set(), "operators": {"importer", "prepare"}, "prepare": {"operators"}}
    assert find_cycle(graph) == ["operators", "prepare", "operators"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) == []
