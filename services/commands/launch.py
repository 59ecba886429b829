"""``slamlens launch FILE.toml``: a described group of services, supervised as one.

Like ``ros2 launch``: each service of the file (:mod:`slamlens.services.commands.launch_file`)
runs as its own ``slamlens`` process, and the supervisor

* **orders** them: a service starts once every service in its ``after`` is ready — has
  printed its "… ready" line on stdout (the router, estimator, monitor, registration,
  viewer and serial commands do), or has started, for commands that print none. No sleeps.
* **respawns** a service that exits with an error (or is killed) after it was ready, with
  back-off (0.5 s, doubling up to ``respawn_max_s``; a run of a minute or more starts the
  back-off again). A service that fails before it was ever ready ends the group: that is a
  configuration error, and respawning would only repeat it. A service that exits 0 has
  finished (a simulator at the end of its run) and is not restarted.
* **logs** everything in one stream: each line of each service's stdout and stderr as
  ``[name] line``, and its own lines as ``[launch] …``; with ``log_dir``, also one file per
  service and the combined ``launch.log``.
* **stops** every service on SIGINT or SIGTERM (all at once: each exits within 2 s),
  kills any that has not exited after 1.5 s, and ends with one line saying what ran, what
  was respawned and how each exited. The group also ends when every service has finished.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TextIO

from slamlens.common.backoff import Backoff
from slamlens.common.cli import setup_logging, stop_event
from slamlens.common.config import settings_from_args
from slamlens.common.errors import ServiceError
from slamlens.services.commands.launch_file import LaunchPlan, ServiceSpec, load_launch
from slamlens.services.commands.settings import LaunchSettings

#: a service that stays up this long after it was ready starts its back-off afresh
STABLE_S = 60.0
#: after a stop signal, how long the services have before they are killed
STOP_GRACE_S = 1.5
#: the first wait before a respawn (then doubled per failure in a row)
RESPAWN_INITIAL_S = 0.5


def _quiet_logger() -> logging.Logger:
    """The back-off's own outage lines are not needed: the supervisor says each respawn."""
    logger = logging.getLogger("slamlens.launch.respawn")
    logger.propagate = False
    if not logger.handlers:
        logger.addHandler(logging.NullHandler())
    return logger


@dataclass
class Child:
    """One service of the group and its current process, if any."""

    spec: ServiceSpec
    backoff: Backoff
    proc: subprocess.Popen | None = None
    started: int = 0  #: processes started (1 + respawns)
    ready: bool = False  #: the current process said it is ready
    ever_ready: bool = False
    ready_at: float = 0.0
    ready_line: str = ""  #: the line that said so (e.g. the viewer's URL)
    restart_at: float | None = None  #: when the next respawn is due
    finished: bool = False  #: exited for good (0, or not respawned)
    exit_code: int | None = None
    tail: deque[str] = field(default_factory=lambda: deque(maxlen=20))
    readers: list[threading.Thread] = field(default_factory=list)

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None


class Supervisor:
    """Runs a :class:`LaunchPlan` (module docstring): ``run(stop)`` until ``stop`` or the end.

    ``echo``: write the combined log to ``out`` (stdout); the demo keeps its own screen and
    only writes the log files. ``on_line(name, line)`` sees every line (tests, the demo).
    """

    def __init__(self, plan: LaunchPlan, *, echo: bool = True, log_dir: str = "",
                 out: TextIO | None = None, env: dict[str, str] | None = None) -> None:
        self.plan = plan
        self.echo = echo
        self.out = out or sys.stdout
        self.env = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self.log_dir = Path(log_dir or plan.options.log_dir) \
            if (log_dir or plan.options.log_dir) else None
        self._files: dict[str, IO[str]] = {}
        if self.log_dir is not None:
            self.log_dir.mkdir(parents=True, exist_ok=True)
            self._files["launch"] = (self.log_dir / "launch.log").open("a")
        self.children = [Child(spec, Backoff(spec.name, logger=_quiet_logger(),
                                             initial_s=RESPAWN_INITIAL_S,
                                             max_s=plan.options.respawn_max_s))
                         for spec in plan.services]
        self.failure: str | None = None  #: why the group failed, if it did
        self._all_ready_said = False

    # -- the log ----------------------------------------------------------------------
    def _write(self, name: str, line: str) -> None:
        text = f"[{name}] {line}"
        with self._lock:
            if self.echo:
                print(text, file=self.out, flush=True)
            for key in (name, "launch"):
                f = self._files.get(key)
                if f is not None:
                    f.write((line if key == name else text) + "\n")
                    f.flush()

    def _say(self, line: str) -> None:
        self._write("launch", line)

    # -- children ---------------------------------------------------------------------
    def child(self, name: str) -> Child:
        return next(c for c in self.children if c.name == name)

    def _read(self, child: Child, pipe: IO[str], stdout: bool) -> None:
        with pipe:
            for raw in pipe:
                line = raw.rstrip("\n")
                self._write(child.name, line)
                with self._changed:
                    child.tail.append(line)
                    if stdout and not child.ready and child.spec.ready \
                            and child.spec.ready in line:
                        self._mark_ready(child, line)

    def _mark_ready(self, child: Child, line: str) -> None:
        """(lock held) the current process of ``child`` is ready."""
        child.ready = child.ever_ready = True
        child.ready_at = time.monotonic()
        child.ready_line = line
        self._changed.notify_all()

    def _start(self, child: Child) -> None:
        spec = child.spec
        argv = [sys.executable, "-m", "slamlens.services", spec.command, *spec.argv]
        if self.log_dir is not None and spec.name not in self._files:
            self._files[spec.name] = (self.log_dir / f"{spec.name}.log").open("a")
        proc = subprocess.Popen(argv, env=self.env, stdin=subprocess.DEVNULL,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                errors="replace", bufsize=1)
        with self._changed:
            child.proc = proc
            child.started += 1
            child.ready = False
            child.restart_at = None
            child.exit_code = None
            child.readers = [threading.Thread(target=self._read, args=(child, pipe, out),
                                              daemon=True, name=f"launch {spec.name}")
                             for pipe, out in ((proc.stdout, True), (proc.stderr, False))]
        what = "respawned" if child.started > 1 else "started"
        self._say(f"{spec.name} {what} (pid {proc.pid}): {spec.shell()}")
        for t in child.readers:
            t.start()
        if not spec.ready:
            with self._changed:
                self._mark_ready(child, "")

    def _due(self, child: Child) -> bool:
        """Whether ``child`` may start now (first start: what it waits for is ready)."""
        if child.proc is None and not child.finished:
            return all(self.child(a).ever_ready for a in child.spec.after)
        return child.restart_at is not None and time.monotonic() >= child.restart_at

    def _reap(self, child: Child) -> None:
        """``child``'s process has exited: respawn it, let it finish, or fail the group."""
        assert child.proc is not None
        code = child.proc.returncode
        for t in child.readers:
            t.join(timeout=1.0)  # its last lines first
        child.exit_code = code
        was_ready, child.ready = child.ready, False
        how = f"code {code}" if code >= 0 else f"signal {signal.Signals(-code).name}"
        if code in (-signal.SIGINT, -signal.SIGTERM):  # stopped from outside (a Ctrl-C
            child.finished = True                      # reaching it before its handler)
            self._say(f"{child.name} stopped by {how} (not respawned)")
            return
        if not child.ever_ready and code != 0:
            last = next((ln for ln in reversed(child.tail) if ln.strip()), "")
            self.failure = (f"{child.name} (`{child.spec.shell()}`) exited with {how} before "
                            f"it was ready" + (f": {last}" if last else ""))
            child.finished = True
            return
        if code == 0:
            child.finished = True
            self._say(f"{child.name} finished (exit 0)")
            if child.spec.required:
                self.failure = f"{child.name} exited (code 0); it is required"
            return
        if child.spec.respawn:
            if was_ready and time.monotonic() - child.ready_at >= STABLE_S:
                child.backoff.succeeded()  # it ran well for a while: start afresh
            wait = child.backoff.failed(f"exited with {how}")
            child.restart_at = time.monotonic() + wait
            self._say(f"{child.name} exited with {how}: respawning in {wait:.1f} s")
            return
        child.finished = True
        self._say(f"{child.name} exited with {how} (not respawned)")
        if child.spec.required:
            tail = "\n  ".join(list(child.tail)[-5:])
            self.failure = f"{child.name} exited with {how}; its output ends:\n  {tail}"

    # -- the loop ---------------------------------------------------------------------
    def run(self, stop: threading.Event) -> int:
        """Supervise until ``stop`` is set or every service has finished; the exit code
        (0 unless a service failed). Raises ServiceError when the group failed."""
        self._say(f"launching {len(self.children)} services from {self.plan.source}"
                  + (f": {self.plan.options.description}" if self.plan.options.description
                     else ""))
        try:
            while not stop.is_set() and self.failure is None:
                for child in self.children:
                    if self._due(child):
                        self._start(child)
                for child in self.children:
                    if child.proc is not None and child.restart_at is None \
                            and not child.finished and child.proc.poll() is not None:
                        self._reap(child)
                self._say_all_ready()
                if all(c.finished for c in self.children):
                    break
                with self._changed:
                    self._changed.wait(timeout=0.1)  # woken at once by a ready line
        finally:
            codes = self._stop_all()
        respawned = [f"{c.name} ×{c.started - 1}" for c in self.children if c.started > 1]
        exits = ", ".join(f"{c.name} {codes.get(c.name, 'never started')}"
                          for c in self.children)
        verb = "failed" if self.failure else "stopped" if stop.is_set() else "done"
        self._say(f"{verb}: {len(self.children)} services; respawned: "
                  f"{', '.join(respawned) or 'none'}; exit codes: {exits}")
        for f in self._files.values():
            f.close()
        self._files.clear()
        if self.failure is not None:
            raise ServiceError(f"{self.plan.source}: {self.failure}")
        bad = [c for c in self.children if isinstance(c.exit_code, int) and c.exit_code != 0
               and not stop.is_set()]
        return 1 if bad else 0

    def _say_all_ready(self) -> None:
        if not self._all_ready_said and all(c.ever_ready for c in self.children):
            self._all_ready_said = True
            self._say(f"all {len(self.children)} services ready")

    def _stop_all(self) -> dict[str, int | str]:
        """Signal every running service, wait up to STOP_GRACE_S, kill the rest."""
        running = [c for c in self.children if c.running]
        for child in running:
            assert child.proc is not None
            try:
                child.proc.send_signal(signal.SIGTERM)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + STOP_GRACE_S
        for child in running:
            assert child.proc is not None
            try:
                child.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self._say(f"{child.name} did not exit within {STOP_GRACE_S:g} s: killed")
                child.proc.kill()
                child.proc.wait()
        for child in running:
            for t in child.readers:
                t.join(timeout=0.2)
        codes: dict[str, int | str] = {}
        for child in self.children:
            if child.proc is not None:
                code = child.proc.returncode
                child.exit_code = code if child in running else child.exit_code
                codes[child.name] = code if code is not None and code >= 0 else \
                    f"signal {signal.Signals(-code).name}" if code is not None else "?"
        return codes

    # -- for the demo -------------------------------------------------------------------
    def wait_ready(self, name: str, stop: threading.Event, timeout_s: float = 120.0) -> str:
        """The ready line of service ``name`` once it is ready ("" if ``stop`` or the group
        failed first); ServiceError after ``timeout_s``."""
        child = self.child(name)
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while not child.ever_ready:
                if stop.is_set() or self.failure is not None:
                    return ""
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ServiceError(f"{name} was not ready within {timeout_s:g} s")
                self._changed.wait(timeout=min(0.2, left))
            return child.ready_line


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, "launch")
    s = settings_from_args(LaunchSettings, args)
    plan = load_launch(s.file, values=s.values)
    if s.check:
        print(f"{plan.source}: {len(plan.services)} services, in start order:")
        for spec in plan.services:
            after = f"  (after {', '.join(spec.after)})" if spec.after else ""
            print(f"  {spec.name}: {spec.shell()}{after}")
        return 0
    stop = stop_event(grace_s=None)  # its own stop is bounded: services killed after 1.5 s
    return Supervisor(plan, log_dir=s.log_dir).run(stop)
