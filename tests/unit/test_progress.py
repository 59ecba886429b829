"""Progress bars: only on a terminal unless asked, and what they say."""

from __future__ import annotations

import threading

import numpy as np

from slamlens.common.inprocess_bus import InProcessBus
from slamlens.common.keys import Keys
from slamlens.common.messages import Odometry, Truth
from slamlens.common.progress import NoBar, count_bar, enabled, time_bar
from slamlens.services.slam.drivers import RobotPublisher, play


def test_auto_shows_no_bar_off_a_terminal_and_off_never() -> None:
    assert not enabled("auto")  # pytest captures stderr: not a terminal
    assert enabled("on") and not enabled("off")
    assert isinstance(time_bar(10.0, desc="x"), NoBar)
    assert isinstance(count_bar(10, desc="x", mode="off"), NoBar)
    assert isinstance(time_bar(0.0, desc="x", mode="on"), NoBar)  # nothing to count


def test_a_time_bar_says_data_time_speed_and_time_left(capsys) -> None:
    bar = time_bar(100.0, desc="replay robot1", mode="on")
    bar.update(25.0)
    bar.refresh()
    bar.close()
    err = capsys.readouterr().err
    assert "replay robot1" in err and "25/100 s of data" in err and "× real time" in err


class Recorder:
    def __init__(self) -> None:
        self.total = 0.0

    def update(self, n: float) -> None:
        self.total += n


def test_play_advances_the_bar_by_the_data_time_published() -> None:
    bus = InProcessBus()
    out = RobotPublisher(bus, keys=Keys(), robot="r1")
    events = [Truth(robot="r1", stamp=100.0, pose=np.zeros(3),
                    landmark_ids=np.zeros(0, np.int64), landmarks=np.zeros((0, 2)))]
    events += [Odometry(robot="r1", stamp=100.0 + 0.5 * k, dt=0.5, v=0.1, w=0.0)
               for k in range(1, 21)]
    bar = Recorder()
    play(events, out, threading.Event(), rate=0.0, bar=bar)
    assert bar.total == 10.0
