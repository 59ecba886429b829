"""Starting and stopping slamlens services as real processes, for tests.

A :class:`Service` reads its process's stdout and stderr on two threads, so a chatty
service never blocks on a full pipe, ``wait_for_line`` really times out (a bare
``readline`` would wait forever for a silent process), and the whole output is there
when the test stops it.
"""

from __future__ import annotations

import ctypes
import functools
import os
import platform
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO

REPO = Path(__file__).resolve().parents[2]  #: the checkout (services/harness/ is in it)


def slamlens_cmd(*args: str) -> list[str]:
    """Command line running the slamlens CLI with this interpreter (no PATH needed)."""
    return [sys.executable, "-m", "slamlens.services", *args]


class Service:
    """A running slamlens process; most of :class:`subprocess.Popen` is passed through."""

    def __init__(self, argv: list[str], *, env: dict[str, str] | None = None,
                 cwd: Path = REPO, stdin: bool = False) -> None:
        full_env = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
        self.proc = subprocess.Popen(argv, cwd=cwd, env=full_env, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True,
                                     stdin=subprocess.PIPE if stdin else None)
        self.args = argv
        self.out: list[str] = []
        self.err: list[str] = []
        self._lines: queue.Queue[str | None] = queue.Queue()
        self._readers = [
            threading.Thread(target=self._read, args=(self.proc.stdout, self.out, True),
                             daemon=True),
            threading.Thread(target=self._read, args=(self.proc.stderr, self.err, False),
                             daemon=True)]
        for t in self._readers:
            t.start()

    def _read(self, pipe: IO[str] | None, into: list[str], lines: bool) -> None:
        assert pipe is not None
        with pipe:
            for line in pipe:
                into.append(line)
                if lines:
                    self._lines.put(line)
        if lines:
            self._lines.put(None)

    def send(self, line: str) -> None:
        """Write one line to the process's standard input (``stdin=True``)."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    # -- Popen-like ------------------------------------------------------------------
    @property
    def pid(self) -> int:
        return self.proc.pid

    @property
    def returncode(self) -> int | None:
        return self.proc.returncode

    def poll(self) -> int | None:
        return self.proc.poll()

    def send_signal(self, sig: int) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def wait(self, timeout: float | None = None) -> int:
        return self.proc.wait(timeout)

    def communicate(self, timeout: float | None = None) -> tuple[str, str]:
        """Wait for the process to end by itself; its whole stdout and stderr."""
        self.proc.wait(timeout)
        return self.output()

    def output(self) -> tuple[str, str]:
        if self.proc.stdin is not None and not self.proc.stdin.closed:
            try:
                self.proc.stdin.close()
            except OSError:  # the process is gone: nothing to flush into
                pass
        for t in self._readers:
            t.join(timeout=5.0)
        return "".join(self.out), "".join(self.err)

    def threads(self) -> dict[int, str]:
        """Thread id → kernel name of each of the process's threads, the main one (tid ==
        pid) first; {} once it is gone."""
        found: dict[int, str] = {}
        try:
            tids = sorted(int(t) for t in os.listdir(f"/proc/{self.proc.pid}/task"))
        except OSError:
            return found
        for tid in sorted(tids, key=lambda t: t != self.proc.pid):
            try:
                found[tid] = Path(f"/proc/{self.proc.pid}/task/{tid}/comm").read_text().strip()
            except OSError:  # the thread ended meanwhile
                continue
        return found

    def cpu_seconds(self) -> float | None:
        """User + system CPU seconds the process has used so far (None once it is gone)."""
        try:
            fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            return None
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    # -- waiting on what it says -------------------------------------------------------
    def wait_for_line(self, text: str, timeout: float = 60.0) -> str:
        """The first line from now on containing ``text``; AssertionError after
        ``timeout`` s or if the process ends first."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"{self.args[3:]} never printed {text!r} in {timeout} s;"
                                     f" stderr tail:\n{''.join(self.err[-15:])}")
            try:
                line = self._lines.get(timeout=min(left, 0.5))
            except queue.Empty:
                continue
            if line is None:
                self._lines.put(None)  # stay at end of file for later callers
                self.proc.wait(10)
                raise AssertionError(f"{self.args[3:]} exited {self.proc.returncode} before "
                                     f"printing {text!r}; stderr:\n{''.join(self.err[-30:])}")
            if text in line:
                return line


#: the tgkill system call's number (not in Python's os module)
SYS_TGKILL = {"x86_64": 234, "aarch64": 131}


@functools.cache
def _libc() -> ctypes.CDLL:
    return ctypes.CDLL(None, use_errno=True)


def tgkill(pid: int, tid: int, sig: int) -> None:
    """Send ``sig`` to thread ``tid`` of process ``pid`` only (as the kernel may deliver a
    process-directed signal to any thread that does not block it); OSError if the thread
    is gone."""
    if _libc().syscall(SYS_TGKILL[platform.machine()], pid, tid, sig) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, f"tgkill({pid}, {tid}, {sig}): {os.strerror(errno)}")


def spawn(*args: str, env: dict[str, str] | None = None, netns: str | None = None) -> Service:
    """Start a slamlens service as a real process (optionally in a network namespace)."""
    argv = slamlens_cmd(*args)
    if netns is not None:
        argv = ["ip", "netns", "exec", netns, *argv]
    return Service(argv, env=env)


def stop(proc: Service, timeout: float = 10.0, *, sig: int = signal.SIGTERM) -> tuple[str, str]:
    """Signal a service (SIGTERM) and collect its output; fail loudly if it will not exit."""
    proc.send_signal(sig)
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise AssertionError(f"{proc.args} did not exit on signal {sig}; stderr:\n"
                             f"{''.join(proc.err[-30:])}") from None
    return proc.output()


def wait_for_line(proc: Service, text: str, timeout: float = 60.0) -> str:
    """Read a service's stdout until a line contains ``text`` (e.g. "estimator ready")."""
    return proc.wait_for_line(text, timeout)


class Started:
    """The services one test or benchmark starts, each once it printed its ready line;
    :meth:`stop_all` (in a ``finally``) stops those still running, the last started first
    (the router, started first, goes last)."""

    def __init__(self) -> None:
        self.procs: list[Service] = []

    def add(self, proc: Service, *, ready: str | None = None) -> Service:
        """``proc``, kept to be stopped, once it printed ``ready`` (if given)."""
        self.procs.append(proc)
        if ready is not None:
            proc.wait_for_line(ready)
        return proc

    def start(self, *args: str, ready: str, netns: str | None = None) -> Service:
        """``slamlens ARGS`` (in network namespace ``netns``), once it printed ``ready``."""
        return self.add(spawn(*args, netns=netns), ready=ready)

    def stop_all(self) -> None:
        for proc in reversed(self.procs):
            if proc.poll() is None:
                stop(proc)
