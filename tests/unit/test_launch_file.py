"""Launch files: what they start, in which order, with which flags, and one clear line for
every mistake (naming the file and the key) before anything starts."""

from __future__ import annotations

import os
import subprocess
import tomllib
from pathlib import Path

import pytest

from slamlens.common.errors import ConfigError
from slamlens.services.commands.launch_file import load_launch, plan_from_mapping, to_toml
from slamlens.services.harness.procs import REPO, slamlens_cmd

DEPLOY = REPO / "deploy"


def _plan(text: str, *values: str):
    return plan_from_mapping(tomllib.loads(text), source="lab.toml", values=values)


GROUP = """
[launch]
respawn_max_s = 4.0

[vars]
robot = "r1"
port = "7999"

[defaults]
connect = ["tcp/127.0.0.1:${port}"]
prefix = "lab"

[service.sim]
command = "sim"
after = ["estimator", "monitor"]
robot = "${robot}"
rate = 0
hold_s = 1.5
wait_for_estimator = false
anonymous = true
marker_ids = [4]
respawn = false

[service.monitor]
command = "monitor"
after = ["router"]
robot = "${robot}"
rtol_growth = 1e-8

[service.router]
command = "router"
listen = ["tcp/127.0.0.1:${port}"]
connect = []

[service.estimator]
command = "estimator"
after = ["router"]
robot = "${robot}"
checkpoint = "~/ckpt"
faulty_features = [3, 12]
fault = "map-update"
verbose = 1
"""


def test_a_group_in_start_order_with_its_flags() -> None:
    plan = _plan(GROUP, "robot=r7")
    # each after what it waits for, else in the file's order
    assert [s.name for s in plan.services] == ["router", "monitor", "estimator", "sim"]
    sim = plan.service("sim")
    assert sim.command == "sim" and not sim.respawn and sim.ready == "sim ready"
    assert sim.argv == ("--connect", "tcp/127.0.0.1:7999", "--prefix", "lab",
                        "--robot", "r7", "--rate", "0.0", "--hold", "1.5", "--no-wait",
                        "--anonymous", "--marker-ids", "4")
    est = plan.service("estimator")
    assert est.respawn and est.ready == "estimator ready"
    argv = list(est.argv)
    assert argv[argv.index("--checkpoint") + 1] == os.path.expanduser("~/ckpt")
    assert argv[argv.index("--faulty-features") + 1] == "3,12"
    assert argv.count("--verbose") == 1
    assert argv[argv.index("--connect") + 1] == "tcp/127.0.0.1:7999"
    router = plan.service("router")
    assert "--connect" not in router.argv  # its own empty list over the default
    assert router.argv == ("--prefix", "lab", "--listen", "tcp/127.0.0.1:7999")
    assert plan.service("monitor").argv[4:] == ("--robot", "r7", "--rtol", "1e-08")
    assert plan.options.respawn_max_s == 4.0
    assert est.shell().startswith("slamlens estimator --connect tcp/127.0.0.1:7999 --prefix "
                                  "lab --robot r7")


@pytest.mark.parametrize(("text", "message"), [
    ('[service.e]\ncommand = "estimator"\nsigma = 1\n',
     "lab.toml [service.e]: unknown key 'sigma': neither a launch key"),
    ('[service.e]\ncommand = "estimator"\nsigma_v = "fast"\n',
     "lab.toml [service.e] key 'sigma_v': setting 'sigma_v': expected a number, got 'fast'"),
    ('[service.e]\ncommand = "estimator"\nfault = "bitflip"\n',
     "lab.toml [service.e] key 'fault': setting 'fault': 'bitflip' is not one of"),
    ('[service.e]\ncommand = "estimater"\n',
     "lab.toml [service.e] key 'command': 'estimater' is not a slamlens service"),
    ('[service.e]\ncommand = "demo"\n',
     "lab.toml [service.e] key 'command': `slamlens demo` is not a service"),
    ('[service.e]\ncommand = "estimator"\nrobot = "${who}"\n',
     "lab.toml [service.e] key 'robot': ${who} is not defined"),
    ('[service.e]\ncommand = "estimator"\nafter = ["router"]\n',
     "lab.toml [service.e] key 'after': no service 'router' in the file"),
    ('[service.a]\ncommand = "monitor"\nafter = ["b"]\n'
     '[service.b]\ncommand = "estimator"\nafter = ["a"]\n',
     "lab.toml: the services a, b wait for each other (key 'after' makes a cycle)"),
    ('[service.e]\ncommand = "estimator"\nrespawn = "yes"\n',
     "lab.toml [service.e] key 'respawn': expected true or false"),
    ('[launch]\nrespawn_max_s = -1\n[service.e]\ncommand = "estimator"\n',
     "lab.toml [launch]: setting 'respawn_max_s': -1.0 is below the minimum"),
    ('[lunch]\n[service.e]\ncommand = "estimator"\n', "lab.toml: unknown key(s) lunch"),
    ('[launch]\n', "lab.toml: no [service.NAME] table"),
    ('[defaults]\nmarker_ids = [1]\n[service.e]\ncommand = "estimator"\n',
     "lab.toml [defaults]: key(s) marker_ids are settings of none of its services"),
    ('[service.r]\ncommand = "replay"\n',
     "lab.toml [service.r]: setting 'path' is required"),
    ('[service.s]\ncommand = "sim"\nconfig = "nowhere.toml"\n',
     "lab.toml [service.s]: config file nowhere.toml does not exist"),
    ('[service.r]\ncommand = "router"\nlisten = ["127.0.0.1:7447"]\n',
     "lab.toml [service.r]: endpoint '127.0.0.1:7447' is not of the form tcp/HOST:PORT"),
    ('[service.e]\ncommand = "estimator"\nsecure = "/nonexistent-pki"\nname = "robot-r1"\n',
     "lab.toml [service.e]: security directory /nonexistent-pki does not exist"),
])
def test_every_mistake_is_one_config_error_naming_file_and_key(text: str, message: str) -> None:
    with pytest.raises(ConfigError) as info:
        _plan(text)
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_set_must_name_a_variable_of_the_file() -> None:
    with pytest.raises(ConfigError, match=r"--set robt: lab.toml has no variable 'robt'"):
        _plan(GROUP, "robt=r2")
    with pytest.raises(ConfigError, match=r"--set 'robot': expected NAME=VALUE"):
        _plan(GROUP, "robot")


def test_a_missing_or_broken_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="launch file .*none.toml does not exist"):
        load_launch(tmp_path / "none.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[service.e\n")
    with pytest.raises(ConfigError, match=f"launch file {bad} is not valid TOML"):
        load_launch(bad)


@pytest.mark.parametrize("name", ["robot", "workstation"])
def test_the_shipped_launch_files_check(name: str) -> None:
    plan = load_launch(DEPLOY / f"{name}.toml", values=["workstation=10.1.2.3"])
    commands = {s.command for s in plan.services}
    assert commands == ({"router", "estimator", "monitor", "summary", "sim"} if name == "robot"
                        else {"router", "registration", "viewer"})
    router = plan.service("router")
    listen = [router.argv[i + 1] for i, a in enumerate(router.argv) if a == "--listen"]
    assert all(not e.split("/")[1].startswith("0.0.0.0") for e in listen)  # one interface
    if name == "robot":
        assert router.argv[router.argv.index("--connect") + 1] == "tcp/10.1.2.3:7447"
        assert "--checkpoint" in plan.service("estimator").argv
        assert set(plan.service("driver").after) == {"estimator", "monitor"}
    else:
        assert listen == ["tcp/127.0.0.1:7447", "tcp/10.1.2.3:7447"]


@pytest.mark.parametrize("name", ["robot_secure", "workstation_secure"])
def test_the_secure_launch_files_name_an_identity_per_service(name: str, tmp_path: Path,
                                                             monkeypatch) -> None:
    from slamlens.common.certs import extend_authority

    monkeypatch.setenv("HOME", str(tmp_path))
    extend_authority(tmp_path / "slamlens-pki", ["router-ws", "router-robot", "robot-robot1",
                                                 "monitor-robot1", "camera-overhead",
                                                 "viewer-lab"], hosts=["10.1.2.3"])
    plan = load_launch(DEPLOY / f"{name}.toml", values=["workstation=10.1.2.3"])
    for spec in plan.services:
        argv = list(spec.argv)
        assert argv[argv.index("--secure") + 1] == str(tmp_path / "slamlens-pki")
        assert argv[argv.index("--name") + 1]
        for flag in ("--listen", "--connect"):
            for i, a in enumerate(argv):
                if a == flag:
                    assert argv[i + 1].startswith("tls/")


def test_to_toml_reads_back_as_the_same_plan() -> None:
    raw = tomllib.loads(GROUP)
    again = tomllib.loads(to_toml(raw))
    assert again == raw
    assert plan_from_mapping(again, source="x") == plan_from_mapping(raw, source="x")


def test_the_command_line_says_a_bad_file_in_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "lab.toml"
    bad.write_text('[service.e]\ncommand = "estimator"\nsigma = 1\n')
    out = subprocess.run(slamlens_cmd("launch", str(bad)), cwd=REPO, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 1 and out.stdout == ""
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    assert lines[0].startswith(f"slamlens: error: {bad} [service.e]: unknown key 'sigma'")


def test_check_prints_the_commands_in_start_order() -> None:
    out = subprocess.run(slamlens_cmd("launch", "deploy/robot.toml", "--check", "--set",
                                      "workstation=10.1.2.3"), cwd=REPO, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == "deploy/robot.toml: 5 services, in start order:"
    assert lines[1].startswith("  router: slamlens router --listen tcp/127.0.0.1:7447 "
                               "--connect tcp/10.1.2.3:7447")
    assert lines[-1].startswith("  driver: slamlens sim --config deploy/sim_paper.toml")
    assert lines[-1].endswith("(after estimator, monitor)")
