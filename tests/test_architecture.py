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
LAYERS = {"errors": 0, "fileio": 0, "jit_cache": 0, "lazy": 0, "lifetime": 0, "memory": 0, "options_json": 0, "paths": 0,
          "runlock": 0, "threads": 0, "validate": 0,
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


def test_option_dataclasses_are_named_options():
    """One naming rule: what a caller chooses for a run is ``*Options``; ``*Config`` is left to a network's
    architecture, read with its weights (``ViCLIPConfig``)."""
    architectures = {"ViCLIPConfig"}
    named_config = []
    for path in sorted(ENGINE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef) and node.name.endswith("Config") and node.name not in architectures:
                named_config.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name}")
    assert named_config == []


def contract_sections() -> list[tuple[str, str, list[str]]]:
    """(module, section text, listed names) of every ``## ... (`module`)`` section of docs/CONTRACTS.md."""
    text = (REPO / "docs" / "CONTRACTS.md").read_text(encoding="utf-8")
    parts = re.split(r"^(## .*)$", text, flags=re.M)
    out = []
    for heading, body in zip(parts[1::2], parts[2::2]):
        module = re.match(r"^## .*\(`([\w.]+)`", heading)
        names = re.search(r"^Names:\s*(.*?)(?:\n\n|\Z)", body, flags=re.M | re.S)
        if module and names:
            out.append((module.group(1), body, re.findall(r"`(\w+)`", names.group(1))))
    return out


def _call_forms(text: str, name: str) -> list[tuple[str, str]]:
    """(argument list, text after the closing parenthesis) of every documented ``name(...)``."""
    forms = []
    for match in re.finditer(rf"(?<![\w.]){name}\(", text):
        depth, i = 1, match.end()
        while i < len(text) and depth:
            depth += {"(": 1, "[": 1, "{": 1, ")": -1, "]": -1, "}": -1}.get(text[i], 0)
            i += 1
        if not depth:
            forms.append((text[match.end():i - 1], text[i:i + 80]))
    return forms


def _documented_parameters(arguments: str) -> list[tuple[str, bool]]:
    """(name, keyword-only) of each parameter of a documented argument list (shapes and defaults dropped)."""
    pieces, depth, current = [], 0, ""
    for ch in arguments:
        depth += {"(": 1, "[": 1, "{": 1, ")": -1, "]": -1, "}": -1}.get(ch, 0)
        if ch == "," and depth == 0:
            pieces.append(current)
            current = ""
        else:
            current += ch
    pieces.append(current)
    out, keyword_only = [], False
    for piece in (p.strip() for p in pieces):
        if piece == "*":
            keyword_only = True
        elif piece and not piece.startswith(("**", "...")):
            name = re.match(r"^(\w+)", piece)
            if name:
                out.append((name.group(1), keyword_only))
    return out


def documented_signatures() -> list[tuple[str, str, str, str]]:
    """(module, name, argument list, what follows) of every call form of a listed callable name."""
    out = []
    for module, body, names in contract_sections():
        for name in names:
            for arguments, after in _call_forms(body, name):
                out.append((module, name, arguments, after))
    return out


def test_the_contracts_document_call_forms_to_check():
    documented = {(m, n) for m, n, _, _ in documented_signatures()}
    for name in ("splat", "rasterize", "distill_scene", "open_scene", "prepare_highlight_job", "fit_capture",
                 "extract_on_ray", "ensure_demo_bundle", "QueryEngine"):
        assert any(n == name for _, n in documented), name


@pytest.mark.parametrize("module,name,arguments,after", documented_signatures(),
                         ids=[f"{m}.{n}" for m, n, _, _ in documented_signatures()])
def test_documented_signatures_match_the_code(module, name, arguments, after):
    """Every parameter a call form in docs/CONTRACTS.md names exists, in that order and of that kind (after
    ``*``: keyword-only); every required parameter is documented; a documented return type is the annotated
    one."""
    import inspect

    target = getattr(importlib.import_module(module), name)
    signature = inspect.signature(target)
    params = [p for p in signature.parameters.values() if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
    real = {p.name: p for p in params}
    documented = _documented_parameters(arguments)
    unknown = [n for n, _ in documented if n not in real]
    assert unknown == [], f"{name}: documented parameters not in the code: {unknown}"
    order = [list(real).index(n) for n, _ in documented]
    assert order == sorted(order), f"{name}: documented order differs from the code's {list(real)}"
    wrong_kind = [n for n, kw in documented if kw != (real[n].kind == inspect.Parameter.KEYWORD_ONLY)]
    assert wrong_kind == [], f"{name}: positional/keyword-only differs for {wrong_kind}"
    required = [p.name for p in params if p.default is inspect.Parameter.empty]
    missing = [n for n in required if n not in dict(documented)]
    assert missing == [], f"{name}: required parameters not documented: {missing}"
    returned = re.match(r"^\s*->\s*([\w.]+)", after)
    if returned and not inspect.isclass(target):
        annotation = str(signature.return_annotation)
        assert returned.group(1).split(".")[-1] in annotation, f"{name} returns {annotation}, documented {returned.group(1)}"


MAX_FILE_LINES = 500
MAX_FUNCTION_LINES = 100


def oversized_units(root: Path) -> list[str]:
    """Files over :data:`MAX_FILE_LINES` lines and functions over :data:`MAX_FUNCTION_LINES` (their ``def``
    line to their last line, docstring included) under ``root``."""
    problems = []
    for path in sorted(root.rglob("*.py")):
        text = path.read_text(encoding="utf-8")
        lines = len(text.splitlines())
        if lines > MAX_FILE_LINES:
            problems.append(f"{path.relative_to(REPO)}: {lines} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    problems.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name}: {length} lines")
    return problems


def test_no_engine_file_or_function_is_oversized():
    assert oversized_units(ENGINE) == []


def test_no_addon_file_or_function_is_oversized():
    assert oversized_units(REPO / "addon") == []


def test_the_size_check_counts_lines(tmp_path, monkeypatch):
    """A 101-line function and a 501-line file are reported (the check can fail)."""
    module = tmp_path / "big.py"
    body = "\n".join(f"    x{i} = {i}" for i in range(99))
    module.write_text("def f():\n" + body + "\n    return 0\n" + "\n" * 400, encoding="utf-8")
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    assert oversized_units(tmp_path) == ["big.py: 501 lines", "big.py:1 f: 101 lines"]


def load_time_imports(path: Path) -> set[str]:
    """The engine modules importing ``path`` imports at once: its top-level imports (``if TYPE_CHECKING``
    blocks and imports inside functions left out), each with its parent packages."""
    modules = set(engine_modules())
    name = ".".join(path.relative_to(REPO).with_suffix("").parts)
    package = name.rpartition(".")[0] if path.name != "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()

    def visit(statements: list[ast.stmt]) -> None:
        for node in statements:
            if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
                continue
            if isinstance(node, (ast.If, ast.Try)):
                visit(node.body + node.orelse + [s for h in getattr(node, "handlers", []) for s in h.body])
            elif isinstance(node, ast.Import):
                found.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
                module = ".".join(base + ([node.module] if node.module else []))
                found.add(module)
                found.update(f"{module}.{alias.name}" for alias in node.names)

    visit(ast.parse(path.read_text(encoding="utf-8")).body)
    with_parents = {".".join(m.split(".")[:i]) for m in found for i in range(1, len(m.split(".")) + 1)}
    own = name[: -len(".__init__")] if name.endswith(".__init__") else name
    return {m for m in with_parents if m in modules and m != own}


def test_engine_modules_import_each_other_without_a_cycle():
    graph = {}
    for path in sorted(ENGINE.rglob("*.py")):
        parts = path.relative_to(REPO).with_suffix("").parts
        graph[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = load_time_imports(path)
    visiting, done, cycles = [], set(), []

    def walk(module: str) -> None:
        if module in done:
            return
        if module in visiting:
            cycles.append(visiting[visiting.index(module):] + [module])
            return
        visiting.append(module)
        for target in sorted(graph[module]):
            walk(target)
        visiting.pop()
        done.add(module)

    for module in sorted(graph):
        walk(module)
    assert cycles == []
