"""``slamlens record`` / ``play`` / ``foxglove`` with real processes on loopback.

A simulated run (sim, estimator, monitor and a viewer as processes) is recorded; the file
passes the ``mcap`` reader's validation and its Foxglove channels decode against their
schemas; played back into a fresh bus it gives the same states byte for byte and a fresh
viewer the same snapshot pixels; its inputs re-run a fresh estimator to the same map; a
Foxglove WebSocket client receives the ellipsoids of the current state; a recorder killed
with SIGKILL leaves a file that reads up to its last complete chunk.
"""

from __future__ import annotations

import asyncio
import base64
import json
import math
import struct
import time
import urllib.request
from pathlib import Path

import aiohttp
import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Channel as McapChannel
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader

from slamlens.common.keys import Keys
from slamlens.common.messages import SlamState, peek_fields
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus
from slamlens.services.harness.collect import StateCollector
from slamlens.services.harness.procs import Service, spawn, stop
from slamlens.services.recorder.reading import Recording, valid_payload
from tests.mcap_check import protobuf_class, validate

KEYS = Keys()
ROBOT = "robot1"


class Collected(StateCollector):
    """Every state on a bus by seq (as a recorder, with the history of the last 120 s)."""

    def __init__(self, endpoint: str) -> None:
        self.states: dict[int, bytes] = {}
        super().__init__(endpoint, KEYS.state(ROBOT), history_s=120.0)

    def take(self, payload: bytes) -> None:
        self.states[int(peek_fields(payload, ("seq",))["seq"])] = payload

    def wait_for(self, seq: int, timeout: float = 120.0) -> bool:
        return self.wait(lambda c: seq in c.states, timeout)


def _router() -> tuple[Service, str]:
    ep = free_tcp_endpoint()
    proc = spawn("router", "--listen", ep)
    proc.wait_for_line("router ready")
    return proc, ep


def _final(out: str, name: str, verb: str = "stopped") -> dict:
    line = next(ln for ln in out.splitlines() if ln.startswith(f"{name} {verb}: "))
    return json.loads(line.split(": ", 1)[1].split(" in ")[0])


def _inputs(out: str) -> int:
    counts = _final(out, "sim", "done")
    return counts["Odometry"] + counts["Observations"]


def _http(url: str, data: dict | None = None) -> tuple[int, dict, bytes]:
    body = None if data is None else json.dumps(data).encode()
    request = urllib.request.Request(url, data=body, method="POST" if data is not None
                                     else "GET", headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=30) as response:
        return response.status, dict(response.headers), response.read()


def _viewer(ep: str) -> tuple[Service, str]:
    proc = spawn("viewer", "--robot", ROBOT, "--http", "127.0.0.1:0", "--connect", ep)
    line = proc.wait_for_line("viewer ready")
    return proc, line.split()[-1].rstrip("/")


def _snapshot_of(url: str, seq: int, timeout: float = 60.0) -> np.ndarray:
    """The viewer's snapshot once it shows state ``seq``.

    Asked only once the run is over, so that the viewer renders for the first time then
    (it renders on demand): the path it draws and the map view's bounds (which only grow)
    are its memory of the states it happened to render, so the client compared has the
    path layer off and its first picture is of the final state.
    """
    status, _, _ = _http(url + "/api/settings?client=cmp", {"path": False})
    assert status == 200
    deadline = time.monotonic() + timeout
    while True:
        status, headers, body = _http(url + "/snapshot.png?client=cmp")
        if status == 200 and headers.get("X-State-Seq") == str(seq):
            image = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR)
            assert image is not None
            return image
        assert time.monotonic() < deadline, f"the viewer never showed seq {seq}"


def _health_seq(ep: str) -> int:
    bus = open_bus(BusSettings(connect=(ep,)))
    try:
        replies = bus.get(KEYS.health(ROBOT), timeout=2.0)
        return int(peek_fields(replies[0].payload, ("seq",))["seq"]) if replies else -1
    finally:
        bus.close()


def _wait(predicate, timeout: float = 60.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.1)
    return predicate()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> dict:
    """A recorded simulated run: the file, every live state, the live snapshot."""
    path = tmp_path_factory.mktemp("rec") / "run.mcap"
    router, ep = _router()
    est = spawn("estimator", "--robot", ROBOT, "--connect", ep)
    est.wait_for_line("estimator ready")
    mon = spawn("monitor", "--robot", ROBOT, "--connect", ep)
    mon.wait_for_line("monitor ready")
    viewer, url = _viewer(ep)
    rec = spawn("record", str(path), "--history", "120", "--connect", ep)
    rec.wait_for_line("record ready")
    live = Collected(ep)
    try:
        sim = spawn("sim", "--robot", ROBOT, "--rate", "0", "--loops", "1", "--seed", "3",
                    "--connect", ep)
        out, err = sim.communicate(timeout=300)
        assert sim.returncode == 0 and "all applied" in out, out + err
        inputs = _inputs(out)
        assert live.wait_for(inputs)
        assert _wait(lambda: _health_seq(ep) >= inputs)
        snapshot = _snapshot_of(url, inputs)
    finally:
        rec_out, rec_err = stop(rec)
        live.close()
        for proc in (viewer, mon, est, router):
            stop(proc)
    assert rec.returncode == 0, rec_err
    summary = _final(rec_out, "record")
    return {"path": path, "states": dict(live.states), "inputs": inputs,
            "snapshot": snapshot, "summary": summary}


def test_the_recording_passes_mcap_validation_and_its_foxglove_channels_decode(
        recorded) -> None:
    path, inputs = recorded["path"], recorded["inputs"]
    assert recorded["summary"]["lost"] == 0 and recorded["summary"]["bad"] == 0
    topics = validate(path)
    state_key = KEYS.state(ROBOT)
    # one channel per key, topic = key, the payloads byte for byte, in order
    states = [m.data for m, _ in topics[state_key]]
    assert states == [recorded["states"][seq] for seq in range(inputs + 1)]
    for key in ("odometry", "observations", "truth", "health"):
        assert topics[KEYS.robot(ROBOT, key)], key
    with path.open("rb") as f:
        channels = make_reader(f).get_summary().channels.values()
        meta = {c.topic: c for c in channels}
    assert meta[state_key].message_encoding == "msgpack"
    assert meta[state_key].metadata["slamlens.message"] == "SlamState"
    log_times = [m.log_time for m, _ in topics[state_key]]
    assert log_times == sorted(log_times)
    # publish time = the Zenoh timestamp: the estimator's clock, before the recorder got it
    for m, _ in topics[state_key]:
        assert 0 <= m.log_time - m.publish_time < 60e9
    # the scene: the last one is the final state, with one ellipsoid per pair
    final = SlamState.from_bytes(recorded["states"][inputs])
    scenes = topics[f"/foxglove/robot/{ROBOT}/scene"]
    last = {e.id: e for e in scenes[-1][1].entities}
    n = final.n
    assert n >= 2
    assert len(last[f"{ROBOT}/ellipsoids"].spheres) == n * (n - 1) // 2
    assert len(last[f"{ROBOT}/features"].cylinders) == n
    meta_of = {kv.key: kv.value for kv in last[f"{ROBOT}/robot"].metadata}
    assert meta_of["seq"] == str(inputs)
    cone = last[f"{ROBOT}/robot"].cylinders[0]
    assert math.isclose(cone.pose.position.x, final.pose[0]) and \
        math.isclose(cone.pose.position.y, final.pose[1])
    sphere = last[f"{ROBOT}/ellipsoids"].spheres[0]
    assert sphere.color.r > 0.8 and sphere.color.g < 0.2 and sphere.color.b < 0.2  # red
    lines = last[f"{ROBOT}/pairs"].lines[0]
    assert len(lines.points) == 2 * (n * (n - 1) // 2)
    covariance = topics[f"/foxglove/robot/{ROBOT}/covariance"][-1][1]
    assert covariance["seq"] == inputs and covariance["n"] == n
    assert covariance["pd_min_m"] <= covariance["pd_mean_m"] <= covariance["pd_max_m"]
    health = topics[f"/foxglove/robot/{ROBOT}/health"][-1][1]
    assert health["seq"] == inputs and health["ok"] is True
    assert any(k.startswith("nees") for k in health["statistics"]), health


def test_played_back_the_states_are_the_same_bytes_and_the_snapshot_the_same_pixels(
        recorded) -> None:
    inputs = recorded["inputs"]
    router, ep = _router()
    viewer, url = _viewer(ep)
    played = Collected(ep)
    try:
        play = spawn("play", str(recorded["path"]), "--rate", "0", "--connect", ep)
        out, err = play.communicate(timeout=300)
        assert play.returncode == 0, err
        assert "play done" in out, out
        assert played.wait_for(inputs)
        snapshot = _snapshot_of(url, inputs)
    finally:
        played.close()
        stop(viewer)
        stop(router)
    assert played.states == recorded["states"]
    assert snapshot.shape == recorded["snapshot"].shape
    assert np.array_equal(snapshot, recorded["snapshot"]), \
        f"{int((snapshot != recorded['snapshot']).any(axis=2).sum())} pixels differ"


def test_inputs_only_re_runs_a_fresh_estimator_to_the_same_map_and_refuses_to_mix(
        recorded) -> None:
    inputs = recorded["inputs"]
    live_final = SlamState.from_bytes(recorded["states"][inputs])
    router, ep = _router()
    est = spawn("estimator", "--robot", ROBOT, "--connect", ep)
    est.wait_for_line("estimator ready")
    try:
        mixing = spawn("play", str(recorded["path"]), "--connect", ep)
        _, err = mixing.communicate(timeout=60)
        assert mixing.returncode == 1
        assert "an estimator is live for robot 'robot1'" in err, err
        play = spawn("play", str(recorded["path"]), "--inputs-only", "--rate", "0",
                     "--connect", ep)
        out, err = play.communicate(timeout=300)
        assert play.returncode == 0 and "all applied by the estimator" in out, out + err
        counts = _final(out, "play", "done")
        assert counts["Odometry"] + counts["Observations"] == inputs
        assert "SlamState" not in counts
        bus = open_bus(BusSettings(connect=(ep,)))
        try:
            final = SlamState.from_bytes(bus.get(KEYS.state(ROBOT), timeout=5.0)[0].payload)
        finally:
            bus.close()
        again = spawn("play", str(recorded["path"]), "--inputs-only", "--connect", ep)
        _, err = again.communicate(timeout=60)
        assert again.returncode == 1 and "not fresh" in err, err
    finally:
        stop(est)
        stop(router)
    assert final.seq == live_final.seq
    assert final.epoch != live_final.epoch  # a new map, from the same inputs
    np.testing.assert_array_equal(final.landmark_ids, live_final.landmark_ids)
    np.testing.assert_array_equal(final.covariance, live_final.covariance)
    np.testing.assert_array_equal(final.pose, live_final.pose)


def test_the_control_page_pauses_and_seeks(recorded) -> None:
    router, ep = _router()
    play = spawn("play", str(recorded["path"]), "--paused", "--connect", ep)
    try:
        url = play.wait_for_line("play control").split()[-1].rstrip("/")
        play.wait_for_line("play ready")
        status = json.loads(_http(url + "/api/status")[2])
        assert status["paused"] is True and status["published"] == 0
        half = round(status["duration_s"] / 2, 3)
        assert half > 0.1
        with urllib.request.urlopen(urllib.request.Request(
                url + f"/api/seek?t={half}", method="POST"), timeout=10) as r:
            status = json.loads(r.read())
        assert math.isclose(status["position_s"], half) and status["paused"] is True
        assert status["published"] == 0
        try:
            urllib.request.urlopen(urllib.request.Request(url + "/api/seek?t=x",
                                                          method="POST"), timeout=10)
            raise AssertionError("a bad seek was accepted")
        except urllib.error.HTTPError as exc:
            assert exc.code == 400 and "expected a number" in json.loads(exc.read())["error"]
        with urllib.request.urlopen(urllib.request.Request(
                url + "/api/resume", method="POST"), timeout=10) as r:
            assert json.loads(r.read())["paused"] is False
        assert _wait(lambda: json.loads(_http(url + "/api/status")[2])["published"] > 0)
        page = _http(url + "/")[2].decode()
        assert "/api/seek" in page and "/api/pause" in page
    finally:
        out, _ = stop(play)
        stop(router)
    assert "play stopped" in out


async def _foxglove_scene(url: str, *, param: tuple[str, object] | None = None) -> list:
    """Connect as a Foxglove client, subscribe to the scene, return the decoded updates
    (two if ``param`` is set: before and after setting that parameter)."""
    async with aiohttp.ClientSession() as session, session.ws_connect(
            url, protocols=["foxglove.sdk.v1"], timeout=aiohttp.ClientWSTimeout(
                ws_close=10)) as ws:
        assert ws.protocol == "foxglove.sdk.v1"
        channels: dict[int, dict] = {}
        info = None
        scene_class = None
        updates: list = []
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            msg = await ws.receive(timeout=30)
            if msg.type == aiohttp.WSMsgType.TEXT:
                data = json.loads(msg.data)
                if data["op"] == "serverInfo":
                    info = data
                elif data["op"] == "advertise":
                    for ch in data["channels"]:
                        channels[ch["id"]] = ch
                        if ch["topic"] == f"/foxglove/robot/{ROBOT}/scene":
                            assert ch["encoding"] == "protobuf"
                            assert ch["schemaName"] == "foxglove.SceneUpdate"
                            scene_class = protobuf_class(ch["schemaName"],
                                                         base64.b64decode(ch["schema"]))
                            await ws.send_json({"op": "subscribe", "subscriptions": [
                                {"id": 7, "channelId": ch["id"]}]})
            elif msg.type == aiohttp.WSMsgType.BINARY:
                opcode, sub_id, _log_time = struct.unpack_from("<BIQ", msg.data)
                if opcode == 1 and sub_id == 7:
                    assert scene_class is not None
                    updates.append(scene_class.FromString(msg.data[13:]))
                    if param is None or len(updates) == 2:
                        assert info is not None and "parameters" in info["capabilities"]
                        return updates
                    if len(updates) == 1:
                        await ws.send_json({"op": "setParameters", "parameters": [
                            {"name": param[0], "value": param[1]}]})
            else:
                raise AssertionError(f"the server closed the connection: {msg}")
        raise AssertionError("no scene received")


def test_a_foxglove_client_receives_the_ellipsoids_of_the_current_state() -> None:
    router, ep = _router()
    est = spawn("estimator", "--robot", ROBOT, "--connect", ep)
    est.wait_for_line("estimator ready")
    try:
        sim = spawn("sim", "--robot", ROBOT, "--rate", "0", "--loops", "1", "--seed", "3",
                    "--connect", ep)
        out, err = sim.communicate(timeout=300)
        assert sim.returncode == 0 and "all applied" in out, out + err
        inputs = _inputs(out)
        fox = spawn("foxglove", "--robot", ROBOT, "--port", "0", "--connect", ep)
        url = fox.wait_for_line("foxglove ready").split()[-1]
        assert url.startswith("ws://127.0.0.1:")
        first, second = asyncio.run(_foxglove_scene(url, param=("mode", "minmeanmax")))
    finally:
        fox_out, _ = stop(fox)
        stop(est)
        stop(router)
    entities = {e.id: e for e in first.entities}
    meta = {kv.key: kv.value for kv in entities[f"{ROBOT}/robot"].metadata}
    assert meta["seq"] == str(inputs) and meta["mode"] == "all"
    n = len(entities[f"{ROBOT}/features"].cylinders)
    assert n >= 2 and len(entities[f"{ROBOT}/ellipsoids"].spheres) == n * (n - 1) // 2
    for sphere in entities[f"{ROBOT}/ellipsoids"].spheres:
        assert sphere.size.x >= sphere.size.y > 0 and math.isclose(sphere.size.y,
                                                                   sphere.size.z)
    entities = {e.id: e for e in second.entities}
    assert {kv.key: kv.value for kv in entities[f"{ROBOT}/robot"].metadata}["mode"] == \
        "minmeanmax"
    spheres = len(entities[f"{ROBOT}/ellipsoids"].spheres)
    assert spheres % 3 == 0 and 0 < spheres < n * (n - 1) // 2  # min, mean, max per pair
    assert "foxglove stopped" in fox_out


def test_a_recorder_killed_with_sigkill_leaves_a_file_readable_to_its_last_chunk(
        tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    router, ep = _router()
    est = spawn("estimator", "--robot", ROBOT, "--connect", ep)
    est.wait_for_line("estimator ready")
    rec = spawn("record", str(path), "--history", "120", "--flush-s", "0.2", "--chunk-kb",
                "64", "--connect", ep)
    rec.wait_for_line("record ready")
    sim = spawn("sim", "--robot", ROBOT, "--rate", "0", "--loops", "40", "--seed", "3",
                "--connect", ep)
    try:
        # kill it in the middle of the run, once a good part is on disk
        assert _wait(lambda: path.exists() and path.stat().st_size > 2_000_000, timeout=120)
        assert sim.poll() is None, "the run ended before the recorder was killed"
        rec.kill()
        rec.wait(10)
    finally:
        stop(sim)
        stop(est)
        stop(router)
    assert rec.returncode == -9
    with path.open("rb") as f:  # no footer: it was killed
        with pytest.raises(Exception, match="exceeds limit|footer|magic|EndOfFile"):
            make_reader(f).get_summary()
    # the mcap reader reads every complete chunk, CRCs checked, then meets the cut (the
    # reader does not say "truncated": a short chunk reads as garbage or a bad CRC)
    messages, msgpack_channels = [], set()
    with path.open("rb") as f:
        try:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, McapMessage):
                    messages.append(record)
                elif isinstance(record, McapChannel) and record.message_encoding == "msgpack":
                    msgpack_channels.add(record.id)
        except Exception:
            pass
    assert len(messages) > 1000
    assert all(valid_payload(m.data) == "" for m in messages
               if m.channel_id in msgpack_channels)
    recording = Recording(path)
    assert recording.truncated
    seqs = [int(peek_fields(m.data, ("seq",))["seq"]) for m in
            recording.messages(topics={KEYS.state(ROBOT)})]
    assert len(seqs) > 300 and seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    assert recording.bad.total == 0


def _recorded_stamps(path: Path, topics: tuple[str, ...]) -> list[float]:
    """The ``stamp`` of every message on ``topics`` in the file's order (what is complete
    of a file still being written)."""
    stamps: list[float] = []
    channels: dict[int, str] = {}
    try:
        with path.open("rb") as f:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, McapChannel):
                    channels[record.id] = record.topic
                elif isinstance(record, McapMessage) and channels.get(record.channel_id) in topics:
                    stamps.append(peek_fields(record.data, ("stamp",))["stamp"])
    except Exception:  # the chunk being written: what came before it is what there is
        pass
    return stamps


def test_a_robots_inputs_are_recorded_in_the_order_they_were_published(tmp_path) -> None:
    """A third-party driver (plain zenoh-python, no input_seq) publishing as fast as it can
    beside two CPU burners: ``record --robot R`` subscribes to the robot's keys with one
    key expression, so its file holds odometry and observations in publication order —
    what ``play --inputs-only`` then publishes again (docs/recording.md)."""
    import subprocess
    import sys

    import zenoh

    from slamlens.common.messages import Observations, Odometry

    path = tmp_path / "order.mcap"
    topics = (KEYS.odometry(ROBOT), KEYS.observations(ROBOT))
    router, ep = _router()
    burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    rec = spawn("record", str(path), "--robot", ROBOT, "--connect", ep, "--no-foxglove",
                "--flush-s", "0.2", "--chunk-kb", "64")
    rec.wait_for_line("record ready")
    conf = zenoh.Config()
    for key, value in (("mode", '"client"'), ("connect/endpoints", f'["{ep}"]'),
                       ("scouting/multicast/enabled", "false"),
                       ("timestamping/enabled", "true")):
        conf.insert_json5(key, value)
    session = zenoh.open(conf)
    count = 4000
    try:
        pubs = [session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
                for k in topics]
        for pub in pubs:  # the recorder's subscription has reached this publisher
            assert _wait(lambda pub=pub: pub.matching_status.matching)
        for i in range(count):
            msg = (Odometry(robot=ROBOT, stamp=float(i), dt=0.01, v=0.1, w=0.0) if i % 2 == 0
                   else Observations(robot=ROBOT, stamp=float(i), ids=[1], ranges=[1.0],
                                     bearings=[0.0]))
            pubs[i % 2].put(msg.to_bytes())
        assert _wait(lambda: len(_recorded_stamps(path, topics)) >= count, timeout=120.0)
    finally:
        session.close()
        rec_out, rec_err = stop(rec)
        for b in burners:
            b.kill()
            b.wait()
        stop(router)
    assert rec.returncode == 0, rec_err
    assert _recorded_stamps(path, topics) == [float(i) for i in range(count)]
