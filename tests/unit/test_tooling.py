"""The tooling configured in pyproject.toml passes on the whole tree."""

from __future__ import annotations

import subprocess
import sys
import tomllib

from slamlens.services.harness.procs import REPO


def test_ruff_clean() -> None:
    out = subprocess.run([sys.executable, "-m", "ruff", "check", "--output-format", "concise",
                          "."], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr


def test_mypy_clean() -> None:
    out = subprocess.run([sys.executable, "-m", "mypy"], cwd=REPO, capture_output=True,
                         text=True, timeout=280)
    assert out.returncode == 0, out.stdout + out.stderr


def test_import_layers_are_kept() -> None:
    # import-linter's contracts in pyproject.toml (docs/architecture.md, "Who imports whom")
    out = subprocess.run([sys.executable, "-c", "from importlinter.cli import "
                          "lint_imports_command; lint_imports_command()", "--no-cache"],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "11 kept, 0 broken" in out.stdout, out.stdout


def test_every_service_core_is_checked_for_io() -> None:
    contracts = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["importlinter"][
        "contracts"]
    pure = set(next(c for c in contracts if c["type"] == "forbidden")["source_modules"])
    cores = {f"{c['containers'][0]}.{m.strip()}" for c in contracts if c.get("containers")
             for m in c["layers"][-1].split(":")}
    assert len(cores) >= 30 and cores == pure
