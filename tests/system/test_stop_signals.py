"""The first SIGTERM or SIGINT stops every long-running command, whichever of its threads the
kernel delivers it to.

A process-directed signal goes to any thread that does not block it, and a Zenoh session
runs many threads. Each command is started as a user starts it (a real process, a loopback
router); once it has said it is ready, the signal is sent to one of its non-main threads
only (``tgkill``), and the command must exit with status 0, its final line printed, within
2 s (its own shutdown watchdog cuts a slow clean shutdown short at 1.8 s). SIGTERM goes to a
thread of Zenoh's runtime (named by Zenoh: ``net-0``, ``app-0`` …; the supervisor of a
launch has none, it gets one of its reader threads), SIGINT to the oldest thread not named
by Zenoh (started by Python, or a native thread of a library); a third case sends SIGTERM to
every thread but the main one at once: the process stops once, as for a single signal.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import tty
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer

from slamlens.common.messages import Truth
from slamlens.common.session import free_tcp_endpoint
from slamlens.services.harness.procs import REPO, Service, slamlens_cmd, spawn, tgkill

#: every long-running command exits within this of the first signal (docs/delivery.md)
BOUND_S = 2.0
ROBOT = "r1"
SMALL_MRCLAM = REPO / "tests" / "fixtures" / "mrclam_small"


@dataclass
class Setup:
    """What a case starts from: the loopback router, a folder, and what must be closed."""

    endpoint: str
    tmp: Path
    stack: contextlib.ExitStack


@dataclass(frozen=True)
class Case:
    """One command: its arguments (given the setup), its ready line, its final line."""

    argv: Callable[[Setup], list[str]]
    ready: str
    final: str
    launch: bool = False  #: started as ``slamlens launch FILE`` (its own log lines)


def _serial_port(setup: Setup) -> str:
    """A pseudo-terminal standing in for the robot's serial line."""
    master, slave = os.openpty()
    tty.setraw(slave)
    setup.stack.callback(os.close, master)
    setup.stack.callback(os.close, slave)
    link = setup.tmp / "ttyROBOT"
    link.symlink_to(os.ttyname(slave))
    return str(link)


def _recording(setup: Setup) -> str:
    """A small recording of the robot's truth (what ``play`` publishes)."""
    path = setup.tmp / "truth.mcap"
    with path.open("wb") as f:
        writer = Writer(f)
        writer.start()
        channel = writer.register_channel(f"slamlens/robot/{ROBOT}/truth", "msgpack", 0,
                                          {"slamlens.message": "Truth"})
        for k in range(20):
            truth = Truth(robot=ROBOT, stamp=0.1 * k, pose=np.array([0.01 * k, 0.0, 0.0]),
                          landmark_ids=np.array([1, 2], dtype=np.int64),
                          landmarks=np.array([[1.0, 0.0], [0.0, 1.0]]))
            t = 1_000_000_000 + 100_000_000 * k
            writer.add_message(channel, log_time=t, data=truth.to_bytes(), publish_time=t)
        writer.finish()
    return str(path)


def _launch_file(setup: Setup) -> str:
    path = setup.tmp / "group.toml"
    path.write_text(f"""
[service.router]
command = "router"
listen = ["{free_tcp_endpoint()}"]

[service.estimator]
command = "estimator"
after = ["router"]
connect = ["{setup.endpoint}"]
robot = "{ROBOT}"
""")
    return str(path)


def _bus(setup: Setup) -> list[str]:
    return ["--connect", setup.endpoint]


CASES: dict[str, Case] = {
    "router": Case(lambda s: ["router", "--listen", free_tcp_endpoint()],
                   "router ready", "router stopped"),
    "sim": Case(lambda s: ["sim", "--robot", ROBOT, *_bus(s)], "sim ready", "sim stopped"),
    "replay": Case(lambda s: ["replay", str(SMALL_MRCLAM), "--robot", ROBOT, *_bus(s)],
                   "replay ready", "replay stopped"),
    "serial": Case(lambda s: ["serial", "--port", _serial_port(s), "--robot", ROBOT,
                              *_bus(s)], "serial ready", "serial stopped"),
    "estimator": Case(lambda s: ["estimator", "--robot", ROBOT, *_bus(s)],
                      "estimator ready", "estimator stopped"),
    "monitor": Case(lambda s: ["monitor", "--robot", ROBOT, *_bus(s)],
                    "monitor ready", "monitor stopped"),
    "summary": Case(lambda s: ["summary", "--robot", ROBOT, *_bus(s)],
                    "summary ready", "summary stopped"),
    "registration": Case(lambda s: ["registration", "--config",
                                    "deploy/camera_overhead.toml", *_bus(s)],
                         "registration ready", "registration stopped"),
    "viewer": Case(lambda s: ["viewer", "--robot", ROBOT, "--http", "127.0.0.1:0", *_bus(s)],
                   "viewer ready", "viewer stopped"),
    "record": Case(lambda s: ["record", str(s.tmp / "bus.mcap"), *_bus(s)],
                   "record ready", "record stopped"),
    "play": Case(lambda s: ["play", _recording(s), "--paused", *_bus(s)],
                 "play ready", "play stopped"),
    "foxglove": Case(lambda s: ["foxglove", "--robot", ROBOT, "--port", "0", *_bus(s)],
                     "foxglove ready", "foxglove stopped"),
    "ros2": Case(lambda s: ["ros2", "--robot", ROBOT, "--from-ros", "estimate", *_bus(s)],
                 "ros2 ready", "ros2 stopped"),
    "rerun": Case(lambda s: ["rerun", "--robot", ROBOT, "--save", str(s.tmp / "scene.rrd"),
                             *_bus(s)], "rerun ready", "rerun stopped"),
    "launch": Case(lambda s: ["launch", _launch_file(s)], "[launch] all 2 services ready",
                   "[launch] stopped: 2 services", launch=True),
}

#: Zenoh names the threads of its runtime; threads Python starts keep the process's name
ZENOH_THREADS = ("app-", "net-", "acc-", "rx-", "tx-")


def _is_zenoh(name: str) -> bool:
    return name.startswith(ZENOH_THREADS)


def _targets(proc: Service, how: str) -> list[int]:
    """The threads to signal, in order of preference (module docstring); never the main."""
    threads = proc.threads()
    others = [tid for tid in threads if tid != proc.pid]
    assert others, f"{proc.args[3:]} runs no thread but its main one"
    zenoh = [tid for tid in others if _is_zenoh(threads[tid])]
    rest = [tid for tid in others if not _is_zenoh(threads[tid])]
    if how == "every":
        return others
    return (zenoh + rest) if how == "zenoh" else (rest + zenoh)


def _signal(proc: Service, sig: signal.Signals, how: str) -> list[tuple[int, str]]:
    """Send ``sig`` to the chosen thread (or to every one); the (tid, name) signalled."""
    names = proc.threads()
    sent: list[tuple[int, str]] = []
    for tid in _targets(proc, how):
        try:
            tgkill(proc.pid, tid, sig)
        except ProcessLookupError:  # that thread ended meanwhile: the next one
            continue
        sent.append((tid, names.get(tid, "?")))
        if how != "every":
            break
    assert sent, f"no thread of {proc.args[3:]} could be signalled"
    return sent


@contextlib.contextmanager
def _started(name: str, endpoint: str, tmp: Path) -> Iterator[Service]:
    case = CASES[name]
    with contextlib.ExitStack() as stack:
        argv = case.argv(Setup(endpoint, tmp, stack))
        proc = Service(slamlens_cmd(*argv), cwd=REPO) if case.launch else spawn(*argv)
        try:
            proc.wait_for_line(case.ready, timeout=120)
            yield proc
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


@pytest.mark.parametrize(("sig", "how"), [(signal.SIGTERM, "zenoh"),
                                          (signal.SIGINT, "python"),
                                          (signal.SIGTERM, "every")],
                         ids=["SIGTERM-zenoh-thread", "SIGINT-python-thread",
                              "SIGTERM-every-thread"])
@pytest.mark.parametrize("name", list(CASES))
def test_the_first_signal_to_any_thread_stops_the_command(
        name: str, sig: signal.Signals, how: str, router_endpoint: str,
        tmp_path: Path) -> None:
    case = CASES[name]
    with _started(name, router_endpoint, tmp_path) as proc:
        sent = _signal(proc, sig, how)
        try:
            proc.wait(BOUND_S)
        except subprocess.TimeoutExpired:
            alive = proc.threads()
            proc.kill()
            proc.wait()
            raise AssertionError(
                f"{name} still ran {BOUND_S:g} s after {sig.name} to its thread(s) {sent} "
                f"(threads {alive}); stderr:\n{''.join(proc.err[-15:])}") from None
        out, err = proc.output()
    assert proc.returncode == 0, err
    finals = [line for line in out.splitlines() if line.startswith(case.final)]
    assert len(finals) == 1, (out, err)  # once, however many threads were signalled
    if case.launch:  # the supervisor stopped its services: each exited 0 by itself
        assert finals[0].endswith("exit codes: router 0, estimator 0"), out


#: the commands without a case above, and why
NOT_HERE = {
    "tune": "ends by itself", "calibrate": "ends by itself", "figures": "ends by itself",
    "certs": "ends by itself", "register": "ends by itself, within its --timeout",
    "status": "a refreshing table: no ready line and no final line",
    "detect": "ends by itself (one pass over its images)",
    "demo": "a launch group behind a screen of its own (tests/system/test_demo.py)",
}


def test_every_long_running_command_has_a_case() -> None:
    """A new command fails this until it has a case above (or a reason in NOT_HERE)."""
    from slamlens.services.commands.registry import COMMANDS

    assert set(COMMANDS) == set(CASES) | set(NOT_HERE)
    assert not set(CASES) & set(NOT_HERE)
