"""``slamlens.common.cli.stop_event``: a signal starts a clean shutdown, whichever thread
receives it, and the shutdown is bounded.

A real child process each: it installs the handler, says it is ready, waits for the signal,
then runs a "cleanup" of a given length (a hung Zenoh close, a render thread that does not
join on an oversubscribed machine).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

import pytest

from slamlens.services.harness.procs import REPO, tgkill

CHILD = textwrap.dedent("""
    import sys, time
    from slamlens.common.cli import stop_event
    grace = None if sys.argv[2] == "none" else float(sys.argv[2])
    stop = stop_event(grace_s=grace)
    print("ready", flush=True)
    stop.wait()
    print("stopping", flush=True)
    time.sleep(float(sys.argv[1]))  # the cleanup
    print("clean end", flush=True)
""")


@contextmanager
def _child(cleanup_s: float, grace: str) -> Iterator[subprocess.Popen]:
    """The child, once it said it is ready; killed at the end if it is still there."""
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(cleanup_s), grace], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def _run(cleanup_s: float, grace: str, sig: signal.Signals) -> tuple[int, float, str, str]:
    with _child(cleanup_s, grace) as proc:
        signalled = time.monotonic()
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
        return proc.returncode, time.monotonic() - signalled, "ready\n" + out, err


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_clean_shutdown_ends_on_its_own(sig: signal.Signals) -> None:
    code, _, out, err = _run(0.0, "1.8", sig)
    assert code == 0
    assert out.splitlines() == ["ready", "stopping", "clean end"]
    assert "exiting now" not in err


def test_a_hung_shutdown_is_cut_short_after_the_grace_with_status_0() -> None:
    code, took, out, err = _run(3600.0, "0.5", signal.SIGTERM)
    assert code == 0
    assert out.splitlines() == ["ready", "stopping"]  # the cleanup never ended
    assert err.strip() == "slamlens: the shutdown took longer than 0.5 s: exiting now"
    assert took >= 0.5  # not before its grace


def test_a_second_signal_during_the_shutdown_changes_nothing() -> None:
    with _child(0.5, "30") as proc:
        assert proc.stdout is not None
        proc.send_signal(signal.SIGINT)  # a Ctrl-C from the terminal …
        assert proc.stdout.readline().strip() == "stopping"
        proc.send_signal(signal.SIGTERM)  # … and the launch's SIGTERM
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0 and out.splitlines() == ["clean end"]
    assert err == ""


def test_without_a_grace_the_cleanup_runs_to_its_end() -> None:
    code, took, out, err = _run(2.5, "none", signal.SIGTERM)
    assert code == 0 and out.splitlines() == ["ready", "stopping", "clean end"]
    assert took >= 2.5 and err == ""


# -- whichever thread the kernel delivers the signal to --------------------------------------

THREADED = textwrap.dedent("""
    import atexit, subprocess, sys, threading
    from slamlens.common.cli import run_cli, stop_event

    def main() -> int:
        stop = stop_event()
        idle = threading.Event()
        worker = threading.Thread(target=idle.wait, daemon=True)  # as Zenoh's threads
        worker.start()
        child = subprocess.Popen(["sleep", "600"]) if sys.argv[1] == "child" else None
        atexit.register(print, "atexit ran")
        print(f"ready {worker.native_id} {child.pid if child else 0}", flush=True)
        stop.wait()  # no timeout: only another thread can wake it
        if child is not None:
            child.wait()
            print(f"child {child.returncode}")
        print("stopping")  # not flushed: the process must flush it before it ends
        return 0

    sys.exit(run_cli(main))
""")


@contextmanager
def _threaded(mode: str = "") -> Iterator[tuple[subprocess.Popen, int, int]]:
    """The child waiting without a timeout, its worker thread's id and its own child's pid."""
    proc = subprocess.Popen([sys.executable, "-c", THREADED, mode], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        word, tid, grandchild = proc.stdout.readline().split()
        assert word == "ready"
        yield proc, int(tid), int(grandchild)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_to_another_thread_wakes_a_main_thread_waiting_without_timeout(
        sig: signal.Signals) -> None:
    with _threaded() as (proc, tid, _):
        tgkill(proc.pid, tid, sig)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert out.splitlines() == ["stopping", "atexit ran"] and err == ""


def test_signals_through_the_whole_shutdown_leave_status_0() -> None:
    """Python puts back the default handlers while it finalizes: a SIGTERM then would end
    the process by that signal; a stopped process ends before (``run_cli``)."""
    with _threaded() as (proc, tid, _):
        tgkill(proc.pid, tid, signal.SIGTERM)
        sent = 1
        while proc.poll() is None:  # until it is reaped: its pid cannot be reused before
            with suppress(ProcessLookupError):
                os.kill(proc.pid, signal.SIGTERM if sent % 2 else signal.SIGINT)
                sent += 1
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, (sent, err)
    assert out.splitlines() == ["stopping", "atexit ran"] and err == ""


def test_child_processes_inherit_no_blocked_signal() -> None:
    """A service's children (a launch's services) can still be stopped by SIGTERM."""
    with _threaded("child") as (proc, _, grandchild):
        status = Path(f"/proc/{grandchild}/status").read_text()
        blocked = int(next(ln for ln in status.splitlines()
                           if ln.startswith("SigBlk:")).split()[1], 16)
        assert not blocked & ((1 << (signal.SIGTERM - 1)) | (1 << (signal.SIGINT - 1)))
        os.kill(grandchild, signal.SIGTERM)
        os.kill(proc.pid, signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert out.splitlines() == [f"child {-signal.SIGTERM}", "stopping", "atexit ran"]
