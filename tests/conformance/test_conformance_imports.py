"""The conformance suite speaks only docs/protocol.md: no file in tests/conformance imports
the project (``slamlens``, ``tests``, ``common``, ``services`` …). Every import, read with
``ast``, must be the standard library, pytest, zenoh, msgpack, numpy, scipy, or one of the
suite's own modules beside it."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
THIRD_PARTY = {"pytest", "zenoh", "msgpack", "numpy", "scipy"}
LOCAL = {p.stem for p in HERE.glob("*.py")}


def imported(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, top-level module) of every import in ``tree``, dynamic ones included."""
    out: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name.split(".")[0]) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            out.append((node.lineno, "." * node.level + (node.module or "").split(".")[0]))
        elif isinstance(node, ast.Call) and node.args and (
                getattr(node.func, "id", None) == "__import__"
                or getattr(node.func, "attr", None) == "import_module"):
            arg = node.args[0]
            name = arg.value if isinstance(arg, ast.Constant) else "<computed>"
            out.append((node.lineno, str(name).split(".")[0]))
    return out


def test_no_file_imports_the_project() -> None:
    allowed = set(sys.stdlib_module_names) | THIRD_PARTY | LOCAL
    files = sorted(HERE.glob("*.py"))
    assert len(files) >= 5
    wrong = [f"{path.name}:{line}: import {name}"
             for path in files
             for line, name in imported(ast.parse(path.read_text(), filename=str(path)))
             if name not in allowed or name in ("slamlens", "tests", "common", "services")]
    assert not wrong, "tests/conformance may not import the project:\n" + "\n".join(wrong)


def test_the_rule_sees_every_kind_of_import() -> None:
    source = ("import slamlens.common\nfrom tests.procs import spawn\nfrom . import x\n"
              "__import__('services')\nimportlib.import_module('common.keys')\n")
    assert [name for _, name in imported(ast.parse(source))] == [
        "slamlens", "tests", ".", "services", "common"]
