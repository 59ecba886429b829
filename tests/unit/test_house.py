"""The house keeps its shape: sizes, one-way imports, flags from settings, no outside refs.

Every module at most 600 lines, class 300, function 80 (the package's, tests/ and benchmarks/);
no import circle between the project's modules; no command-line flag declared anywhere but the
settings machinery (common/config.py); benchmarks never import tests/ (they share the
harness, services/harness/); no code, docstring or help text refers to the outside
specification the project started from, or to an issue number (docs/ is where the contract
lives; tests and benchmarks point to docs/ as well).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from slamlens.services.harness.procs import REPO

MODULE_LINES, CLASS_LINES, FUNCTION_LINES = 600, 300, 80
#: the settings machinery: the only place that may call ``add_argument``
FLAG_MAKERS = {"common/config.py"}


def _package_files() -> list[Path]:
    return sorted(p for root in ("common", "services") for p in (REPO / root).rglob("*.py"))


def _rel(path: Path) -> str:
    return str(path.relative_to(REPO))


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    name = "slamlens." + ".".join(parts)
    return name.removesuffix(".__init__")


def _tree(path: Path) -> ast.Module:
    return ast.parse(path.read_text(), _rel(path))


def _sized_files() -> list[Path]:
    """The files held to the sizes: the package's, the tests' and the benchmarks'."""
    return _package_files() + sorted(p for root in ("tests", "benchmarks")
                                     for p in (REPO / root).rglob("*.py"))


def test_modules_classes_and_functions_are_within_their_sizes() -> None:
    found = []
    for path in _sized_files():
        lines = path.read_text().count("\n")
        if lines > MODULE_LINES:
            found.append(f"{_rel(path)}: {lines} lines (> {MODULE_LINES})")
        for node in ast.walk(_tree(path)):
            length = getattr(node, "end_lineno", 0) - getattr(node, "lineno", 0)
            if isinstance(node, ast.ClassDef) and length > CLASS_LINES:
                found.append(f"{_rel(path)}: class {node.name} {length} lines")
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) \
                    and length > FUNCTION_LINES:
                found.append(f"{_rel(path)}: function {node.name} {length} lines")
    assert not found, "over the house's limits:\n" + "\n".join(found)


def _imports(path: Path, modules: set[str]) -> set[str]:
    """The project modules ``path`` imports (at any depth of the file)."""
    me = _module_name(path)
    out = set()
    for node in ast.walk(_tree(path)):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        for name in names:
            while name and name not in modules:
                name = name.rpartition(".")[0]
            if name and name != me:
                out.add(name)
    return out


def test_there_is_no_import_circle() -> None:
    files = {_module_name(p): p for p in _package_files()}
    graph = {m: _imports(p, set(files)) for m, p in files.items()}
    circles = []
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                circles.append(" <-> ".join(sorted(component)))

    for module in graph:
        if module not in index:
            visit(module)
    assert not circles, "import circles:\n" + "\n".join(circles)


def test_flags_are_declared_only_by_the_settings_machinery() -> None:
    found = []
    for path in _package_files():
        if _rel(path) in FLAG_MAKERS:
            continue
        for node in ast.walk(_tree(path)):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                    and node.func.attr == "add_argument":
                found.append(f"{_rel(path)}:{node.lineno}")
    assert not found, "flags declared by hand (use common.config.setting):\n" + \
        "\n".join(found)


def test_benchmarks_and_the_package_never_import_tests() -> None:
    found = []
    for path in [*_package_files(), *sorted((REPO / "benchmarks").rglob("*.py"))]:
        for node in ast.walk(_tree(path)):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                     [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            if any(n == "tests" or n.startswith("tests.") for n in names):
                found.append(f"{_rel(path)}:{node.lineno}")
            # nor by putting a folder of tests/ on the import path
            if isinstance(node, ast.Call) and "sys.path" in ast.unparse(node.func) \
                    and "'tests'" in ast.unparse(node):  # (unparse quotes with ')
                found.append(f"{_rel(path)}:{node.lineno} (sys.path)")
    assert not found, "imports of tests/ (use slamlens.services.harness):\n" + "\n".join(found)


@pytest.mark.parametrize("pattern,what", [
    #: (spelt in two halves so that this file does not name it)
    (re.compile(r"\bSP" + r"EC\b"), "a document outside the repository (point to docs/)"),
    (re.compile(r"\b[Ii]ssues? #?\d+"), "an issue number (history lives in git)"),
])
def test_code_and_help_texts_refer_to_nothing_outside_the_repository(pattern, what) -> None:
    texts = [*_package_files(), *(REPO / "services").rglob("*.js"),
             *(REPO / "services").rglob("*.html"), *(REPO / "deploy").rglob("*"),
             REPO / "pyproject.toml", REPO / "README.md", *(REPO / "docs").glob("*.md")]
    if "docs/" in what:  # the contract's references: tests and benchmarks too
        texts += [*(REPO / "tests").rglob("*.py"), *(REPO / "benchmarks").rglob("*.py"),
                  *(REPO / "benchmarks").rglob("*.toml"), REPO / ".ci" / "run"]
    found = [f"{_rel(p)}:{n}" for p in texts if p.is_file()
             for n, line in enumerate(p.read_text(errors="replace").splitlines(), 1)
             if pattern.search(line)]
    assert not found, f"refers to {what}:\n" + "\n".join(found)
