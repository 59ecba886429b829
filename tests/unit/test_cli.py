"""The ``slamlens`` command lines: built from the settings, the same as before, documented.

Every flag comes from one settings field (common/config.py). These tests pin what a user
types: each flag name that existed before the settings were declared once still parses
into the same setting, every flag has help that says its default, and docs/cli.md is what
the code generates.
"""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from slamlens.common.cli import BusFlags, LogFlags, bus_flags, bus_settings, keys_from, log_flags
from slamlens.common.config import settings_from_args
from slamlens.common.errors import ConfigError
from slamlens.services.commands.cli import command_parser, main
from slamlens.services.commands.reference import DOC, reference
from slamlens.services.commands.registry import COMMANDS, Command
from slamlens.services.commands.settings import (
    CertsSettings,
    DemoSettings,
    FigureSettings,
    LaunchSettings,
    RegisterSettings,
)
from slamlens.services.harness.procs import REPO
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.recorder.settings import PlaySettings, RecordSettings
from slamlens.services.registration.settings import (
    CalibrateSettings,
    DetectSettings,
    RegistrationSettings,
)
from slamlens.services.slam.settings import (
    EstimatorSettings,
    ReplaySettings,
    SerialSettings,
    SimSettings,
    TuneSettings,
)
from slamlens.services.visualiser.settings import ViewerConfig, ViewSettings

#: every flag each command had before its settings were declared once (must keep working)
LEGACY_FLAGS = {
    "router": ["--connect", "--listen", "--prefix", "--quiet", "--verbose", "--zenoh-config"],
    "sim": ["--anonymous", "--config", "--connect", "--hold", "--listen", "--loops",
            "--no-wait", "--prefix", "--quiet", "--rate", "--robot", "--scenario", "--seed",
            "--verbose", "--zenoh-config"],
    "estimator": ["--config", "--connect", "--fault", "--fault-magnitude", "--fault-onset",
                  "--faulty-features", "--gate-chi2", "--listen", "--new-landmark-chi2",
                  "--prefix", "--quiet", "--robot", "--sigma-bearing", "--sigma-range",
                  "--sigma-v", "--sigma-w", "--verbose", "--zenoh-config"],
    "replay": ["--config", "--connect", "--duration", "--format", "--listen", "--no-wait",
               "--prefix", "--quiet", "--rate", "--robot", "--robot-index", "--start",
               "--verbose", "--zenoh-config"],
    "serial": ["--baudrate", "--config", "--connect", "--listen", "--port", "--prefix",
               "--quiet", "--robot", "--verbose", "--zenoh-config"],
    "monitor": ["--config", "--connect", "--listen", "--prefix", "--quiet", "--robot", "--rtol",
                "--verbose", "--zenoh-config"],
    "registration": ["--arena", "--blur", "--board", "--calibration", "--camera",
                     "--camera-height", "--camera-pose-source", "--camera-yaw", "--config",
                     "--connect", "--dictionary", "--fps", "--gain", "--gradient", "--height",
                     "--hfov", "--jpeg-quality", "--listen", "--loop", "--marker-id",
                     "--marker-offset", "--marker-size", "--mode", "--noise", "--offset",
                     "--prefix", "--quiet", "--register-frames", "--robot", "--seed",
                     "--source", "--stereo-baseline", "--verbose", "--width",
                     "--zenoh-config"],
    "detect": ["--config", "--detector", "--dictionary", "--json", "--quiet", "--verbose"],
    "calibrate": ["--dictionary", "--legacy-pattern", "--marker", "--quiet", "--square",
                  "--squares-x", "--squares-y", "--verbose", "-o", "--output"],
    "viewer": ["--camera", "--config", "--connect", "--fps", "--http", "--jpeg-quality",
               "--listen", "--prefix", "--quiet", "--record-codec", "--recordings-dir",
               "--robot", "--stereo-baseline", "--verbose", "--view", "--zenoh-config"],
    "figures": ["--output-dir", "--quiet", "--seed", "--verbose"],
    "demo": ["--camera", "--connect", "--duration", "--fault", "--fault-magnitude",
             "--fault-onset", "--faulty", "--faulty-features", "--http", "--listen",
             "--log-dir", "--loops", "--no-camera", "--prefix", "--quiet", "--rate", "--robot",
             "--seed", "--verbose", "--zenoh-config"],
    "certs": ["--host", "--name", "--quiet", "--verbose"],  # docs/security.md
    "tune": ["--config", "--gate-chi2", "--motion-model", "--output", "--quiet",
             "--robot-index", "--truth", "--verbose", "-o"],  # docs/cli.md
    "record": ["--robot", "--camera", "--keys", "--mode", "--cluster-threshold", "--connect",
               "--config", "--quiet", "--verbose"],  # docs/cli.md
    "play": ["--rate", "--start", "--end", "--loop", "--inputs-only", "--connect", "--config",
             "--quiet", "--verbose"],
    "foxglove": ["--robot", "--camera", "--mode", "--cluster-threshold", "--connect",
                 "--config", "--quiet", "--verbose"],
    # the live scene into Rerun
    "rerun": ["--robot", "--camera", "--save", "--viewer", "--serve", "--host", "--port",
              "--source", "--mode", "--connect", "--config", "--quiet", "--verbose"],
    # docs/cli.md: launch files, status, re-registration
    "launch": ["--check", "--log-dir", "--quiet", "--set", "--verbose"],
    "status": ["--connect", "--interval", "--json", "--listen", "--once", "--prefix",
               "--quiet", "--secure", "--name", "--timeout", "--verbose", "--zenoh-config"],
    "register": ["--camera", "--connect", "--listen", "--prefix", "--quiet", "--robot",
                 "--secure", "--name", "--timeout", "--verbose", "--zenoh-config"],
    # the summary stream for remote viewers
    "summary": ["--robot", "--hold-s", "--cache", "--max-pending", "--max-group-pairs",
                "--max-pairs",
                "--connect", "--config", "--secure", "--name", "--quiet", "--verbose"],
    # the ROS 2 bridge (docs/ros2.md)
    "ros2": ["--robot", "--domain", "--distro", "--from-ros", "--no-export", "--node",
             "--mode", "--cluster-threshold", "--glyph", "--connect", "--config", "--secure",
             "--name", "--quiet", "--verbose"],
}


def _options(parser: argparse.ArgumentParser) -> set[str]:
    return {o for a in parser._actions for o in a.option_strings}


def _parse(command: str, *argv: str) -> argparse.Namespace:
    return command_parser(command).parse_args(list(argv))


def test_the_command_table_is_the_legacy_one() -> None:
    assert set(COMMANDS) == set(LEGACY_FLAGS)


@pytest.mark.parametrize("command", sorted(LEGACY_FLAGS))
def test_every_legacy_flag_still_exists(command: str) -> None:
    missing = set(LEGACY_FLAGS[command]) - _options(command_parser(command))
    assert not missing, missing


# Each legacy flag, given, lands in the same setting as before (the names differed: --hold →
# hold_s, --no-wait → wait_for_estimator, --rtol → rtol_growth, --stereo-baseline → …_m).
LEGACY_PARSES = [
    ("sim", ["--robot", "r2", "--scenario", "grid", "--seed", "3", "--rate", "0", "--loops",
             "2", "--anonymous", "--no-wait", "--hold", "1.5"],
     SimSettings(robot="r2", scenario="grid", seed=3, rate=0.0, loops=2, anonymous=True,
                 wait_for_estimator=False, hold_s=1.5)),
    ("estimator", ["--robot", "r", "--sigma-v", "0.1", "--sigma-w", "0.2", "--sigma-range",
                   "0.3", "--sigma-bearing", "0.04", "--gate-chi2", "5", "--new-landmark-chi2",
                   "20", "--fault", "map-update", "--faulty-features", "3,12",
                   "--fault-magnitude", "1e-3", "--fault-onset", "2.5"],
     EstimatorSettings(robot="r", sigma_v=0.1, sigma_w=0.2, sigma_range=0.3,
                       sigma_bearing=0.04, gate_chi2=5.0, new_landmark_chi2=20.0,
                       fault="map-update", faulty_features=(3, 12), fault_magnitude=1e-3,
                       fault_onset=2.5)),
    ("replay", ["data/m", "--robot", "r", "--format", "mrclam", "--robot-index", "2", "--rate",
                "3", "--start", "10", "--duration", "5", "--no-wait"],
     ReplaySettings(path="data/m", robot="r", robot_index=2, rate=3.0, start_s=10.0,
                    duration_s=5.0, wait_for_estimator=False)),
    ("serial", ["--robot", "r", "--port", "loop://", "--baudrate", "9600"],
     SerialSettings(robot="r", port="loop://", baudrate=9600)),
    ("monitor", ["--robot", "r", "--rtol", "1e-6"], MonitorSettings(robot="r", rtol_growth=1e-6)),
    ("registration", ["--camera", "top", "--robot", "r", "--source", "synthetic",
                      "--dictionary", "aruco_4x4_50", "--marker-id", "7", "--marker-size",
                      "0.1", "--marker-offset", "0,0,0.3", "--mode", "head-mounted",
                      "--camera-pose-source", "tracker", "--board", "b.toml",
                      "--stereo-baseline", "0.1", "--fps", "15", "--jpeg-quality", "60",
                      "--loop", "--register-frames", "3", "--width", "640", "--height", "480",
                      "--hfov", "60", "--camera-height", "2", "--camera-yaw", "0",
                      "--arena=-2,-2,2,2", "--noise", "0", "--blur", "0", "--gain", "1.5",
                      "--offset", "4", "--gradient", "0.1", "--seed", "9"],
     RegistrationSettings(camera="top", robot="r", source="synthetic",
                          dictionary="aruco_4x4_50", marker_id=7, marker_size=0.1,
                          marker_offset=(0.0, 0.0, 0.3), mode="head-mounted",
                          camera_pose_source="tracker", board="b.toml", stereo_baseline=0.1,
                          fps=15.0, jpeg_quality=60, loop=True, register_frames=3, width=640,
                          height=480, hfov=60.0, camera_height=2.0, camera_yaw=0.0,
                          arena=(-2.0, -2.0, 2.0, 2.0), noise=0.0, blur=0, gain=1.5,
                          offset=4.0, gradient=0.1, seed=9)),
    ("calibrate", ["a.jpg", "b.jpg", "--squares-x", "6", "--squares-y", "8", "--square", "0.03",
                   "--marker", "0.015", "--dictionary", "aruco_4x4_50", "--legacy-pattern",
                   "-o", "cam.yml"],
     CalibrateSettings(images=("a.jpg", "b.jpg"), squares_x=6, squares_y=8, square=0.03,
                       marker=0.015, dictionary="aruco_4x4_50", legacy_pattern=True,
                       output="cam.yml")),
    ("viewer", ["--robot", "r", "--camera", "top", "--view", "stereo", "--http", "0.0.0.0:0",
                "--fps", "10", "--jpeg-quality", "50", "--recordings-dir", "rec",
                "--record-codec", "MJPG", "--stereo-baseline", "0.1"],
     ViewerConfig(robot="r", camera="top", view="stereo", http="0.0.0.0:0", fps=10.0,
                  jpeg_quality=50, recordings_dir="rec", record_codec="MJPG",
                  stereo_baseline_m=0.1)),
    ("figures", ["--output-dir", "out", "--seed", "4"], FigureSettings(output_dir="out", seed=4)),
    ("demo", ["--robot", "r", "--camera", "top", "--http", "127.0.0.1:0", "--rate", "4",
              "--seed", "2", "--loops", "3", "--faulty", "--fault", "cross-covariance",
              "--faulty-features", "1,2", "--fault-onset", "5", "--fault-magnitude", "0.5",
              "--no-camera", "--duration", "40", "--log-dir", "logs"],
     DemoSettings(robot="r", camera="top", http="127.0.0.1:0", rate=4.0, seed=2, loops=3,
                  faulty=True, fault="cross-covariance", faulty_features=(1, 2),
                  fault_onset=5.0, fault_magnitude=0.5, synthetic_camera=False,
                  duration_s=40.0, log_dir="logs")),
]


@pytest.mark.parametrize(("command", "argv", "expected"), LEGACY_PARSES,
                         ids=[c for c, _, _ in LEGACY_PARSES])
def test_legacy_flags_set_the_same_settings(command: str, argv: list[str], expected) -> None:
    cls = COMMANDS[command].settings_class()
    assert cls is type(expected)
    assert settings_from_args(cls, _parse(command, *argv)) == expected


@pytest.mark.parametrize("command", sorted(c for c in COMMANDS if COMMANDS[c].settings))
def test_no_flags_give_the_documented_defaults(command: str) -> None:
    cls = COMMANDS[command].settings_class()
    required = {"replay": ["p"], "calibrate": ["a.jpg", "-o", "c.yml"], "detect": ["a.jpg"],
                "serial": ["--port", "loop://"], "certs": ["pki", "--name", "robot-r1"],
                "tune": ["p"], "record": ["a.mcap"], "play": ["a.mcap"],
                "launch": ["robot.toml"], "register": ["--camera", "c"]}.get(command, [])
    given = settings_from_args(cls, _parse(command, *required))
    expected = {"replay": ReplaySettings(path="p"),
                "calibrate": CalibrateSettings(images=("a.jpg",), output="c.yml"),
                "detect": DetectSettings(images=("a.jpg",)),
                "serial": SerialSettings(port="loop://"),
                "certs": CertsSettings(directory="pki", names=("robot-r1",)),
                "tune": TuneSettings(path="p"),
                "record": RecordSettings(path="a.mcap"),
                "play": PlaySettings(path="a.mcap"),
                "launch": LaunchSettings(file="robot.toml"),
                "register": RegisterSettings(camera="c")}.get(command) or cls()
    assert given == expected


def test_common_flags_parse_as_before() -> None:
    args = _parse("sim", "--connect", "tcp/127.0.0.1:1", "--connect", "tcp/127.0.0.1:2",
                  "--listen", "tcp/127.0.0.1:3", "--zenoh-config", "z.json5", "--prefix", "lab",
                  "-v", "-v")
    assert bus_flags(args) == BusFlags(connect=("tcp/127.0.0.1:1", "tcp/127.0.0.1:2"),
                                       listen=("tcp/127.0.0.1:3",), zenoh_config="z.json5",
                                       prefix="lab")
    settings = bus_settings(args)
    assert settings.connect == ("tcp/127.0.0.1:1", "tcp/127.0.0.1:2")
    assert settings.zenoh_config == "z.json5"
    assert keys_from(args).state("r") == "lab/robot/r/state"
    assert log_flags(args) == LogFlags(verbose=2, quiet=False)
    none = _parse("sim")
    assert bus_settings(none).connect == () and bus_settings(none).zenoh_config is None
    assert keys_from(none).state("r") == "slamlens/robot/r/state"
    assert log_flags(_parse("figures", "-q")) == LogFlags(quiet=True)


def test_file_first_then_flags_for_every_kind_of_command(tmp_path) -> None:
    demo = tmp_path / "demo.toml"
    demo.write_text('robot = "file"\nrate = 2.0\nfaulty = true\nfaulty_features = [4, 5]\n')
    s = settings_from_args(DemoSettings, _parse("demo", "--config", str(demo), "--rate", "3"))
    assert (s.robot, s.rate, s.faulty, s.faulty_features) == ("file", 3.0, True, (4, 5))
    figures = tmp_path / "figures.toml"
    figures.write_text('seed = 7\neye_m = [0, -1, 2]\n[view]\nmode = "inter"\nlabels = true\n')
    f = settings_from_args(FigureSettings, _parse("figures", "--config", str(figures)))
    assert f.seed == 7 and f.eye_m == (0.0, -1.0, 2.0)
    assert f.view == ViewSettings(mode="inter", labels=True)
    replay = tmp_path / "replay.toml"
    replay.write_text('path = "data/m"\nrobot_index = 3\n')
    r = settings_from_args(ReplaySettings, _parse("replay", "--config", str(replay)))
    assert (r.path, r.robot_index) == ("data/m", 3)
    calibrate = tmp_path / "calibrate.toml"
    calibrate.write_text("squares_x = 9\n")
    c = settings_from_args(CalibrateSettings,
                           _parse("calibrate", "x.jpg", "-o", "c.yml", "--config", str(calibrate)))
    assert (c.squares_x, c.images) == (9, ("x.jpg",))


def test_router_has_no_config_and_says_so_in_the_reference() -> None:
    assert "--config" not in _options(command_parser("router"))
    with pytest.raises(SystemExit) as info:
        _parse("router", "--config", "x.toml")
    assert info.value.code == 2
    assert "## slamlens router" in reference() and "no `--config`" in reference()


@pytest.mark.parametrize(("command", "argv", "message"), [
    ("serial", [], "setting 'port' is required: give --port"),
    ("replay", [], "setting 'path' is required: give PATH"),
    ("calibrate", ["x.jpg"], "setting 'output' is required: give --output"),
    ("viewer", ["--jpeg-quality", "101"], "'jpeg_quality': 101 is above the maximum 100"),
    ("registration", ["--jpeg-quality", "0"], "'jpeg_quality': 0 is below the minimum 1"),
    ("viewer", ["--view", "sideways"], "'view': 'sideways' is not one of"),
    ("figures", ["--eye-m", "1,2"], "'eye_m': expected 3 values, got 2"),
])
def test_bad_or_missing_settings_are_one_config_error(command: str, argv: list[str],
                                                      message: str) -> None:
    cls = COMMANDS[command].settings_class()
    with pytest.raises(ConfigError) as info:
        settings_from_args(cls, _parse(command, *argv))
    assert message in str(info.value)


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_flag_has_help_and_says_its_default(command: str) -> None:
    parser = command_parser(command)
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        assert action.help and action.help != argparse.SUPPRESS, action
        valued = action.nargs is None and not action.const and action.option_strings \
            and not isinstance(action, (argparse._AppendAction, argparse._CountAction))
        if valued and action.dest != "config":
            assert "default: " in action.help or "required" in action.help, \
                (command, action.option_strings, action.help)


def test_the_new_users_complaints_are_answered() -> None:
    def help_of(command: str, flag: str) -> str:
        action = next(a for a in command_parser(command)._actions if flag in a.option_strings)
        return str(action.help)

    assert "do not wait" in help_of("replay", "--no-wait")
    assert "baud" in help_of("serial", "--baudrate")
    assert help_of("figures", "-v") and help_of("figures", "-q")
    assert "default: 1" in help_of("sim", "--rate") and "default: 1" in help_of("replay", "--rate")
    assert "default: 1" in help_of("replay", "--robot-index")
    assert "docs/figures" in COMMANDS["figures"].help
    assert "default: docs/figures" in help_of("figures", "--output-dir")
    for command in ("demo", "calibrate", "figures"):
        assert "--config" in _options(command_parser(command))


def test_help_prints_every_flag(capsys) -> None:
    for command in COMMANDS:
        with pytest.raises(SystemExit) as info:
            main([command, "--help"])
        assert info.value.code == 0
        text = capsys.readouterr().out
        for option in _options(command_parser(command)):
            assert option in text, (command, option)


def test_cli_reference_is_up_to_date() -> None:
    assert DOC.read_text() == reference(), \
        "docs/cli.md is out of date: run `python -m slamlens.services.commands.reference`"


def test_cli_reference_names_every_flag_of_every_command() -> None:
    text = reference()
    common = text[text.index("## Common flags"):text.index("## slamlens ")]
    for command in COMMANDS:
        start = text.index(f"## slamlens {command}\n")
        end = text.find("\n## slamlens ", start + 1)
        section = text[start:end if end > 0 else None]
        for action in command_parser(command)._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            names = action.option_strings or [str(action.metavar)]
            assert any(f"`{n}" in section or f"`{n}" in common for n in names), \
                (command, names)


def test_help_does_not_load_numpy_or_opencv() -> None:
    # the estimator sets one BLAS thread before numpy is imported; --help must not import it
    code = ("import sys; from slamlens.services.commands.cli import command_parser\n"
            "for c in ('estimator', 'monitor', 'figures', 'registration', 'viewer', 'demo'):\n"
            "    command_parser(c).format_help()\n"
            "print(sorted(m for m in ('numpy', 'cv2', 'zenoh') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_a_command_can_take_its_settings_from_flags_only(monkeypatch) -> None:
    monkeypatch.setitem(COMMANDS, "flagsonly", Command(
        "router", "x", "slam.settings:SerialSettings", config=False))
    options = _options(command_parser("flagsonly"))
    assert "--port" in options and "--config" not in options
    assert "Flags only (no `--config`)." in reference()
