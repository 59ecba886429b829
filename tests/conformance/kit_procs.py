"""Processes for the conformance suite: started as a user starts them, read line by line.

Nothing here imports the project: the services run as ``slamlens COMMAND`` (the console
script beside this interpreter, else ``python -m slamlens.services``) in subprocesses.
"""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import IO

#: the repository (for the working directory of the processes)
ROOT = Path(__file__).resolve().parents[2]


def slamlens(*args: str) -> list[str]:
    """The command line of ``slamlens ARGS`` as a user of this virtual environment types it."""
    script = Path(sys.executable).parent / "slamlens"
    if script.exists():
        return [str(script), *args]
    return [sys.executable, "-m", "slamlens.services", *args]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


#: every process started here, in order (a test's leftovers are killed after it: conftest)
LAUNCHED: list[Proc] = []


class Proc:
    """A running process whose stdout and stderr are read on threads (a chatty process
    never blocks on a full pipe) and kept; stdout lines can be waited for."""

    def __init__(self, argv: list[str], *, name: str = "") -> None:
        LAUNCHED.append(self)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.argv = argv
        self.name = name or " ".join(argv[1:3])
        self.proc = subprocess.Popen(argv, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        self.out: list[str] = []
        self.err: list[str] = []
        self._lines: queue.Queue[str | None] = queue.Queue()
        self._threads = [threading.Thread(target=self._read, args=(pipe, into, tell),
                                          daemon=True)
                         for pipe, into, tell in ((self.proc.stdout, self.out, True),
                                                  (self.proc.stderr, self.err, False))]
        for t in self._threads:
            t.start()

    def _read(self, pipe: IO[str] | None, into: list[str], tell: bool) -> None:
        assert pipe is not None
        with pipe:
            for line in pipe:
                into.append(line)
                if tell:
                    self._lines.put(line)
        if tell:
            self._lines.put(None)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def tail(self, lines: int = 30) -> str:
        return ("".join(self.out[-lines:]) + "--- stderr ---\n" + "".join(self.err[-lines:]))

    def wait_for_line(self, text: str, timeout: float = 60.0) -> str:
        """The first stdout line from now on containing ``text``. Fails if the process
        ends first; ``timeout`` only bounds a failing test."""
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise AssertionError(f"{self.name} never printed {text!r}:\n{self.tail()}")
            try:
                line = self._lines.get(timeout=min(left, 0.5))
            except queue.Empty:
                continue
            if line is None:
                self._lines.put(None)
                self.proc.wait(10)
                raise AssertionError(f"{self.name} exited {self.proc.returncode} before "
                                     f"printing {text!r}:\n{self.tail()}")
            if text in line:
                return line

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 15.0) -> int:
        """Signal the process and wait for it; its exit status."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            code = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            code = self.proc.wait()
        for t in self._threads:
            t.join(timeout=5.0)
        return code


def launch(*args: str) -> Proc:
    """``slamlens ARGS``, started (not waited for)."""
    return Proc(slamlens(*args), name=f"slamlens {args[0]}")


def wait_ready(proc: Proc, text: str, timeout: float = 60.0) -> str:
    """The line of ``proc`` that says ``text`` (it is killed if none does)."""
    try:
        return proc.wait_for_line(text, timeout)
    except BaseException:
        proc.stop(signal.SIGKILL)
        raise


def start(*args: str, ready: str, timeout: float = 60.0) -> Proc:
    """``slamlens ARGS``, once it printed the line ``ready``."""
    proc = launch(*args)
    wait_ready(proc, ready, timeout)
    return proc


#: a CPU burner that ends by itself when the test process (its argument) goes, even killed
_BURN = "import os, sys\nparent = int(sys.argv[1])\nwhile os.getppid() == parent:\n    pass\n"


class Burners:
    """Two processes that burn a CPU each, beside every case (a loaded machine)."""

    def __init__(self, count: int = 2) -> None:
        self.procs = [subprocess.Popen([sys.executable, "-c", _BURN, str(os.getpid())])
                      for _ in range(count)]

    def stop(self) -> None:
        for p in self.procs:
            p.kill()
        for p in self.procs:
            p.wait()
