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


def wait_for_line(proc: subprocess.Popen, text: str, timeout: float = 60.0) -> None:
    """Read a service's stdout until a line contains ``text`` (e.g. "estimator ready")."""
    import time

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stdout.readline() if proc.stdout else ""
        if text in line:
            return
        if proc.poll() is not None:
            err = proc.stderr.read() if proc.stderr else ""
            raise AssertionError(f"{proc.args} exited {proc.returncode}: {err}")
    raise AssertionError(f"{proc.args} never printed {text!r}")
