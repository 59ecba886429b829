"""Third parties on either side of the estimator (docs/protocol.md, "Keys and messages",
"Queries", "Late join"):

* a third-party estimator publishing ``SlamState`` (and a third-party camera publishing
  ``CameraFrame`` and ``Registration``): ``slamlens viewer`` draws its features where the
  camera model puts them (``GET /snapshot.png``), and ``slamlens monitor`` answers with a
  ``Health`` for its seq;
* a third-party consumer of ``slamlens estimator``: ``get`` of the state, of
  ``state?header`` and of the health, and a consumer that joins late gets the current
  state at once.
"""

from __future__ import annotations

import json
import signal
import threading
import time
import urllib.request
from typing import Any

import kit_wire as wire
import numpy as np
from kit_driver import INPUT_COUNTS, Driver, last_state, stop_line
from kit_image import GREY, grey_jpeg, png_pixels
from kit_procs import endpoint, free_port, launch, wait_ready
from kit_run import simulate

WIDTH, HEIGHT, FOCAL = 320, 240, 200.0
#: the camera 4 m above the map origin, looking down: map (X, Y, 0) → camera (X, −Y, 4)
T_CAMERA_FROM_MAP = np.array([[1.0, 0, 0, 0], [0, -1.0, 0, 0], [0, 0, -1.0, 4.0],
                              [0, 0, 0, 1.0]])
K = np.array([[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1.0]])
#: in the lower half of the picture (the viewer's legend covers the top of it)
FEATURES = np.array([[1.8, -0.5], [-1.9, -0.6], [-1.0, -1.7], [1.1, -1.8]])
FEATURE_IDS = [3, 8, 12, 20]
EPOCH = 4242


def project(points: np.ndarray) -> np.ndarray:
    """Pixels of map points on the floor through K and T_camera_from_map (no distortion)."""
    homogeneous = np.c_[points, np.zeros(len(points)), np.ones(len(points))]
    cam = (T_CAMERA_FROM_MAP @ homogeneous.T)[:3]
    uvw = K @ cam
    return (uvw[:2] / uvw[2]).T


def third_party_state(seq: int) -> dict[str, Any]:
    """A SlamState as docs/protocol.md describes it: 4 landmarks, a small diagonal P."""
    n = len(FEATURES)
    cov = np.diag(np.r_[[1e-4, 1e-4, 1e-5], np.full(2 * n, 4e-3)])
    return {"robot": "third", "seq": seq, "stamp": 10.0 + seq, "step": "update",
            "pose": wire.array([0.0, 0.0, 0.3], "<f8"),
            "landmark_ids": wire.array(FEATURE_IDS, "<i8"),
            "landmarks": wire.array(FEATURES, "<f8"),
            "covariance": wire.array(cov.reshape(-1), "<f8"),
            "observed_ids": wire.array([], "<i8"), "new_ids": wire.array([], "<i8"),
            "epoch": EPOCH, "input_stamp": 10.0 + seq}


def registration() -> dict[str, Any]:
    return {"camera": "cam", "robot": "third", "stamp": 10.0, "K": wire.array(K, "<f8"),
            "dist": wire.array(np.zeros(5), "<f8"), "width": WIDTH, "height": HEIGHT,
            "T_camera_from_map": wire.array(T_CAMERA_FROM_MAP, "<f8"),
            "reprojection_error_px": 0.3, "epoch": EPOCH}


def frame(seq: int) -> dict[str, Any]:
    return {"camera": "cam", "seq": seq, "stamp": 10.0 + seq, "encoding": "jpeg",
            "width": WIDTH, "height": HEIGHT, "data": grey_jpeg(WIDTH, HEIGHT)}


class ThirdParty:
    """The third-party estimator and camera: publishers, and queryables answering the
    latest state and registration (late join)."""

    def __init__(self, port: int) -> None:
        self.session = wire.session(port)
        self.seq = 0
        self.keys = {"state": wire.key("third", "state"),
                     "registration": f"{wire.PREFIX}/camera/cam/registration/third",
                     "frame": f"{wire.PREFIX}/camera/cam/frame"}
        self.pubs = {name: wire.plain(self.session, k) for name, k in self.keys.items()}
        self.latest = {"registration": wire.pack(registration())}
        self.queryables = [self.session.declare_queryable(self.keys[name], self._answer(name))
                           for name in ("state", "registration")]
        self.healths: list[dict[str, Any]] = []
        self.heard = threading.Condition()
        self.health_sub = self.session.declare_subscriber(wire.key("third", "health"),
                                                          self._on_health)

    def _answer(self, name: str) -> Any:
        def reply(query: Any) -> None:
            if name in self.latest:
                query.reply(self.keys[name], self.latest[name])
        return reply

    def _on_health(self, sample: Any) -> None:
        with self.heard:
            self.healths.append(wire.unpack(sample.payload.to_bytes()))
            self.heard.notify_all()

    def publish(self) -> int:
        """The next state (and a frame, and the registration again); its seq."""
        self.seq += 1
        self.latest["state"] = wire.pack(third_party_state(self.seq))
        self.republish()
        return self.seq

    def republish(self) -> None:
        """The same state, registration and a frame again (a subscriber that was not there
        yet gets them; one that was sees the same seq twice)."""
        self.pubs["registration"].put(self.latest["registration"])
        self.pubs["frame"].put(wire.pack(frame(self.seq)))
        self.pubs["state"].put(self.latest["state"])

    def health_for(self, seqs: range, timeout: float) -> dict[str, Any] | None:
        """The first Health heard for one of ``seqs`` (waiting up to ``timeout``)."""
        def found() -> dict[str, Any] | None:
            return next((h for h in self.healths if h.get("seq") in seqs), None)

        with self.heard:
            self.heard.wait_for(lambda: found() is not None, timeout)
            return found()

    def close(self) -> None:
        self.session.close()


def snapshot(url: str) -> tuple[int, np.ndarray]:
    """``GET /snapshot.png``: (its X-State-Seq, the pixels)."""
    with urllib.request.urlopen(f"{url.rstrip('/')}/snapshot.png", timeout=30) as answer:
        return int(answer.headers.get("X-State-Seq") or -1), png_pixels(answer.read())


def _status_of(s: Any, service: str, robot: str) -> dict[str, Any] | None:
    """A service's ServiceStatus (docs/protocol.md, "The status protocol")."""
    for reply in s.get(f"{wire.PREFIX}/status/**", timeout=wire.GET_TIMEOUT_S):
        if reply.ok is not None:
            status = wire.unpack(reply.ok.payload.to_bytes())
            if status.get("service") == service and status.get("robot") == robot:
                return dict(status)
    return None


def _forged_state_is_refused(party: ThirdParty, url: str) -> None:
    """A state with seq −2⁶³ (a count is never negative) is refused and counted by the
    viewer and the monitor, not taken for a new map; the next good state is the same map."""
    forged = third_party_state(party.seq + 1)
    forged["seq"] = -(2 ** 63)
    party.pubs["state"].put(wire.pack(forged))
    deadline = time.monotonic() + 30.0
    while (_status_of(party.session, "viewer", "third") or {}).get("dropped", 0) < 1:
        assert time.monotonic() < deadline, "the viewer did not refuse the forged state"
        time.sleep(0.2)  # its status is rebuilt once a second: ask again
    seq = party.publish()
    health = party.health_for(range(seq, seq + 1), timeout=wire.PATIENCE_S)
    assert health is not None, f"no Health for seq {seq} after the forged state"
    statistics = health.get("statistics", {})
    assert statistics.get("restarts") == 0, f"the forged state made a new map: {statistics}"
    assert statistics.get("dropped", 0) >= 1, f"the monitor did not count it: {statistics}"
    while snapshot(url)[0] != seq:  # the snapshot waits for a picture of the newest inputs
        assert time.monotonic() < deadline + wire.PATIENCE_S, "the viewer never drew it"
    with urllib.request.urlopen(f"{url.rstrip('/')}/api/status", timeout=30) as answer:
        robots = json.loads(answer.read())["robots"]
    assert [r.get("restarts") for r in robots] == [0], robots


def test_third_party_estimator_drawn_and_checked(router: int) -> None:
    party = ThirdParty(router)
    party.publish()  # answered to the late joiners' get
    monitor = launch("monitor", "--robot", "third", "--connect", endpoint(router))
    viewer = launch("viewer", "--robot", "third", "--camera", "cam", "--http",
                    f"127.0.0.1:{free_port()}", "--connect", endpoint(router))
    wait_ready(monitor, "monitor ready")
    url = wait_ready(viewer, "viewer ready").split()[-1]
    try:
        wire.wait_matched(party.session, party.keys["state"])
        health = None
        for _ in range(30):  # until the monitor has subscribed: each turn waits for it
            party.publish()
            health = party.health_for(range(1, party.seq + 1), timeout=2.0)
            if health is not None:
                break
        assert health is not None, f"no Health for any of seq 1..{party.seq}"
        assert health["robot"] == "third" and health["ok"] in (True, False)
        assert health.get("verdict") in ("ok", "fault", "tuning"), health
        deadline = time.monotonic() + wire.PATIENCE_S
        while True:  # the snapshot waits for a picture of the newest inputs
            shown, pixels = snapshot(url)
            if shown == party.seq:
                break
            assert time.monotonic() < deadline, f"the viewer shows seq {shown}, not {party.seq}"
            party.republish()
        assert pixels.shape[:2] == (HEIGHT, WIDTH), pixels.shape
        rgb = pixels[..., :3].astype(int)
        background = np.all(np.abs(rgb - GREY) <= 2, axis=2)
        assert background.mean() > 0.3, "the picture is not the camera's frame"
        for (u, v), fid in zip(project(FEATURES), FEATURE_IDS, strict=True):
            x, y = int(round(u)), int(round(v))
            window = background[y - 3:y + 4, x - 3:x + 4]
            assert not window.all(), f"nothing drawn at feature {fid}'s pixel ({x}, {y})"
        _forged_state_is_refused(party, url)
    finally:
        party.close()
        viewer.stop(signal.SIGTERM)
        monitor.stop(signal.SIGTERM)


def _check_state_fields(raw: dict[str, Any], robot: str, seq: int, stamp: float) -> None:
    """A SlamState on the wire as docs/protocol.md describes it."""
    assert raw["schema"] == 1 and raw["robot"] == robot and raw["seq"] == seq, raw["seq"]
    assert raw["step"] == "update" and raw["stamp"] == stamp == raw["input_stamp"]
    assert isinstance(raw["epoch"], int) and 0 < raw["epoch"] < 2 ** 64
    assert raw["origin_stamp"] == 0.0  # the start of the first odometry step
    ids = wire.unarray(raw["landmark_ids"])
    n = len(ids)
    assert raw["landmark_ids"]["dtype"] == "<i8" and len(set(ids.tolist())) == n
    assert raw["pose"]["dtype"] == "<f8" and raw["pose"]["shape"] == [3]
    assert raw["landmarks"]["shape"] == [n, 2]
    assert raw["covariance"]["shape"] == [(3 + 2 * n) ** 2], "the covariance is sent flat"
    cov = wire.unarray(raw["covariance"]).reshape(3 + 2 * n, 3 + 2 * n)
    assert np.abs(cov - cov.T).max() <= 1e-6 * np.abs(cov).max()
    assert np.linalg.eigvalsh((cov + cov.T) / 2).min() > -1e-9
    for name in ("observed_ids", "new_ids"):
        assert raw[name]["dtype"] == "<i8" and len(raw[name]["shape"]) == 1
    k = raw.get("innovation_ids", {"shape": [0]})["shape"][0]
    if "innovations" in raw:
        assert raw["innovations"]["shape"] == [k, 2]
        assert raw["innovation_covariances"]["shape"] == [k, 2, 2]
    diagnostics = raw.get("diagnostics", {})
    missing = [f"inputs.{c}" for c in ("duplicates", "late", "lost", "waited", "reordered")
               if f"inputs.{c}" not in diagnostics]
    assert not missing, f"diagnostics lack {missing}: {diagnostics}"


def _health_for(s: Any, robot: str, seq: int) -> dict[str, Any]:
    """The monitor's Health for state ``seq``, by a ``get`` on the health key, asked again
    whenever a Health of that seq is heard (the monitor checks every state, in order)."""
    heard = threading.Event()
    sub = s.declare_subscriber(
        wire.key(robot, "health"),
        lambda sample: heard.set() if wire.unpack(sample.payload.to_bytes()).get("seq") == seq
        else None)
    try:
        deadline = time.monotonic() + wire.PATIENCE_S
        while True:
            answer = wire.get_one(s, wire.key(robot, "health"))
            health = None if answer is None else wire.unpack(answer)
            if health is not None and health.get("seq") == seq:
                return dict(health)
            assert time.monotonic() < deadline, f"no Health for seq {seq}; the last: {health}"
            heard.wait(3.0)
    finally:
        sub.undeclare()


def test_third_party_consumer(router: int) -> None:
    robot = "consumer"
    inputs = simulate(seed=41)
    est = launch("estimator", "--robot", robot, "--connect", endpoint(router))
    monitor = launch("monitor", "--robot", robot, "--connect", endpoint(router))
    wait_ready(est, "estimator ready")
    wait_ready(monitor, "monitor ready")
    driver = Driver.open(router, robot, kind="plain", timestamping=True)
    watch = wire.StateWatch(driver.session, robot)
    try:
        driver.publish(robot, inputs, numbered_from=1)
        final = last_state(watch, inputs)
        seq, stamp = len(inputs), inputs[-1].stamp
        payload = wire.get_one(driver.session, wire.key(robot, "state"))
        assert payload is not None
        raw = wire.unpack(payload)
        _check_state_fields(raw, robot, seq, stamp)
        head = wire.header(driver.session, robot)
        assert head is not None
        for name in ("schema", "robot", "seq", "stamp", "step", "epoch", "input_stamp",
                     "origin_stamp"):
            assert head[name] == raw[name], (name, head, raw[name])
        assert head["n"] == len(final["landmark_ids"])
        missing = [c for c in INPUT_COUNTS if c not in head]
        assert not missing, f"state?header lacks {missing}: {head}"
        health = _health_for(driver.session, robot, seq)
        assert health["robot"] == robot and health["stamp"] == stamp
        assert isinstance(health["ok"], bool)
        assert isinstance(health.get("violations", []), list)
        assert wire.unarray(health["suspects"]).dtype == np.dtype("<i8")
        assert health.get("verdict") in ("ok", "fault", "tuning")
        # a consumer that joins now gets the current state at once, and the token
        late = wire.session(router, timestamping=False)
        try:
            assert wire.get_one(late, wire.key(robot, "state")) == payload
            tokens = list(late.liveliness().get(wire.key(robot, "alive/estimator"),
                                                timeout=wire.GET_TIMEOUT_S))
            assert any(t.ok is not None for t in tokens), "no estimator liveliness token"
        finally:
            late.close()
    finally:
        watch.close()
        driver.close()
        code = est.stop()
        monitor.stop(signal.SIGTERM)
    stop_line(est, code)
