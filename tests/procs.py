"""Starting and stopping slamlens services as real processes, for tests."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def slamlens_cmd(*args: str) -> list[str]:
    """Command line running the slamlens CLI with this interpreter (no PATH needed)."""
    return [sys.executable, "-m", "services", *args]


def spawn(*args: str, **kw) -> subprocess.Popen:
    """Start a slamlens service as a real process (stdout/stderr piped)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(slamlens_cmd(*args), cwd=REPO, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, **kw)


def stop(proc: subprocess.Popen, timeout: float = 10.0) -> tuple[str, str]:
    """SIGTERM a service and collect its output; fail loudly if it will not exit."""
    if proc.poll() is None:
        proc.terminate()
    elif proc.stdout is not None and proc.stdout.closed:
        return "", ""  # already stopped and collected
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        raise AssertionError(f"{proc.args} did not exit on SIGTERM; stderr:\n{err}") from None
    return out, err
