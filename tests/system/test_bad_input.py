"""What a new user types wrong gets one clear line and exit 1, before anything else happens:
a missing video file before the network is tried, a taken port refused
by the demo instead of silently replaced."""

from __future__ import annotations

import socket
import subprocess
from pathlib import Path

import pytest

from slamlens.common.session import free_tcp_endpoint
from slamlens.services.harness.procs import REPO, slamlens_cmd


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(slamlens_cmd(*args), cwd=REPO, capture_output=True, text=True,
                          timeout=60)


@pytest.mark.parametrize(("flag", "value", "message"), [
    ("--source", "nope.mp4", "slamlens: error: source nope.mp4 does not exist"),
    ("--calibration", "nope.yml", "slamlens: error: nope.yml: calibration file does not exist"),
])
def test_a_missing_file_is_said_before_the_network_is_tried(flag: str, value: str,
                                                            message: str) -> None:
    nobody = free_tcp_endpoint()  # no router there: trying it would fail differently
    argv = ["registration", flag, value, "--connect", nobody]
    if flag == "--source":
        argv += ["--calibration", "deploy/calibration_synthetic_1280x720.yml"]
    out = _run(*argv)
    assert out.returncode == 1
    assert out.stderr.strip().splitlines() == [message]


@pytest.fixture
def taken():
    """A port on loopback held by someone else."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


def test_the_demo_refuses_a_taken_router_port(taken: int, tmp_path: Path) -> None:
    out = _run("demo", "--listen", f"tcp/127.0.0.1:{taken}", "--log-dir", str(tmp_path))
    assert out.returncode == 1 and out.stdout == ""
    assert out.stderr.strip() == (
        f"slamlens: error: port {taken} on 127.0.0.1 is taken (another slamlens router or "
        "demo? `slamlens status` lists what runs): stop it, or give --listen "
        "tcp/127.0.0.1:PORT (port 0: any free port)")
    assert not list(tmp_path.iterdir())  # nothing was started


def test_the_demo_refuses_a_taken_viewer_port(taken: int, tmp_path: Path) -> None:
    out = _run("demo", "--listen", "tcp/127.0.0.1:0", "--http", f"127.0.0.1:{taken}",
               "--log-dir", str(tmp_path))
    assert out.returncode == 1 and out.stdout == ""
    assert out.stderr.strip() == (
        f"slamlens: error: viewer address 127.0.0.1:{taken} is taken (another viewer or "
        "demo?): stop it, or give --http 127.0.0.1:PORT (port 0: any free port)")
    assert not list(tmp_path.iterdir())
