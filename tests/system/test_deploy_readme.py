"""deploy/README.md works as written: its commands, parsed from its ```sh blocks, run in a
fresh copy of the repository from its root, in network namespaces standing for the machines
(the `two_hosts` fixture; the one-machine section runs in the workstation's namespace, whose
loopback is its own, so the default ports are free).

What is taken as the reader would:

* **Install** is the one block not run: it needs the network for pip. The test checks it
  is the documented three lines and gives the commands what they leave behind — a
  ``.venv/bin/slamlens`` of this interpreter on the ``PATH``, exactly the console script
  ``pip install -e .`` writes (``slamlens.services.commands.cli:main``).
* A block's first comment says where it runs: ``# on the workstation``, ``# on the robot``
  (``# on either machine``: the workstation); a block without one runs on the one machine.
  ``192.0.2.10``, the example's workstation address, is the workstation namespace's.
* A command of a service (router, estimator, … , launch) keeps running, as in its own
  terminal; the test waits for what it says when it is ready. Any other command must end
  with exit status 0. ``HOME`` is a fresh folder (``~/slamlens-pki`` and the checkpoints go
  there).
* **Start at boot** needs systemd and root's /opt: its unit is checked by
  ``systemd-analyze verify`` and the launch it starts, with its .env file, by
  ``slamlens launch … --check``.

Then each section's outcome is checked: the viewer shows the robot's states over a
registered camera, the monitor's health is ok, ``slamlens status`` lists every service of
every host, ``slamlens register`` re-registers; every service stops within 2 s with status 0.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from slamlens.services.harness.netns import Hosts, curl_json
from slamlens.services.harness.procs import REPO, Service

README = REPO / "deploy" / "README.md"
EXAMPLE_WORKSTATION = "192.0.2.10"
INSTALL = ["python3 -m venv .venv", ".venv/bin/pip install -e .", ". .venv/bin/activate"]
SECTIONS = ("Install", "One machine, without a camera", "Two machines",
            "Two machines over mutual TLS", "Start at boot (systemd)")
#: what a service prints on stdout when it is ready
READY = {"router": "router ready", "estimator": "estimator ready",
         "monitor": "monitor ready", "registration": "registration ready",
         "viewer": "viewer ready", "sim": "sim ready", "replay": "replay ready",
         "serial": "serial ready", "summary": "summary ready", "launch": " services ready"}
SERVICES = (*READY, "demo")


@dataclass(frozen=True)
class Block:
    section: str
    host: str | None  #: "workstation", "robot", or None: the one machine
    commands: tuple[str, ...]


def readme_blocks(text: str) -> list[Block]:
    """The ```sh blocks of the README with their section and host (module docstring)."""
    blocks: list[Block] = []
    section = ""
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("## "):
            section = line[3:].strip()
        if line.strip() == "```sh":
            body = []
            i += 1
            while lines[i].strip() != "```":
                body.append(lines[i])
                i += 1
            host = None
            comments = [b for b in body if b.lstrip().startswith("#")]
            if comments:
                where = comments[0].lower()
                host = ("robot" if "on the robot" in where else
                        "workstation" if "workstation" in where or "either" in where else None)
            joined = "\n".join(b for b in body if not b.lstrip().startswith("#"))
            commands = [c.strip() for c in joined.replace("\\\n", " ").splitlines()
                        if c.strip()]
            blocks.append(Block(section, host, tuple(" ".join(c.split()) for c in commands)))
        i += 1
    return blocks


BLOCKS = readme_blocks(README.read_text())


def test_every_section_with_commands_is_run_here() -> None:
    assert [b.section for b in BLOCKS if b.section not in SECTIONS] == []
    assert {b.section for b in BLOCKS} == set(SECTIONS)
    install, = [b for b in BLOCKS if b.section == "Install"]
    assert list(install.commands) == INSTALL


@pytest.fixture
def clone(tmp_path: Path) -> Path:
    """A fresh copy of the repository (its tracked files) with what the install leaves."""
    root = tmp_path / "slamlens"
    files = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True,
                           check=True).stdout.decode().split("\0")
    for name in filter(None, files):
        source = REPO / name
        if source.is_file():
            (root / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, root / name)
    bin_dir = root / ".venv" / "bin"
    bin_dir.mkdir(parents=True)
    script = bin_dir / "slamlens"  # what pip writes for [project.scripts] slamlens
    script.write_text(f"#!{sys.executable}\nimport sys\n"
                      "from slamlens.services.commands.cli import main\nsys.exit(main())\n")
    script.chmod(0o755)
    (tmp_path / "home").mkdir()
    return root


class Reader:
    """Runs a section's commands as the README's reader would (module docstring)."""

    def __init__(self, clone: Path, home: Path, hosts: Hosts | None) -> None:
        self.clone, self.hosts = clone, hosts
        # the console script runs from the root, as the README says: the clone's code
        self.env = {"PATH": f"{clone / '.venv' / 'bin'}:{os.environ['PATH']}",
                    "HOME": str(home), "PYTHONPATH": str(clone)}
        self.running: list[tuple[str, Service]] = []
        self.outputs: dict[str, str] = {}

    def _argv(self, command: str, host: str | None) -> list[str]:
        if self.hosts is not None:
            command = command.replace(EXAMPLE_WORKSTATION, self.hosts.workstation_ip)
        argv = ["bash", "-c", command]
        ns = None if self.hosts is None else (
            self.hosts.robot if host == "robot" else self.hosts.workstation)
        return argv if ns is None else ["ip", "netns", "exec", ns, *argv]

    def run_block(self, block: Block) -> None:
        for command in block.commands:
            words = shlex.split(command)
            assert words[0] == "slamlens", command
            name = words[1]
            keeps_running = name in SERVICES
            proc = Service(self._argv(command, block.host), env=self.env, cwd=self.clone)
            if keeps_running:
                self.running.append((command, proc))
                proc.wait_for_line(READY[name], timeout=120)
                continue
            out, err = proc.communicate(timeout=120)
            assert proc.returncode == 0, f"{command}\n{out}\n{err}"
            self.outputs[command] = out

    def output_of(self, start: str) -> str:
        return next(out for command, out in self.outputs.items() if command.startswith(start))

    def stop_all(self) -> dict[str, tuple[int, float, str]]:
        """Ctrl-C each running command, last started first: {command: (status, s, out)}."""
        done = {}
        for command, proc in reversed(self.running):
            started = time.monotonic()
            # bash -c runs a single command in place (exec): the signal reaches slamlens
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            out, err = proc.output()
            done[command] = (proc.returncode, time.monotonic() - started, out + err)
        self.running.clear()
        return done


def _viewer(ns: str) -> dict | None:
    """The viewer's /api/status, asked from inside ``ns`` (None if it does not answer)."""
    try:
        return curl_json(ns, "http://127.0.0.1:8080/api/status", timeout=5.0)
    except subprocess.TimeoutExpired:  # a loaded machine: ask again
        return None


def _the_viewer_shows_the_run(ns: str, *, min_seq: int = 100) -> dict:
    """The viewer's status once it draws the robot's states over a registered camera,
    with the monitor's health ok."""
    deadline = time.monotonic() + 120
    status: dict | None = None
    while time.monotonic() < deadline:
        status = _viewer(ns)
        state = (status or {}).get("state") or {}
        cameras = (status or {}).get("cameras") or [{}]
        registration = cameras[0].get("registration") or {}
        health = (status or {}).get("health") or {}
        if state.get("seq", 0) >= min_seq and registration.get("status") == "registered" \
                and health.get("seq", 0) >= min_seq:
            assert health["ok"] and not health["suspects"], health
            return status  # type: ignore[return-value]
        time.sleep(0.5)
    raise AssertionError(f"the viewer never showed the run: {status}")


def _services_listed(table: str) -> list[str]:
    return [line.split()[0] for line in table.splitlines()[1:] if line.strip()]


def _all_stopped_cleanly(done: dict[str, tuple[int, float, str]]) -> None:
    for command, (code, took, out) in done.items():
        assert code == 0, f"{command} exited {code}:\n{out[-2000:]}"
        assert took < 2.5, f"{command} took {took:.1f} s to stop"


def _block(section: str) -> list[Block]:
    return [b for b in BLOCKS if b.section == section]


def test_one_machine_without_a_camera(two_hosts: Hosts, clone: Path) -> None:
    reader = Reader(clone, clone.parent / "home", two_hosts)
    try:
        for block in _block("One machine, without a camera"):
            assert block.host is None
            reader.run_block(block)
        listed = _services_listed(reader.output_of("slamlens status"))
        assert sorted(listed) == ["estimator", "monitor", "registration", "router", "sim",
                                  "viewer"], reader.output_of("slamlens status")
        assert reader.output_of("slamlens register").startswith(
            "camera overhead registered robot robot1: registered")
        _the_viewer_shows_the_run(two_hosts.workstation)
    finally:
        done = reader.stop_all()
    _all_stopped_cleanly(done)
    assert any("monitor stopped: " in out and '"violations": 0' in out
               for _, _, out in done.values())


def _two_machines(section: str, hosts: Hosts, clone: Path) -> tuple[Reader, dict]:
    reader = Reader(clone, clone.parent / "home", hosts)
    try:
        blocks = _block(section)
        assert [b.host for b in blocks][-3:] == ["workstation", "robot", "workstation"]
        for block in blocks:
            reader.run_block(block)
        status = next(out for command, out in reader.outputs.items()
                      if command.startswith("slamlens status"))
        assert sorted(_services_listed(status)) == ["estimator", "monitor", "registration",
                                                    "router", "router", "sim", "summary",
                                                    "viewer"], status
        _the_viewer_shows_the_run(hosts.workstation)
    finally:
        done = reader.stop_all()
    _all_stopped_cleanly(done)
    return reader, done


def test_two_machines(two_hosts: Hosts, clone: Path) -> None:
    _, done = _two_machines("Two machines", two_hosts, clone)
    for command, (_, _, out) in done.items():
        if "launch" in command:
            assert "[launch] stopped: " in out and "respawned: none" in out, command


def test_two_machines_over_mutual_tls(two_hosts: Hosts, clone: Path) -> None:
    _, done = _two_machines("Two machines over mutual TLS", two_hosts, clone)
    for command, (_, _, out) in done.items():
        if "launch" not in command:
            continue
        assert "(mutual TLS); roles enforced for " in out, command
        refused = [ln for ln in out.splitlines() if "refused" in ln and "[router]" in ln
                   and "router stopped" not in ln]
        # the only thing a real service says outside its role: the camera's tracked pose
        # (docs/security.md, limits); nothing else of any service is refused
        assert all(re.search(r"refused(?: \d+ more)?: camera-overhead may not \w+ \(ingress\) "
                             r"on slamlens/robot/robot1/tracked", ln) for ln in refused), \
            refused


def test_start_at_boot(clone: Path, tmp_path: Path) -> None:
    block, = _block("Start at boot (systemd)")
    unit = clone / "deploy" / "systemd" / "slamlens@.service"
    for command in block.commands:
        for word in shlex.split(command):
            if word.startswith("deploy/"):
                assert (clone / word).exists(), command
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed")
    text = unit.read_text().replace("/opt/slamlens", str(clone))
    for name in ("robot", "workstation"):
        instance = tmp_path / f"slamlens@{name}.service"
        instance.write_text(text)
        check = subprocess.run(["systemd-analyze", "verify", str(instance)],
                               capture_output=True, text=True, timeout=60)
        assert check.returncode == 0, check.stdout + check.stderr
        env = dict(line.split("=", 1) for line in
                   (clone / "deploy" / "systemd" / f"{name}.env").read_text().splitlines()
                   if line and not line.startswith("#"))
        exec_start = next(ln.split("=", 1)[1] for ln in text.splitlines()
                          if ln.startswith("ExecStart="))
        argv = shlex.split(exec_start.replace("%i", name).replace(
            "$SLAMLENS_LAUNCH_ARGS", env["SLAMLENS_LAUNCH_ARGS"]))
        assert argv[0] == str(clone / ".venv" / "bin" / "slamlens")
        out = subprocess.run([*argv, "--check"], cwd=clone, capture_output=True, text=True,
                             timeout=60, env=dict(os.environ, PYTHONPATH=str(clone)))
        assert out.returncode == 0, out.stderr
        assert out.stdout.startswith(f"deploy/{name}.toml: ")
