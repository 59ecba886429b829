"""Settings loading (file, then flags; unknown keys named) and key builders."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from common.config import load_settings
from common.errors import ConfigError
from common.geometry import wrap_angle
from common.keys import Keys


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
