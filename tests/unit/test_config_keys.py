"""Settings: declared once (flags, help, checks), loaded file-then-flags; key builders."""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass, field

import pytest

from slamlens.common.config import (
    add_flags,
    describe,
    flag_values,
    load_settings,
    setting,
    settings_from_args,
)
from slamlens.common.errors import ConfigError
from slamlens.common.geometry import wrap_angle
from slamlens.common.keys import Keys


@dataclass(frozen=True)
class _Demo:
    name: str = "a"
    rate: float = field(default=1.0, metadata={"min": 0.0})
    count: int = 3
    mode: str = field(default="x", metadata={"choices": ("x", "y")})
    ids: tuple[int, ...] = ()
    flag: bool = False


def test_file_then_flags(tmp_path) -> None:
    path = tmp_path / "s.toml"
    path.write_text('name = "file"\nrate = 2.5\nids = [1, 2]\n')
    s = load_settings(_Demo, path, {"rate": 4, "count": None, "mode": "y", "flag": True})
    assert s == _Demo(name="file", rate=4.0, count=3, mode="y", ids=(1, 2), flag=True)
    assert load_settings(_Demo, None, {"ids": "3, 4"}).ids == (3, 4)


@pytest.mark.parametrize(
    ("text", "overrides", "message"),
    [
        ("colour = 1\n", {}, "unknown setting(s) in"),
        ("", {"mode": "z"}, "'mode': 'z' is not one of"),
        ("", {"rate": -1.0}, "'rate': -1.0 is below the minimum"),
        ("count = 'many'\n", {}, "'count': expected an integer"),
        ("rate = nan\n", {}, "'rate': expected a finite number"),
        ("rate = [\n", {}, "not valid TOML"),
    ],
)
def test_bad_settings_named(tmp_path, text: str, overrides: dict, message: str) -> None:
    path = tmp_path / "s.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_settings(_Demo, path, overrides)
    assert message in str(info.value)


def test_missing_file_named(tmp_path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        load_settings(_Demo, tmp_path / "nope.toml")


def test_keys_follow_spec() -> None:
    k = Keys()
    assert k.odometry("r1") == "slamlens/robot/r1/odometry"
    assert k.observations("r1") == "slamlens/robot/r1/observations"
    assert k.truth("r1") == "slamlens/robot/r1/truth"
    assert k.state("r1") == "slamlens/robot/r1/state"
    assert k.health("r1") == "slamlens/robot/r1/health"
    assert k.frame("top") == "slamlens/camera/top/frame"
    assert k.registration("top", "r1") == "slamlens/camera/top/registration/r1"
    assert k.camera_pose("top") == "slamlens/camera/top/pose"
    assert Keys("lab/a").state("r") == "lab/a/robot/r/state"
    assert k.leaf_of(k.state("r1")) == "state" and k.robot_of(k.state("r1")) == "r1"


def test_keys_parse_back_the_names_they_were_built_from() -> None:
    lab = Keys("lab/a")
    assert lab.camera_of(lab.camera_control("top-left")) == "top-left"
    assert lab.camera_of(lab.registration("top", "r1")) == "top"
    assert lab.robot_of(lab.state("r2")) == "r2"
    assert lab.camera_of(lab.state("r2")) is None  # a robot key names no camera
    assert lab.robot_of(lab.frame("top")) is None
    assert lab.camera_of(Keys().camera_control("top")) is None  # another prefix
    assert lab.camera_of("lab/a/camera") is None  # too short to hold a name


@pytest.mark.parametrize("name", ["", "a/b", "r*", "x y", "$z"])
def test_bad_names_rejected(name: str) -> None:
    with pytest.raises(ConfigError):
        Keys().state(name)


def test_wrap_angle_range() -> None:
    import math

    import numpy as np

    a = np.linspace(-20, 20, 4001)
    w = wrap_angle(a)
    assert np.all(w >= -math.pi) and np.all(w < math.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    assert wrap_angle(math.pi) == -math.pi


# ------------------------------------------------------------ a setting declared once


@dataclass(frozen=True)
class _Declared:
    path: str = setting("", doc="input folder", positional=True, required=True, metavar="DIR")
    rate_hz: float = setting(2.0, doc="how often", unit="Hz", min=0.5, max=10.0,
                             flag="--rate")
    mode: str = setting("x", doc="the mode", choices=("x", "y"))
    wait: bool = setting(True, doc="wait for the peer")
    loud: bool = setting(False, doc="say more", short="-L")
    peers: tuple[str, ...] = setting((), doc="peer to call", action="append", metavar="PEER")
    size_m: tuple[float, float] = setting((1.0, 2.0), doc="size", unit="m", metavar="W,H")
    secret: int = setting(0, doc="an internal knob", hidden=True)
    file_only: int = setting(3, doc="only in the file", flag=False)
    view: _Demo = setting(doc="a nested table", flag=False, default_factory=_Demo)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="demo")
    add_flags(parser, _Declared, title="demo settings")
    parser.add_argument("--config")
    return parser


def test_one_field_gives_flag_help_and_checks() -> None:
    parser = _parser()
    flags = {a.dest: a for a in parser._actions}
    assert flags["rate_hz"].option_strings == ["--rate"]
    assert flags["rate_hz"].help == "how often (default: 2 Hz; 0.5 … 10)"
    assert flags["wait"].option_strings == ["--no-wait"]
    assert flags["wait"].help == "do not wait for the peer"
    assert flags["loud"].option_strings == ["-L", "--loud"]
    assert flags["mode"].metavar == "{x,y}" and "default: x" in flags["mode"].help
    assert flags["size_m"].help == "size (default: 1,2 m)"
    assert flags["secret"].help == argparse.SUPPRESS
    assert "file_only" not in flags and "view" not in flags
    assert flags["path"].option_strings == [] and flags["path"].help == "input folder (required)"
    assert describe(next(f for f in dataclasses.fields(_Declared) if f.name == "wait")) == \
        "wait for the peer"  # the TOML key's meaning; the flag says "do not"


def test_only_given_flags_override_the_file(tmp_path) -> None:
    path = tmp_path / "d.toml"
    path.write_text('rate_hz = 4.0\nwait = false\nfile_only = 7\n[view]\nmode = "y"\n')
    args = _parser().parse_args(["here", "--config", str(path), "-L", "--peers", "a",
                                 "--peers", "b", "--size-m", "3,4"])
    assert flag_values(_Declared, args) == {"path": "here", "loud": True,
                                            "peers": ["a", "b"], "size_m": "3,4"}
    s = settings_from_args(_Declared, args)
    assert s == _Declared(path="here", rate_hz=4.0, wait=False, loud=True, peers=("a", "b"),
                          size_m=(3.0, 4.0), file_only=7, view=_Demo(mode="y"))
    s = settings_from_args(_Declared, _parser().parse_args(["here", "--no-wait", "--rate", "8"]))
    assert (s.wait, s.rate_hz, s.file_only) == (False, 8.0, 3)
    hidden = settings_from_args(_Declared, _parser().parse_args(["here", "--secret", "5"]))
    assert hidden.secret == 5


@pytest.mark.parametrize(("argv", "message"), [
    ([], "setting 'path' is required: give DIR"),
    (["p", "--rate", "11"], "'rate_hz': 11.0 is above the maximum 10.0"),
    (["p", "--rate", "0.1"], "'rate_hz': 0.1 is below the minimum 0.5"),
    (["p", "--mode", "z"], "'mode': 'z' is not one of ['x', 'y']"),
    (["p", "--size-m", "1,2,3"], "'size_m': expected 2 values, got 3"),
])
def test_declared_checks_name_the_key(argv: list[str], message: str) -> None:
    with pytest.raises(ConfigError) as info:
        settings_from_args(_Declared, _parser().parse_args(argv))
    assert message in str(info.value)


def test_a_nested_table_is_checked_like_its_own_file(tmp_path) -> None:
    path = tmp_path / "d.toml"
    path.write_text('path = "p"\n[view]\nmode = "z"\n')
    with pytest.raises(ConfigError, match="'mode': 'z' is not one of"):
        load_settings(_Declared, path)
    path.write_text('path = "p"\nview = 3\n')
    with pytest.raises(ConfigError, match="'view': expected a table"):
        load_settings(_Declared, path)


def test_setting_rejects_an_unknown_action() -> None:
    with pytest.raises(ConfigError, match="action"):
        setting(0, doc="x", action="store_const")
