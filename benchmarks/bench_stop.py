"""How fast a stop signal is acted on, whichever thread receives it.

The kernel delivers a signal sent to a process to any thread that does not block it.
Measured with ``tgkill`` (the signal to one chosen thread: the main thread or another) and
with ``kill`` (to the process, the kernel's choice):

* **mechanism**: a small process (``--threads`` idle threads beside the main one, which
  waits on its stop event without a timeout) with each way of taking the signal:
  ``taker`` — slamlens's (:func:`slamlens.common.cli.stop_event`: Python's C handler writes
  to the wakeup fd, a thread reading it sets the event); ``handler`` — the Python handler
  sets the event (what every command did before; the baseline); ``sigwait`` — SIGINT and
  SIGTERM blocked before any thread starts, one thread taking them with ``sigwait`` (not
  chosen: child processes inherit the blocked signals, and a signal sent to one thread that
  blocks it stays pending there). The figure: signal sent → the
  main thread awake (``CLOCK_MONOTONIC`` is one clock for every process), median of
  ``--repeats``, or how many times the main thread was not woken within 2 s.
* **services**: ``slamlens router`` and ``slamlens viewer`` as a user
  starts them, the signal to the main thread or to a Zenoh thread: signal sent → final line
  and → process exited, median of ``--repeats`` / 4 (at least 3). The baseline ends the
  same command through the interpreter's finalization instead of ``run_cli``'s end
  (:func:`slamlens.common.cli.run_cli`).

Run: ``.venv/bin/python benchmarks/bench_stop.py [--repeats 20] [--only mechanism|services]``
"""

from __future__ import annotations

import argparse
import os
import select
import signal
import statistics
import subprocess
import sys
import textwrap
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from slamlens.common.session import free_tcp_endpoint  # noqa: E402
from slamlens.services.harness.procs import Service, spawn, stop, tgkill  # noqa: E402

WAKE_LIMIT_S = 2.0

CHILD = textwrap.dedent("""
    import signal, sys, threading, time
    mode, threads = sys.argv[1], int(sys.argv[2])
    stop = threading.Event()
    if mode == "taker":
        from slamlens.common.cli import stop_event
        stop = stop_event()
    elif mode == "handler":
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    else:  # sigwait: blocked before any thread starts, taken by one thread
        wanted = {signal.SIGINT, signal.SIGTERM}
        signal.pthread_sigmask(signal.SIG_BLOCK, wanted)
        def take():
            signal.sigwait(wanted)
            stop.set()
        threading.Thread(target=take, daemon=True).start()
    idle = threading.Event()
    workers = [threading.Thread(target=idle.wait, daemon=True) for _ in range(threads)]
    for w in workers:
        w.start()
    print("ready", workers[-1].native_id, flush=True)
    stop.wait()
    print("awake", time.monotonic_ns(), flush=True)
""")


def wake_latency(mode: str, to: str, threads: int) -> float | None:
    """Seconds from the signal (``to`` the main thread, another thread, or the process:
    the kernel's choice) to the main thread awake; None if not within the limit."""
    proc = subprocess.Popen([sys.executable, "-c", CHILD, mode, str(threads)], cwd=REPO,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        word, tid = proc.stdout.readline().split()
        assert word == "ready"
        sent = time.monotonic_ns()
        if to == "process":
            os.kill(proc.pid, signal.SIGTERM)
        else:
            tgkill(proc.pid, proc.pid if to == "main" else int(tid), signal.SIGTERM)
        # the "awake" line, not the exit: a process that imported Zenoh may take seconds to
        # finalize on a loaded machine, and that is not what is measured here
        if not select.select([proc.stdout], [], [], WAKE_LIMIT_S)[0]:
            return None
        return (int(proc.stdout.readline().split()[1]) - sent) / 1e9
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate()


def _median_ms(values: list[float | None]) -> str:
    woken = [v for v in values if v is not None]
    missed = f"not within the limit: {len(values) - len(woken)}/{len(values)}"
    if not woken:
        return f"never   ({missed})"
    return (f"{statistics.median(woken) * 1e3:7.3f} ms (range {min(woken) * 1e3:.3f}–"
            f"{max(woken) * 1e3:.3f}; {missed})")


DELIVERIES = {"main": "to the main thread ", "other": "to another thread  ",
              "process": "to the process     "}


def mechanisms(repeats: int, threads: int) -> None:
    print(f"signal → main thread awake (limit {WAKE_LIMIT_S:g} s), {threads} idle threads, "
          f"{repeats} runs each (interleaved):")
    results: dict[tuple[str, str], list[float | None]] = {}
    for _ in range(repeats):  # interleaved: the machine's load falls on every mode alike
        for mode in ("handler", "taker", "sigwait"):
            for to in DELIVERIES:
                results.setdefault((mode, to), []).append(wake_latency(mode, to, threads))
    base = [v for v in results[("handler", "main")] if v is not None]
    for (mode, to), values in results.items():
        woken = [v for v in values if v is not None]
        ratio = (f"  ×{statistics.median(woken) / statistics.median(base):.2f} the baseline"
                 if woken and base and len(woken) == len(values) else "")
        print(f"  {mode:8s} {DELIVERIES[to]}: {_median_ms(values)}{ratio}")


#: a command run as ``slamlens`` runs it, but ending through the interpreter's finalization
#: (the baseline of ``run_cli``'s end after a stop signal)
FINALIZING = textwrap.dedent("""
    import sys
    from slamlens.common.memory import keep_freed_memory
    from slamlens.services.commands.cli import command_parser
    from slamlens.services.commands.registry import COMMANDS, import_service_module
    name = sys.argv[1]
    args = command_parser(name).parse_args(sys.argv[2:])
    keep_freed_memory()
    sys.exit(import_service_module(COMMANDS[name].module).run(name, args))
""")


def _service(command: str, endpoint: str, finalizing: bool) -> Service:
    argv = ["router", "--listen", free_tcp_endpoint()] if command == "router" else \
        ["viewer", "--robot", "r1", "--http", "127.0.0.1:0", "--connect", endpoint]
    if finalizing:
        return Service([sys.executable, "-c", FINALIZING, *argv], cwd=REPO)
    return spawn(*argv)


def stop_times(command: str, endpoint: str, *, to_main: bool,
               finalizing: bool) -> tuple[float | None, float | None]:
    """Seconds from the signal to the final line and to the exit (None: not within 10 s)."""
    proc = _service(command, endpoint, finalizing)
    try:
        proc.wait_for_line(f"{command} ready", timeout=120)
        threads = proc.threads()
        target = proc.pid if to_main else next(t for t, name in threads.items()
                                               if name.startswith(("net-", "app-")))
        sent = time.monotonic()
        tgkill(proc.pid, target, signal.SIGTERM)
        try:
            proc.wait_for_line(f"{command} stopped", timeout=10.0)
            final: float | None = time.monotonic() - sent
        except AssertionError:
            final = None
        try:
            proc.wait(10.0)
            ended: float | None = time.monotonic() - sent
        except subprocess.TimeoutExpired:
            ended = None
        return final, ended
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.output()


def services(repeats: int) -> None:
    endpoint = free_tcp_endpoint()
    router = spawn("router", "--listen", endpoint)
    router.wait_for_line("router ready")
    try:
        print(f"signal → final line, → process exited (limit 10 s), {repeats} runs each "
              "(interleaved):")
        cases = [(command, to_main, finalizing) for command in ("router", "viewer")
                 for to_main in (True, False) for finalizing in (False, True)]
        times: dict[tuple[str, bool, bool], list[tuple[float | None, float | None]]] = {}
        for _ in range(repeats):
            for case in cases:
                command, to_main, finalizing = case
                times.setdefault(case, []).append(
                    stop_times(command, endpoint, to_main=to_main, finalizing=finalizing))
        for (command, to_main, finalizing), values in times.items():
            where = "main thread " if to_main else "Zenoh thread"
            end = "finalizing (baseline)" if finalizing else "run_cli"
            print(f"  {command:7s} to a {where}, ending by {end}:")
            print(f"    final line {_median_ms([f for f, _ in values])}")
            print(f"    exited     {_median_ms([e for _, e in values])}")
    finally:
        stop(router)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--threads", type=int, default=8)
    parser.add_argument("--only", choices=("mechanism", "services"),
                        help="one of the two parts (default: both)")
    args = parser.parse_args()
    if args.only != "services":
        mechanisms(args.repeats, args.threads)
    if args.only != "mechanism":
        services(max(3, args.repeats // 4))


if __name__ == "__main__":
    main()
