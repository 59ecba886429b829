"""``slamlens replay``: a recorded dataset as a robot driver, by its format.

``--format mrclam`` (the UTIAS dataset) is the SLAM side's driver (``services/slam/cli.py``);
``--format rosbag2`` is the ROS 2 side's bag player (``services/ros2/cli.py``). The command
and its settings (``slam.settings.ReplaySettings``) are one; this module only chooses, so
neither service imports the other.
"""

from __future__ import annotations

import argparse

from slamlens.common.config import settings_from_args
from slamlens.common.errors import ConfigError
from slamlens.services.slam.settings import ReplaySettings


def run(command: str, args: argparse.Namespace) -> int:
    s = settings_from_args(ReplaySettings, args)
    if s.format != "rosbag2":
        from slamlens.services.slam import cli

        return cli.run(command, args)
    if s.robots:
        raise ConfigError("--robots is for MRCLAM; a rosbag2 folder is played as one robot "
                          "(--robot R)")
    from slamlens.services.ros2 import cli as ros2_cli
    from slamlens.services.ros2.settings import BagReplay

    return ros2_cli.run_bag(args, BagReplay(
        path=s.path, robot=s.robot, what=s.from_ros, rate=s.rate, start_s=s.start_s,
        duration_s=s.duration_s, wait_for_estimator=s.wait_for_estimator,
        wait_timeout_s=s.wait_timeout_s, progress=s.progress))
