"""The allocator's policy (common/memory.py): a thread's large temporaries reuse freed memory.

Each case runs in a fresh interpreter (the policy must be set before any thread makes an
arena, and pytest's own process is left as it is). The workload is the viewer's at
n = 1000 in miniature: a worker thread holds five 16 MB arrays at once, frees them, and
does it again; its page faults are counted per round (``RUSAGE_THREAD``). With glibc's
defaults the thread's arena deletes the heaps that became empty, so every round faults
its memory in again; with the policy the second round and every later one fault nothing.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from slamlens.services.harness.procs import REPO

WORKLOAD = """
import json, resource, sys, threading
import numpy as np
from slamlens.common.memory import keep_freed_memory
took = keep_freed_memory() if sys.argv[1] == "policy" else None
faults = []

def work():
    for _ in range(8):
        before = resource.getrusage(resource.RUSAGE_THREAD).ru_minflt
        held = [np.ones(4_000_000, np.float32) for _ in range(5)]  # 5 x 16 MB at once
        del held
        faults.append(resource.getrusage(resource.RUSAGE_THREAD).ru_minflt - before)

thread = threading.Thread(target=work)
thread.start()
thread.join()
print(json.dumps({"took": took, "faults": faults}))
"""

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="glibc's mallopt: Linux only")


def _run(mode: str) -> dict:
    out = subprocess.run([sys.executable, "-c", WORKLOAD, mode], cwd=REPO, check=True,
                         capture_output=True, text=True, timeout=120).stdout
    return json.loads(out.strip().splitlines()[-1])


def test_freed_large_arrays_are_reused_without_faulting_their_pages_in_again() -> None:
    default, policy = _run("default"), _run("policy")
    # (a fault maps a 4 kB page, or 2 MB where NumPy asked for huge pages: no page count)
    # the workload does show the cost: with glibc's defaults every round faults again
    assert min(default["faults"][2:]) > 100, default
    assert policy["took"] is True
    assert policy["faults"][0] > 100, policy  # the first round maps its memory
    assert max(policy["faults"][1:]) < 20, policy  # every later one reuses it


def test_the_slamlens_program_sets_the_policy_before_the_command_runs(monkeypatch) -> None:
    import slamlens.services.commands.cli as cli

    calls: list[str] = []
    monkeypatch.setattr(cli, "keep_freed_memory", lambda: calls.append("policy"))
    monkeypatch.setattr(cli, "run_cli", lambda fn: calls.append("command") or 0)
    assert cli.main(["status", "--json"]) == 0
    assert calls == ["policy", "command"]
