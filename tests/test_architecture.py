"""The package structure holds: one-way imports in the engine, no benchmarks or add-on inside it, the
add-on reaching the engine only through its facade, and every name docs/CONTRACTS.md lists importable."""
from __future__ import annotations

import ast
import importlib
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ENGINE = REPO / "fourlegs_engine"
#: engine packages in data-flow order; a module may import its own layer and the ones before it; the
#: command line (``commands``) is the last layer and the only one that may use argparse
LAYERS = {"errors": 0, "fileio": 0, "lazy": 0, "options_json": 0, "paths": 0, "threads": 0, "validate": 0,
          "scene": 1, "render": 2, "fit": 3, "language": 3, "cluster": 3, "demo": 4, "query": 5, "highlights": 6,
          "pipeline": 7, "highlight_job": 8, "api": 8, "commands": 9}
FORBIDDEN = ("fourlegs_bench", "fourlegs_addon", "bpy")


def engine_modules() -> list[str]:
    names = []
    for path in sorted(ENGINE.rglob("*.py")):
        parts = path.relative_to(REPO).with_suffix("").parts
        names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


def imported_modules(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module) of every import in ``path``, relative ones resolved; string arguments of
    ``importlib.import_module`` / ``__import__`` count as imports too."""
    package = ".".join(path.relative_to(REPO).with_suffix("").parts[:-1])
    if path.name == "__init__.py":
        package = ".".join(path.relative_to(REPO).parts[:-1])
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            out.append((node.lineno, module))
            if not node.module:  # from . import x, y: x and y may be modules
                out += [(node.lineno, f"{module}.{alias.name}") for alias in node.names]
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) in (
                "import_module", "__import__") and node.args and isinstance(node.args[0], ast.Constant):
            out.append((node.lineno, str(node.args[0].value)))
    return out


def layer_of(module: str) -> int | None:
    parts = module.split(".")
    if parts[0] != "fourlegs_engine" or len(parts) < 2:
        return None
    return LAYERS.get(parts[1])


def test_engine_imports_run_one_way_and_never_reach_benchmarks_or_the_addon():
    problems = []
    for path in sorted(ENGINE.rglob("*.py")):
        own = layer_of(".".join(path.relative_to(REPO).with_suffix("").parts))
        for line, module in imported_modules(path):
            where = f"{path.relative_to(REPO)}:{line}"
            if module.split(".")[0] in FORBIDDEN:
                problems.append(f"{where} imports {module}")
            target = layer_of(module)
            if own is not None and target is not None and target > own:
                problems.append(f"{where} imports {module} against the data flow")
    assert problems == []


def test_every_engine_module_and_package_has_a_layer():
    """A module or package missing from LAYERS would go unchecked."""
    tops = {p.stem for p in ENGINE.glob("*.py") if p.stem != "__init__"}
    tops |= {p.name for p in ENGINE.iterdir() if (p / "__init__.py").is_file()}
    assert sorted(tops - set(LAYERS)) == []


def test_argparse_lives_only_in_the_command_line():
    users = [str(p.relative_to(REPO)) for p in sorted(ENGINE.rglob("*.py"))
             if "argparse" in {m for _, m in imported_modules(p)} and "commands" not in p.relative_to(ENGINE).parts]
    assert users == []


def test_the_layer_check_catches_a_violation(tmp_path):
    """The scan really resolves relative imports (a check that cannot fail would prove nothing)."""
    bad = ENGINE / "scene" / "_probe_violation.py"
    assert not bad.exists()
    bad.write_text("from ..query import engine\nfrom fourlegs_bench import metrics\n", encoding="utf-8")
    try:
        found = [m for _, m in imported_modules(bad)]
    finally:
        bad.unlink()
    assert "fourlegs_engine.query" in found and "fourlegs_bench" in found
    assert layer_of("fourlegs_engine.query") > layer_of("fourlegs_engine.scene.bundle")


def test_importing_every_engine_module_loads_neither_benchmarks_nor_the_addon_nor_bpy():
    code = ("import importlib, json, sys\n"
            f"for name in {engine_modules()!r}:\n"
            "    importlib.import_module(name)\n"
            f"print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in {FORBIDDEN!r})))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == []


def test_addon_reaches_the_engine_only_through_its_facade():
    """What runs in Blender imports ``fourlegs_engine.api`` (the headless job also the command-line
    helpers); the build script and the ``fourlegs`` command registration run outside Blender."""
    from fourlegs_addon.build import NOT_IN_BLENDER

    allowed = {"fourlegs_engine.api", "fourlegs_engine.commands.options", "fourlegs_engine"}
    problems = []
    for path in sorted((REPO / "addon").glob("*.py")):
        text = path.read_text(encoding="utf-8")
        assert "engine_module(" not in text, path
        if path.name in NOT_IN_BLENDER:
            continue
        for line, module in imported_modules(path):
            if module.startswith("fourlegs_engine") and module not in allowed:
                problems.append(f"{path.name}:{line} imports {module}")
            if module == "fourlegs_engine":  # `from fourlegs_engine import X`: X must be the facade
                names = [n for n in re.findall(r"from fourlegs_engine import (\w+)", text)]
                problems += [f"{path.name} imports fourlegs_engine.{n}" for n in names if n != "api"]
    assert sorted(set(problems)) == []


def contract_names() -> list[tuple[str, str]]:
    """(module, name) of every ``Names:`` line in docs/CONTRACTS.md, under its section's module."""
    text = (REPO / "docs" / "CONTRACTS.md").read_text(encoding="utf-8")
    out, module = [], None
    for line in text.splitlines():
        heading = re.match(r"^## .*\(`([\w.]+)`", line)
        if heading:
            module = heading.group(1)
        names = re.match(r"^Names:\s*(.*)$", line)
        if names:
            assert module is not None, line
            out += [(module, n) for n in re.findall(r"`(\w+)`", names.group(1))]
    return out


def test_contracts_lists_names_for_every_package():
    modules = {m for m, _ in contract_names()}
    for package in ("fourlegs_engine.scene", "fourlegs_engine.render", "fourlegs_engine.language",
                    "fourlegs_engine.query", "fourlegs_engine.highlights", "fourlegs_engine.pipeline",
                    "fourlegs_engine.api"):
        assert package in modules, package


@pytest.mark.parametrize("module,name", contract_names())
def test_every_name_in_the_contracts_is_exported(module, name):
    mod = importlib.import_module(module)
    assert hasattr(mod, name), f"{module}.{name}"
    assert name in getattr(mod, "__all__", ()), f"{name} missing from {module}.__all__"


TORCH_PROBE = ("import json, sys\n"
               "from fourlegs_engine.commands.main import main\n"
               "try:\n"
               "    code = main(sys.argv[1:])\n"
               "except SystemExit as exc:\n"
               "    code = exc.code\n"
               "print(json.dumps({'code': code, 'torch': 'torch' in sys.modules}))\n")


def _command_modules_loaded(argv: list[str], tmp_path: Path) -> dict:
    """Run ``fourlegs ARGV`` in a fresh interpreter: its exit code and whether torch got imported."""
    proc = subprocess.run([sys.executable, "-c", TORCH_PROBE, *argv], capture_output=True, text=True, cwd=tmp_path,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("argv", [["--help"], ["info", "--help"], ["highlight", "--help"], ["query", "--help"]])
def test_help_imports_no_torch(argv, tmp_path):
    assert _command_modules_loaded(argv, tmp_path) == {"code": 0, "torch": False}


def test_info_of_a_ply_imports_no_torch(tmp_path):
    """`fourlegs info` of a scene on disk reads numpy arrays; torch would only cost seconds of start-up."""
    import numpy as np

    from fourlegs_engine.scene.ply import read_ply_splats, write_ply_splats

    rng = np.random.default_rng(0)
    n = 7
    path = write_ply_splats(tmp_path / "splats.ply", rng.normal(size=(n, 3)), np.tile([1.0, 0, 0, 0], (n, 1)),
                            np.full((n, 3), -2.0), np.zeros(n), rng.uniform(size=(n, 1, 3)))
    assert read_ply_splats(path).means.shape == (n, 3)
    assert _command_modules_loaded(["info", str(path), "--json"], tmp_path) == {"code": 0, "torch": False}
