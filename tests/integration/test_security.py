"""docs/security.md on real Zenoh: a `slamlens router` process serving mutual TLS, enforcing the
roles of every identity in its folder, against clients on loopback — legitimate ones, with
plain and advanced (zenoh.ext) publishers and subscribers, and spoofers.

Every spoofing test brackets the spoofed messages with legitimate ones and asserts the
subscriber got exactly the legitimate ones. The bracket is causal, not timed: after its
spoofed put the spoofer queries a queryable of the legitimate robot over the same link, so
the router has handled (forwarded or dropped) the put before the robot publishes the
closing sample — if the put got through, it reaches the subscriber first.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest
import zenoh
import zenoh.ext as zx

from slamlens.common.certs import extend_authority
from slamlens.common.errors import BusError, SecurityError
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus
from slamlens.common.zenoh_bus import ZenohBus
from slamlens.services.harness.procs import REPO, slamlens_cmd, spawn, stop

NAMES = ["router-ws", "robot-r1", "robot-r2", "camera-overhead", "monitor-r1", "viewer-lab"]
STATE = "slamlens/robot/r1/state"
ODOMETRY = "slamlens/robot/r1/odometry"


class RouterProcess:
    """A `slamlens router` process whose log is collected as it is written."""

    def __init__(self, *args: str) -> None:
        self.proc = spawn("router", *args)
        self.proc.wait_for_line("router ready", timeout=30)

    @property
    def lines(self) -> list[str]:
        return [line.rstrip("\n") for line in self.proc.err]

    def wait_log(self, text: str, timeout: float = 10.0) -> str:
        """The first line of the router's log containing ``text``, once it is written."""
        deadline = time.monotonic() + timeout
        while True:
            line = next((x for x in self.lines if text in x), None)
            if line is not None:
                return line
            if time.monotonic() > deadline or self.proc.poll() is not None:
                raise AssertionError(f"router never logged {text!r}; log:\n"
                                     + "\n".join(self.lines))
            time.sleep(0.05)

    def close(self) -> None:
        stop(self.proc)
        assert self.proc.returncode == 0, "\n".join(self.lines)


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("pki")
    extend_authority(root, NAMES)
    return root


@pytest.fixture(scope="module")
def secure_router(pki):
    endpoint = free_tcp_endpoint().replace("tcp/", "tls/")
    router = RouterProcess("--listen", endpoint, "--secure", str(pki), "--name", "router-ws")
    router.endpoint = endpoint  # type: ignore[attr-defined]
    yield router
    router.close()


@pytest.fixture
def connect(secure_router, pki):
    """Factory of secure client buses by identity; all closed at teardown."""
    buses: list[ZenohBus] = []

    def make(name: str) -> ZenohBus:
        bus = open_bus(BusSettings(connect=(secure_router.endpoint,), secure=str(pki),
                                   name=name))
        buses.append(bus)
        return bus

    yield make
    for bus in buses:
        bus.close()


class Inbox:
    """Payloads received by a subscriber, waited for by content."""

    def __init__(self) -> None:
        self.items: list[bytes] = []
        self._cond = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.items.append(sample.payload.to_bytes())
            self._cond.notify_all()

    def wait_for(self, payload: bytes, timeout: float = 10.0) -> list[bytes]:
        with self._cond:
            if not self._cond.wait_for(lambda: payload in self.items, timeout):
                raise AssertionError(f"{payload!r} never arrived; got {self.items}")
            return list(self.items)


def _until(fn, what: str, timeout: float = 10.0):
    """``fn()`` once it is truthy (declarations take a moment to reach every session)."""
    deadline = time.monotonic() + timeout
    while not (value := fn()):
        assert time.monotonic() < deadline, f"never: {what}"
        time.sleep(0.05)
    return value


def _deliver(publisher, inbox: Inbox, payload: bytes) -> None:
    """Put ``payload`` until it arrives: the first put on a new route can be lost even once
    the publisher matches (observed with a plain router too), so a bracket must be seen."""
    deadline = time.monotonic() + 10.0
    while True:
        publisher.put(payload)
        try:
            inbox.wait_for(payload, timeout=0.5)
            return
        except AssertionError:
            assert time.monotonic() < deadline, f"{payload!r} never arrived"


def _settle(spoofer: ZenohBus) -> None:
    """A round trip from the spoofer to robot-r1's queryable (see module docstring)."""
    replies = _until(lambda: spoofer.get(STATE, timeout=2.0), "robot-r1's queryable answers")
    assert [r.payload for r in replies] == [b"latest"]


def _legit(got: list[bytes]) -> list[bytes]:
    """``got`` without the repeats of a bracket (see :func:`_deliver`)."""
    return [x for i, x in enumerate(got) if i == 0 or x != got[i - 1]]


def test_tls_pub_sub_get_and_liveliness_between_roles(connect, secure_router) -> None:
    robot, viewer = connect("robot-r1"), connect("viewer-lab")
    robot.serve_latest(STATE, lambda: b"latest")
    robot.declare_alive("slamlens/robot/r1/alive/estimator")
    inbox = Inbox()
    viewer.session.declare_subscriber("slamlens/robot/r1/**", inbox)
    pub = robot.session.declare_publisher(STATE)
    _deliver(pub, inbox, b"s1")
    assert _legit(inbox.items) == [b"s1"]
    replies = _until(lambda: viewer.get(STATE), "the viewer's get is answered")
    assert [s.payload for s in replies] == [b"latest"]
    assert _until(lambda: viewer.alive("slamlens/robot/*/alive/**"), "the token is seen") == [
        "slamlens/robot/r1/alive/estimator"]
    assert "roles enforced for camera-overhead, monitor-r1, robot-r1, robot-r2, router-ws, " \
           "viewer-lab" in secure_router.wait_log("mutual TLS")


def test_a_viewer_cannot_publish_a_state(connect, secure_router) -> None:
    robot, viewer, spoofer = connect("robot-r1"), connect("viewer-lab"), connect("viewer-lab")
    robot.serve_latest(STATE, lambda: b"latest")
    inbox = Inbox()
    viewer.session.declare_subscriber(STATE, inbox)
    legit = robot.session.declare_publisher(STATE)
    fake = spoofer.session.declare_publisher(STATE)
    _deliver(legit, inbox, b"before")
    for _ in range(3):
        fake.put(b"forged state")
        spoofer.session.put(STATE, b"forged state, no publisher")
        _settle(spoofer)
    legit.put(b"after")
    assert _legit(inbox.wait_for(b"after")) == [b"before", b"after"]
    secure_router.wait_log(f"refused: viewer-lab may not Put (ingress) on {STATE}")


def test_a_viewer_puts_its_ar_pages_frames_and_no_camera_output(connect,
                                                                secure_router) -> None:
    camera, viewer, robot = connect("camera-overhead"), connect("viewer-lab"), connect("robot-r1")
    robot.serve_latest(STATE, lambda: b"latest")  # what _settle's round trip asks
    frames, outputs = Inbox(), Inbox()
    camera.session.declare_subscriber("slamlens/camera/*/capture", frames)
    camera.session.declare_subscriber("slamlens/camera/phone-1/frame", outputs)
    pub = viewer.session.declare_publisher("slamlens/camera/phone-1/capture")
    _deliver(pub, frames, b"a browser's frame")  # the AR page's frames reach registration
    for _ in range(3):  # but the viewer cannot speak for the camera
        viewer.session.put("slamlens/camera/phone-1/frame", b"forged frame")
        _settle(viewer)
    secure_router.wait_log("refused: viewer-lab may not Put (ingress) on "
                           "slamlens/camera/phone-1/frame")
    assert outputs.items == []


def test_another_robot_cannot_feed_r1_odometry(connect, secure_router) -> None:
    driver, estimator, spoofer = connect("robot-r1"), connect("robot-r1"), connect("robot-r2")
    driver.serve_latest(STATE, lambda: b"latest")
    inbox = Inbox()
    estimator.session.declare_subscriber("slamlens/robot/r1/*", inbox)
    legit = driver.session.declare_publisher(ODOMETRY)
    _deliver(legit, inbox, b"odo 1")
    for _ in range(3):
        spoofer.session.put(ODOMETRY, b"forged odometry")
        spoofer.session.put("slamlens/robot/r1/observations", b"forged observations")
        spoofer.session.put("slamlens/robot/r2/odometry", b"r2's own")  # allowed, not r1's
        _settle(spoofer)
    legit.put(b"odo 2")
    assert _legit(inbox.wait_for(b"odo 2")) == [b"odo 1", b"odo 2"]
    secure_router.wait_log(f"refused: robot-r2 may not Put (ingress) on {ODOMETRY}")


def test_roles_of_monitor_and_camera(connect, secure_router) -> None:
    robot, viewer = connect("robot-r1"), connect("viewer-lab")
    monitor, camera = connect("monitor-r1"), connect("camera-overhead")
    robot.serve_latest(STATE, lambda: b"latest")
    inbox = Inbox()
    viewer.session.declare_subscriber("slamlens/**", inbox)
    health = monitor.session.declare_publisher("slamlens/robot/r1/health")
    frame = camera.session.declare_publisher("slamlens/camera/overhead/frame")
    tracked = camera.session.declare_publisher("slamlens/camera/overhead/tracked/r1")
    _deliver(health, inbox, b"health 1")
    _deliver(frame, inbox, b"frame 1")
    _deliver(tracked, inbox, b"tracked 1")  # its own measure of a robot: under its own name
    for _ in range(3):
        monitor.session.put(STATE, b"monitor's forged state")
        camera.session.put("slamlens/camera/other/frame", b"another camera's frame")
        # docs/security.md: a camera says nothing outside slamlens/camera/C/** (not a tracked pose)
        camera.session.put("slamlens/robot/r1/tracked", b"camera's tracked pose")
        _settle(monitor)
        _settle(camera)
    health.put(b"health 2")
    got = inbox.wait_for(b"health 2")
    assert set(got) == {b"frame 1", b"health 1", b"health 2", b"tracked 1"}
    secure_router.wait_log(f"refused: monitor-r1 may not Put (ingress) on {STATE}")
    secure_router.wait_log("refused: camera-overhead may not Put (ingress) on "
                           "slamlens/camera/other/frame")


def test_every_identity_announces_its_own_status_and_only_its_own(connect,
                                                                  secure_router) -> None:
    """The status protocol (common/status.py) through the roles: each identity holds its
    token and answers under slamlens/status/NAME/**; one robot posing as another is
    refused both, and the reader never sees it."""
    from slamlens.common.keys import Keys
    from slamlens.common.messages import ServiceStatus
    from slamlens.common.status import Report, StatusAnnouncer

    keys = Keys()
    reader = connect("viewer-lab")
    announcers = [StatusAnnouncer(connect(name), keys, service=service, name=name,
                                  provider=lambda: Report(counts={"n": 1.0}))
                  for name, service in (("robot-r1", "estimator"), ("monitor-r1", "monitor"),
                                        ("camera-overhead", "registration"),
                                        ("viewer-lab", "viewer"))]
    poser = StatusAnnouncer(connect("robot-r2"), keys, service="estimator", name="robot-r1",
                            provider=lambda: Report(state="forged"))
    try:
        honest = sorted(a.key for a in announcers)

        def clients(found: list[str]) -> list[str]:  # not the router's own
            return sorted(k for k in found if "/router-ws/" not in k)

        assert _until(lambda: clients(reader.alive(keys.any_status())) == honest or None,
                      "every honest token is seen")
        replies = _until(lambda: (r := [s for s in reader.get(keys.any_status())
                                        if "/router-ws/" not in s.key]) and len(r) >= 4 and r,
                         "every honest status answers")
        statuses = {s.key: ServiceStatus.from_bytes(s.payload) for s in replies}
        assert sorted(statuses) == honest
        assert {st.name for st in statuses.values()} == {"robot-r1", "monitor-r1",
                                                         "camera-overhead", "viewer-lab"}
        secure_router.wait_log("refused: robot-r2 may not ")
        assert poser.key not in reader.alive(keys.any_status())
        assert poser.key not in {s.key for s in reader.get(keys.any_status())}
    finally:
        for a in [*announcers, poser]:
            a.close()


def _advanced_publisher(bus: ZenohBus, key: str):
    return zx.declare_advanced_publisher(
        bus.session, key, cache=zx.CacheConfig(max_samples=100),
        sample_miss_detection=zx.MissDetectionConfig(heartbeat=0.2, sporadic_heartbeat=None),
        publisher_detection=True)


def _advanced_subscriber(bus: ZenohBus, key: str, inbox: Inbox):
    return zx.declare_advanced_subscriber(
        bus.session, key, inbox,
        history=zx.HistoryConfig(detect_late_publishers=True, max_samples=100),
        recovery=zx.RecoveryConfig(heartbeat=True, periodic_queries=None),
        subscriber_detection=True)


def test_advanced_pub_sub_history_and_recovery_through_the_roles(connect, secure_router) -> None:
    """docs/delivery.md's advanced publishers/subscribers need the @adv key spaces: a late
    subscriber gets robot-r1's cached history, never the spoofer's, and the spoofer's
    cache queryable and detection token are refused."""
    robot, spoofer, viewer = connect("robot-r1"), connect("robot-r2"), connect("viewer-lab")
    robot.serve_latest(STATE, lambda: b"latest")
    legit = _advanced_publisher(robot, STATE)
    fake = _advanced_publisher(spoofer, STATE)
    legit.put(b"s1")
    legit.put(b"s2")
    fake.put(b"x1")
    fake.put(b"x2")
    _settle(spoofer)
    inbox = Inbox()
    sub = _advanced_subscriber(viewer, STATE, inbox)
    assert inbox.wait_for(b"s2") == [b"s1", b"s2"]  # history from robot-r1's cache only
    fake.put(b"x3")
    _settle(spoofer)
    legit.put(b"s3")
    assert inbox.wait_for(b"s3") == [b"s1", b"s2", b"s3"]
    # only robot-r1's publisher is detectable (the spoofer's token was refused)
    tokens = _until(lambda: viewer.alive(f"{STATE}/@adv/pub/**"), "r1's publisher token")
    assert len(tokens) == 1 and str(robot.session.info.zid()) in tokens[0]
    # the subscriber's detection token (any identity may announce its subscribers)
    subscribers = _until(lambda: robot.alive(f"{STATE}/@adv/sub/**"), "viewer's token")
    assert len(subscribers) == 1 and str(viewer.session.info.zid()) in subscribers[0]
    for kind in ("Declare Queryable", "Liveliness Token", "Put"):
        line = secure_router.wait_log(f"refused: robot-r2 may not {kind} (ingress) on {STATE}")
        assert "/@adv/pub/" in line or kind == "Put"
    sub.undeclare()
    legit.undeclare()
    fake.undeclare()


def test_advanced_inputs_to_an_estimator_and_health_to_a_viewer(connect, secure_router) -> None:
    driver, estimator = connect("robot-r1"), connect("robot-r1")
    monitor, viewer, spoofer = connect("monitor-r1"), connect("viewer-lab"), connect("robot-r2")
    driver.serve_latest(STATE, lambda: b"latest")
    odometry = _advanced_publisher(driver, ODOMETRY)
    odometry.put(b"odo 1")  # before the estimator starts: recovered from the cache
    inputs = Inbox()
    est_sub = _advanced_subscriber(estimator, "slamlens/robot/r1/*", inputs)
    inputs.wait_for(b"odo 1")
    health = _advanced_publisher(monitor, "slamlens/robot/r1/health")
    health.put(b"health 1")
    healths = Inbox()
    view_sub = _advanced_subscriber(viewer, "slamlens/robot/r1/health", healths)
    healths.wait_for(b"health 1")
    spoofer.session.put(ODOMETRY, b"forged")
    _settle(spoofer)
    odometry.put(b"odo 2")
    health.put(b"health 2")
    got = inputs.wait_for(b"odo 2")  # robot/r1/* also matches the health key
    assert [x for x in got if not x.startswith(b"health")] == [b"odo 1", b"odo 2"]
    assert healths.wait_for(b"health 2") == [b"health 1", b"health 2"]
    for entity in (est_sub, view_sub, odometry, health):
        entity.undeclare()


def _raw_tls_config(endpoint: str, *, ca: Path, cert: Path, key: Path) -> zenoh.Config:
    """A client built by hand, as an attacker would (no slamlens checks in the way)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("connect/timeout_ms", "{client: 2000}")
    conf.insert_json5("scouting/multicast/enabled", "false")
    for k, v in {"root_ca_certificate": ca, "connect_certificate": cert,
                 "connect_private_key": key, "listen_certificate": cert,
                 "listen_private_key": key}.items():
        conf.insert_json5(f"transport/link/tls/{k}", json.dumps(str(v)))
    return conf


def test_a_certificate_of_another_authority_cannot_connect(secure_router, pki,
                                                            tmp_path) -> None:
    extend_authority(tmp_path / "rogue", ["robot-r1"])
    rogue = tmp_path / "rogue"
    # it trusts our authority (ca.pem is public) but its own certificate is not ours
    conf = _raw_tls_config(secure_router.endpoint, ca=pki / "ca.pem",
                           cert=rogue / "robot-r1.pem", key=rogue / "robot-r1.key")
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        zenoh.open(conf)
    secure_router.wait_log("refused a TLS connection")
    # and through slamlens itself: refused before it tries, naming the file
    shutil.copy(pki / "ca.pem", rogue / "ca.pem")
    with pytest.raises(SecurityError, match=r"robot-r1\.pem was not issued by"):
        open_bus(BusSettings(connect=(secure_router.endpoint,), secure=str(rogue),
                             name="robot-r1"))


def test_a_plain_tcp_client_cannot_connect_to_the_tls_port(secure_router) -> None:
    plain = secure_router.endpoint.replace("tls/", "tcp/")
    with pytest.raises(BusError, match=f"no Zenoh router answered at {plain}"):
        open_bus(BusSettings(connect=(plain,), extra={"connect/timeout_ms": "{client: 2000}"}))
    secure_router.wait_log("refused a TLS connection: received corrupt message")


def test_an_identity_the_router_does_not_hold_is_refused_everything(secure_router, pki,
                                                                    connect, tmp_path) -> None:
    """A name issued after the router started (its certificate is not in the router's
    folder) connects — it is of this authority — but may say nothing."""
    late = tmp_path / "late"
    late.mkdir()
    for f in ("ca.pem", "ca.key"):
        (late / f).write_bytes((pki / f).read_bytes())
    extend_authority(late, ["robot-r1b"])
    robot, viewer = connect("robot-r1"), connect("viewer-lab")
    robot.serve_latest(STATE, lambda: b"latest")
    inbox = Inbox()
    viewer.session.declare_subscriber("slamlens/robot/**", inbox)
    stranger = open_bus(BusSettings(connect=(secure_router.endpoint,), secure=str(late),
                                    name="robot-r1b"))
    try:
        legit = robot.session.declare_publisher(STATE)
        _deliver(legit, inbox, b"before")
        for _ in range(3):
            stranger.session.put("slamlens/robot/r1b/state", b"stranger's state")
            stranger.session.put(STATE, b"stranger's r1 state")
        # it may not even ask; but its puts went first on its link, so they are handled
        assert stranger.get(STATE, timeout=1.0) == []
        legit.put(b"after")
        assert _legit(inbox.wait_for(b"after")) == [b"before", b"after"]
        secure_router.wait_log("presented no identity this router knows")
    finally:
        stranger.close()


def test_router_process_honours_its_zenoh_config_listen(tmp_path) -> None:
    endpoint = free_tcp_endpoint()
    file = tmp_path / "router.json5"
    file.write_text(f'{{ mode: "router", listen: {{ endpoints: ["{endpoint}"] }},'
                    ' scouting: { multicast: { enabled: false } } }')
    router = RouterProcess("--zenoh-config", str(file))
    try:
        router.wait_log(f"router listening on {endpoint}")
        bus = open_bus(BusSettings(connect=(endpoint,)))
        bus.close()
    finally:
        router.close()


def test_a_missing_router_is_one_line(tmp_path) -> None:
    endpoint = free_tcp_endpoint()  # nobody listens there
    file = tmp_path / "client.json5"  # the user's own file: waits 1 s, not the default 10 s
    file.write_text(f'{{ mode: "client", connect: {{ endpoints: ["{endpoint}"], '
                    'timeout_ms: { client: 1000 } }, scouting: { multicast: { enabled: false } } }')
    proc = subprocess.run(slamlens_cmd("monitor", "--robot", "r1", "--zenoh-config", str(file)),
                          cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert lines[-1] == (f"slamlens: error: no Zenoh router answered at {endpoint}: "
                         "is `slamlens router` running there?")
    assert ".rs:" not in proc.stderr
