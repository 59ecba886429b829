"""The tooling configured in pyproject.toml passes on the whole tree."""

from __future__ import annotations

import subprocess
import sys

from tests.procs import REPO


def test_ruff_clean() -> None:
    out = subprocess.run([sys.executable, "-m", "ruff", "check", "--output-format", "concise",
                          "."], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr


def test_mypy_clean() -> None:
    out = subprocess.run([sys.executable, "-m", "mypy"], cwd=REPO, capture_output=True,
                         text=True, timeout=280)
    assert out.returncode == 0, out.stdout + out.stderr
