"""``slamlens.common.cli.stop_event``: a signal starts a clean shutdown, and the shutdown is
bounded.

A real child process each: it installs the handler, says it is ready, waits for the signal,
then runs a "cleanup" of a given length (a hung Zenoh close, a render thread that does not
join on an oversubscribed machine).
"""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from slamlens.services.harness.procs import REPO

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
