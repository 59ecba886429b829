"""A service with a cache connected straight off its host says so, once (docs/delivery.md,
"What a lab can expect": a caching publisher behind a slow link waits while a subscriber
recovers, unless a router on its own host stands between).

Two network namespaces: the workstation's router listens on the link. An estimator on the
robot connected straight to it logs the warning naming that endpoint; one connected to the
robot's own router (on loopback, linked to the workstation's, as deploy/robot.toml runs
it) does not.
"""

from __future__ import annotations

from slamlens.services.harness.netns import Hosts
from slamlens.services.harness.procs import Started, stop

WARNING = "off this host: a publisher with a cache then waits"


def test_an_estimator_connected_straight_across_the_link_warns(two_hosts: Hosts) -> None:
    h = two_hosts
    across = f"tcp/{h.workstation_ip}:7447"
    started = Started()
    try:
        started.start("router", "--listen", across, ready="router ready", netns=h.workstation)
        started.start("router", "--listen", "tcp/127.0.0.1:7447", "--connect", across,
                      ready="router ready", netns=h.robot)
        straight = started.start("estimator", "--robot", "robot1", "--connect", across,
                                 ready="estimator ready", netns=h.robot)
        routed = started.start("estimator", "--robot", "robot2", "--connect",
                               "tcp/127.0.0.1:7447", ready="estimator ready", netns=h.robot)
        _, straight_err = stop(straight)
        _, routed_err = stop(routed)
    finally:
        started.stop_all()
    warned = [ln for ln in straight_err.splitlines() if WARNING in ln]
    assert len(warned) == 1, straight_err[-2000:]
    assert across in warned[0] and "connect to a router on this host" in warned[0]
    assert WARNING not in routed_err, routed_err[-2000:]
