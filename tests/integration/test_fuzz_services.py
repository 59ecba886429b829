"""Malformed payloads on every key a service subscribes to, through real processes.

A fast sample of services/harness/fuzz.py per key (benchmarks/bench_fuzz.py sends ≥ 100 000 each):
the service never crashes, counts every rejection, and still produces correct output
afterwards.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable

import msgpack
import numpy as np

from slamlens.common.keys import Keys
from slamlens.common.messages import Health, Observations, Odometry, SlamState, Truth
from slamlens.services.harness.fuzz import bad_payloads, valid
from slamlens.services.harness.procs import spawn, stop

KEYS = Keys()
ROBOT = "robot1"
PER_KEY = 400


def _final(out: str, name: str) -> dict:
    line = [ln for ln in out.splitlines() if ln.startswith(f"{name} stopped: ")][-1]
    return json.loads(line.split(": ", 1)[1])


class Inbox:
    def __init__(self, bus, key: str, kind) -> None:
        self.items: list = []
        self.kind = kind
        self.cond = threading.Condition()
        bus.subscribe(key, self._on)

    def _on(self, key: str, payload: bytes) -> None:
        with self.cond:
            self.items.append(self.kind.from_bytes(payload))
            self.cond.notify_all()

    def wait(self, predicate, timeout: float = 30.0) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: predicate(self.items), timeout)


def _flood(bus, key: str, kind, count: int, seed: int, *,
           counted: Callable[[], int] | None = None, already: int = 0) -> int:
    """Send ``count`` bad payloads none of which is lost on the way: the test's publisher
    blocks under congestion (slamlens' own never do), so the service must count them all.

    With ``counted`` (the service's live count of rejections, ``already`` of them sent
    before): the first payload is put again until it is counted, since a route may still
    drop samples for a few hundred ms after its publisher matched (zenoh 1.10 under load,
    measured up to 0.3 s); returns how many were sent and counted."""
    import zenoh

    pub = bus.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
    deadline = time.monotonic() + 10
    while not pub.matching_status and time.monotonic() < deadline:
        time.sleep(0.01)
    assert pub.matching_status  # a new publisher may drop what it puts before it matches
    payloads = iter(bad_payloads(kind, np.random.default_rng(seed), count))
    n = 0
    if counted is not None:
        assert _until(lambda: counted() == already), "the previous flood was not all counted"
        first = next(payloads)
        deadline = time.monotonic() + 30
        while True:
            pub.put(first)
            if _until(lambda: counted() > already, timeout=4.0):  # status: ≤ 1 s old
                break
            assert time.monotonic() < deadline, f"nothing put on {key} was counted"
        n = counted() - already
    for payload in payloads:
        pub.put(payload)
        n += 1
    pub.undeclare()
    return n


def _until(predicate: Callable[[], bool], timeout: float = 30.0) -> bool:
    """Poll ``predicate`` until it holds (True) or ``timeout`` s passed (False)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.02)
    return True


def _status_dropped(bus, service: str) -> int:
    """What ``service`` counted as dropped, from its status (rebuilt once a second)."""
    from slamlens.common.messages import ServiceStatus

    for reply in bus.get(KEYS.any_status(), timeout=2.0):
        status = ServiceStatus.from_bytes(reply.payload)
        if status.service == service:
            return status.dropped
    return -1


def _header(bus) -> dict:
    import msgpack

    (reply,) = bus.get(KEYS.state(ROBOT) + "?header", timeout=5.0)
    return msgpack.unpackb(reply.payload)


def test_estimator_survives_garbage_on_both_input_keys(router_endpoint, make_client) -> None:
    est = spawn("estimator", "--robot", ROBOT, "--connect", router_endpoint)
    est.wait_for_line("estimator ready")
    client = make_client()
    states = Inbox(client, KEYS.state(ROBOT), SlamState)
    assert client.wait_for_subscriber(KEYS.odometry(ROBOT))
    try:
        def dropped() -> int:
            return _status_dropped(client, "estimator")

        sent = _flood(client, KEYS.odometry(ROBOT), Odometry, PER_KEY, 1, counted=dropped)
        sent += _flood(client, KEYS.observations(ROBOT), Observations, PER_KEY, 2,
                       counted=dropped, already=sent)
        # afterwards, correct output: an odometry step then an observation batch
        client.publisher(KEYS.odometry(ROBOT)).put(valid(Odometry, robot=ROBOT).to_bytes())
        client.publisher(KEYS.observations(ROBOT)).put(
            valid(Observations, robot=ROBOT).to_bytes())
        assert states.wait(lambda s: any(x.step == "update" and x.n == 2 for x in s))
        # every bad payload counted (the two keys' samples may interleave on the way)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and _header(client)["dropped"] != sent:
            time.sleep(0.05)
        assert est.poll() is None
    finally:
        out, err = stop(est)
    assert est.returncode == 0, err
    summary = _final(out, "estimator")
    assert summary["dropped"] == sent, summary
    assert summary["odometry"] == 1 and summary["observation_batches"] == 1
    assert "Traceback" not in err


def test_monitor_survives_garbage_on_state_truth_and_tracked(router_endpoint,
                                                            make_client) -> None:
    mon = spawn("monitor", "--robot", ROBOT, "--connect", router_endpoint)
    mon.wait_for_line("monitor ready")
    client = make_client()
    healths = Inbox(client, KEYS.health(ROBOT), Health)
    assert client.wait_for_subscriber(KEYS.state(ROBOT))
    try:
        def dropped() -> int:
            return _status_dropped(client, "monitor")

        sent = _flood(client, KEYS.state(ROBOT), SlamState, PER_KEY, 3, counted=dropped)
        sent += _flood(client, KEYS.truth(ROBOT), Truth, PER_KEY, 4, counted=dropped,
                       already=sent)
        sent += _flood(client, KEYS.tracked_by("overhead", ROBOT), Truth, PER_KEY, 5,
                       counted=dropped, already=sent)
        pub = client.publisher(KEYS.state(ROBOT))
        assert pub.wait_matched()  # type: ignore[attr-defined]
        # correct output afterwards: a Health per state, until one says every bad payload
        # was counted (the three keys' samples may interleave on the way)
        seq = 0
        while seq < 200:
            seq += 1
            pub.put(valid(SlamState, robot=ROBOT, seq=seq).to_bytes())
            assert healths.wait(lambda h, s=seq: h and h[-1].seq == s)
            if healths.items[-1].statistics.get("dropped") == sent:
                break
        assert [x.seq for x in healths.items] == list(range(1, seq + 1))
        assert all(h.ok for h in healths.items)
        assert mon.poll() is None
    finally:
        out, err = stop(mon)
    assert mon.returncode == 0, err
    summary = _final(out, "monitor")
    assert summary["dropped"] == sent and summary["checked"] == seq, summary
    assert "Traceback" not in err


def test_registration_counts_a_control_flood_in_a_few_log_lines(router_endpoint,
                                                                make_client) -> None:
    """20 000 bad control messages are counted, logged in a handful of lines,
    and the camera keeps registering (garbage on truth and camera pose too)."""
    from slamlens.common.messages import CameraControl, Registration

    reg = spawn("registration", "--config", "deploy/camera_overhead.toml", "--connect",
                router_endpoint, "--fps", "10", "--width", "640", "--height", "360")
    reg.wait_for_line("registration ready")
    client = make_client()
    registrations = Inbox(client, KEYS.registration("overhead", ROBOT), Registration)
    try:
        def dropped() -> int:
            return _status_dropped(client, "registration")

        sent = _flood(client, KEYS.camera_control("overhead"), CameraControl, 20_000, 6,
                      counted=dropped)
        sent += _flood(client, KEYS.truth(ROBOT), Truth, PER_KEY, 7, counted=dropped,
                       already=sent)
        truth = client.publisher(KEYS.truth(ROBOT))
        good = valid(Truth, robot=ROBOT)
        good = type(good)(robot=ROBOT, stamp=0.0, pose=np.zeros(3),
                          landmark_ids=np.zeros(0, np.int64), landmarks=np.zeros((0, 2)))
        # afterwards, correct output: the robot at the origin is registered
        deadline_ok = False
        for _ in range(200):
            truth.put(good.to_bytes())
            if registrations.wait(lambda r: len(r) > 0, timeout=0.1):
                deadline_ok = True
                break
        assert deadline_ok and reg.poll() is None
    finally:
        out, err = stop(reg)
    assert reg.returncode == 0, err
    summary = _final(out, "registration")
    assert summary["dropped"] == sent, summary
    control_lines = [ln for ln in err.splitlines() if "CameraControl" in ln]
    assert 1 <= len(control_lines) <= 10, control_lines[:12]
    assert "Traceback" not in err


# ------------------------------------------------------------------------------ the viewer
CAMERA = "cam1"
#: random bytes, truncated msgpack, wrong roots (services/harness/fuzz.py) per key
RANDOM_PER_KEY = 36


def _viewer_payloads(kind, seed: int) -> list[bytes]:
    """Every field breaker of ``kind`` once (a dtype as a list or an unknown string, 70
    dimensions, a huge declared shape, NaN and infinity, wrong types, missing fields),
    then a random sample of the other malformed kinds."""
    import msgpack

    from slamlens.services.harness.fuzz import field_breakers

    template = valid(kind, robot=ROBOT, camera=CAMERA).to_dict()
    out = []
    for name, value in field_breakers(kind):
        broken = dict(template)
        if value is None:
            broken.pop(name, None)
        else:
            broken[name] = value
        out.append(msgpack.packb(broken, use_bin_type=True))
    rng = np.random.default_rng(seed)
    out += [p for i, p in enumerate(bad_payloads(kind, rng, RANDOM_PER_KEY * 2,
                                                 robot=ROBOT, camera=CAMERA))
            if i % 6 < 3][:RANDOM_PER_KEY]
    return out


class _ViewerStatus:
    """A viewer process's ``/api/status``, read now or polled until a condition holds."""

    def __init__(self, viewer, url: str) -> None:
        self.viewer, self.url = viewer, url

    def now(self) -> dict:
        from slamlens.services.harness.web_client import http

        code, _, body = http(self.url + "/api/status")
        assert code == 200, body
        return json.loads(body)

    def wait(self, predicate, timeout: float = 30.0) -> dict:
        deadline = time.monotonic() + timeout
        while True:  # polling the status endpoint until the condition holds
            now = self.now()
            if predicate(now):
                return now
            assert time.monotonic() < deadline, now
            assert self.viewer.poll() is None, "".join(self.viewer.err[-30:])
            time.sleep(0.01)


def _garbage_publishers(client) -> tuple[dict, dict[str, list[bytes]]]:
    """A matched publisher per input the viewer takes, and the bad payloads for each, by
    the name the viewer counts them under."""
    import dataclasses

    import zenoh

    from slamlens.common.messages import CameraFrame, Registration

    # (key, message type, the input the viewer counts it under)
    inputs = [(KEYS.tracked_by("overhead", ROBOT), Truth, "tracked"),
              (KEYS.state(ROBOT), SlamState, "state"),
              (KEYS.health(ROBOT), Health, "health"),
              (KEYS.registration(CAMERA, ROBOT), Registration, f"registration {CAMERA}"),
              (KEYS.frame(CAMERA), CameraFrame, f"frame {CAMERA}")]
    pubs, queues = {}, {}
    for seed, (key, kind, name) in enumerate(inputs, start=10):
        pubs[name] = client.session.declare_publisher(
            key, congestion_control=zenoh.CongestionControl.BLOCK)
        queues[name] = _viewer_payloads(kind, seed)
    # well-formed registrations no camera has: they once made every render fail
    reg = valid(Registration, robot=ROBOT, camera=CAMERA)
    queues[f"registration {CAMERA}"] += [
        dataclasses.replace(reg, **change).to_bytes() for change in (
            {"K": np.zeros((3, 3))}, {"K": np.diag([500.0, 500.0, 2.0])},
            {"dist": np.zeros(3)}, {"width": 10 ** 9, "height": 10 ** 9})]
    negative = msgpack.unpackb(reg.to_bytes(), raw=False)  # malformed on the wire
    negative["width"] = -640
    queues[f"registration {CAMERA}"].append(msgpack.packb(negative, use_bin_type=True))
    for name, pub in pubs.items():  # a new publisher drops what it puts before matching
        deadline = time.monotonic() + 10
        while not pub.matching_status and time.monotonic() < deadline:
            time.sleep(0.01)
        assert pub.matching_status, name
    return pubs, queues


def _send_every_payload(pubs: dict, queues: dict[str, list[bytes]],
                        status: _ViewerStatus) -> dict[str, int]:
    """Every bad payload, one per input at a time, each round once the viewer counted the
    last; how many were sent of each."""
    # a route may still drop samples for a while after its publisher matched (zenoh
    # 1.10 on a loaded machine, measured up to 0.3 s): the first bad payload of each
    # key is put again until the viewer counted it (its counts are exact and live)
    sent = dict.fromkeys(pubs, 0)
    deadline = time.monotonic() + 30
    while not all(sent.values()):
        for name in [n for n, k in sent.items() if not k]:
            pubs[name].put(queues[name][0])
        try:
            status.wait(lambda s: all(s["bad_messages"].get(n) for n in pubs), timeout=2)
        except AssertionError:
            assert time.monotonic() < deadline, f"never counted: {sent}"
        counted = status.now()["bad_messages"]
        sent = {n: counted.get(n, 0) for n in sent}
    for i in range(1, max(len(q) for q in queues.values())):
        # tracked first: it wakes nobody and is taken in with the next state or health
        for name, pub in pubs.items():
            if i < len(queues[name]):
                pub.put(queues[name][i])
                sent[name] += 1
        status.wait(lambda s: s["bad_messages"] == {k: n for k, n in sent.items() if n})
    return sent


def _a_good_state_is_drawn(pubs: dict, status: _ViewerStatus, sent: dict[str, int]) -> None:
    """A good registration, frame and state after the garbage: drawn, nothing more counted."""
    import cv2

    from slamlens.common.messages import CameraFrame, Registration
    from slamlens.services.harness.web_client import http

    width, height = 640, 480
    ok, jpeg = cv2.imencode(".jpg", np.full((height, width, 3), 90, np.uint8))
    assert ok
    pubs[f"registration {CAMERA}"].put(valid(Registration, robot=ROBOT,
                                             camera=CAMERA).to_bytes())
    pubs[f"frame {CAMERA}"].put(CameraFrame(
        camera=CAMERA, seq=3, stamp=1.0, encoding="jpeg", width=width, height=height,
        data=jpeg.tobytes()).to_bytes())
    pubs["state"].put(valid(SlamState, robot=ROBOT, seq=41).to_bytes())
    final = status.wait(lambda s: (s["state"] or {}).get("seq") == 41
                        and s["cameras"][0]["frame"] is not None
                        and s["cameras"][0]["registration"] is not None)
    assert final["bad_messages"] == sent
    code, headers, body = http(status.url + "/snapshot.png")
    assert code == 200 and body[:8] == b"\x89PNG\r\n\x1a\n"
    assert headers["X-State-Seq"] == "41"
    image = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (height, width, 3)  # the camera's picture, registered size


def test_viewer_survives_garbage_on_every_key_it_subscribes(router_endpoint, make_client,
                                                            tmp_path) -> None:
    """State, health, tracked pose, the camera's registration and frames: each malformed
    payload (and each registration no camera model can be made of) is counted under its
    input (the viewer keeps the newest state, frame and registration, so they are sent one
    at a time, each once the previous was counted), logged in a few clear lines, and a good
    state afterwards is drawn."""
    viewer = spawn("viewer", "--robot", ROBOT, "--camera", CAMERA, "--connect",
                   router_endpoint, "--http", "127.0.0.1:0", "--late-join-timeout-s", "0",
                   "--recordings-dir", str(tmp_path / "recordings"))
    pubs: dict = {}
    try:
        status = _ViewerStatus(viewer, viewer.wait_for_line("viewer ready").split()[-1])
        pubs, queues = _garbage_publishers(make_client())
        sent = _send_every_payload(pubs, queues, status)
        assert viewer.poll() is None
        assert all(n >= 60 for n in sent.values()), sent
        _a_good_state_is_drawn(pubs, status, sent)
        assert viewer.poll() is None
    finally:
        for pub in pubs.values():
            pub.undeclare()
        out, err = stop(viewer)
    assert viewer.returncode == 0, err
    assert "Traceback" not in err, err[-3000:]
    for name in sent:  # one clear line per bad message, then a summary now and then
        lines = [ln for ln in err.splitlines() if f"dropped bad {name} " in ln
                 or f"dropped bad {name}:" in ln]
        assert 1 <= len(lines) <= 5 + 3, (name, lines)
