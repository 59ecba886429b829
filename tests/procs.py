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


def netns_cmd(namespace: str, *args: str) -> list[str]:
    """``args`` (a command line) run inside network namespace ``namespace``."""
    return ["ip", "netns", "exec", namespace, *args]


def spawn_in(namespace: str, *args: str, module: str = "services") -> subprocess.Popen:
    """A slamlens service (or another ``python -m`` module) as a real process inside a
    network namespace (stdout/stderr piped)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(netns_cmd(namespace, sys.executable, "-m", module, *args), cwd=REPO,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


class Output:
    """A process's stdout and stderr, collected line by line as it writes them, so a test
    waits for a line with a real timeout (a bare ``readline`` blocks until a line comes)."""

    def __init__(self, proc: subprocess.Popen) -> None:
        import threading

        self.proc = proc
        self.stdout: list[str] = []
        self.stderr: list[str] = []
        self._cond = threading.Condition()
        self._threads = [threading.Thread(target=self._read, args=(pipe, lines), daemon=True)
                         for pipe, lines in ((proc.stdout, self.stdout),
                                             (proc.stderr, self.stderr)) if pipe is not None]
        for t in self._threads:
            t.start()

    def _read(self, pipe, lines: list[str]) -> None:
        for line in pipe:
            with self._cond:
                lines.append(line.rstrip("\n"))
                self._cond.notify_all()
        with self._cond:
            self._cond.notify_all()

    def wait(self, text: str, *, stream: str = "stdout", timeout: float = 60.0) -> str:
        """The first line of ``stream`` containing ``text``; fails after ``timeout`` s or
        when the process exits without writing it."""
        lines = self.stdout if stream == "stdout" else self.stderr

        def found() -> str | None:
            return next((x for x in lines if text in x), None)

        with self._cond:
            self._cond.wait_for(lambda: found() is not None or self.proc.poll() is not None,
                                timeout)
            line = found()
        if line is None and self.proc.poll() is not None:
            for t in self._threads:  # it exited: take in what it wrote last
                t.join(timeout=5)
            with self._cond:
                line = found()
        if line is None:
            raise AssertionError(f"{self.proc.args} never wrote {text!r} "
                                 f"(exit status {self.proc.poll()}); stderr:\n"
                                 + "\n".join(self.stderr[-30:]))
        return line

    def stop(self, timeout: float = 10.0) -> int:
        """SIGTERM the process, wait for it and its output; its exit status."""
        if self.proc.poll() is None:
            self.proc.terminate()
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            raise AssertionError(f"{self.proc.args} did not exit on SIGTERM") from None
        for t in self._threads:
            t.join(timeout=5)
        for pipe in (self.proc.stdout, self.proc.stderr):
            if pipe is not None:
                pipe.close()
        return self.proc.returncode
