"""``slamlens rerun`` and ``slamlens record``'s Foxglove channels, with real processes on
loopback: a simulated run (router, estimator, monitor, the synthetic overhead camera with
its registration, the simulator) watched at once by a recorder writing MCAP and a Foxglove
layout, a Rerun sink saving an ``.rrd``, and a second Rerun sink streaming to Rerun's own
gRPC proxy (``rerun --serve-grpc --save``, the CLI of the SDK). The ``.rrd`` files are read
back with Rerun's own reader; the layout's topics are held to the recording's channels.
"""

from __future__ import annotations

import json
import math
import signal
import sys
import time
import warnings

import numpy as np
import pytest
from rerun.error_utils import RerunWarning

from slamlens.common.keys import Keys
from slamlens.common.messages import Registration, ServiceStatus, SlamState, peek_fields
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus
from slamlens.services.harness.collect import StateCollector
from slamlens.services.harness.procs import Service, Started, spawn, stop
from slamlens.services.recorder.foxglove_layout import SHIPPED, layout
from tests.mcap_check import layout_topics, validate
from tests.rrd_check import read_rrd, stores

KEYS = Keys()
ROBOT, CAMERA = "robot1", "overhead"
#: Rerun's own command line, from the SDK: its binary, exec'd with SIGINT at its default and
#: unblocked (``python -m rerun`` runs the binary as a child and, when the suite's process
#: has SIGINT ignored or blocked — inherited by children — never passes Ctrl-C on: a
#: fresh-clone CI run waited 180 s for it)
RERUN_CLI = [sys.executable, "-c",
             "import os, signal, sys, rerun_cli; "
             "signal.signal(signal.SIGINT, signal.SIG_DFL); "
             "signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT}); "
             "exe = os.path.join(os.path.dirname(rerun_cli.__file__), 'rerun'); "
             "os.execv(exe, [exe, *sys.argv[1:]])"]


class Collected(StateCollector):
    def __init__(self, endpoint: str) -> None:
        self.states: dict[int, bytes] = {}
        super().__init__(endpoint, KEYS.state(ROBOT), history_s=120.0)

    def take(self, payload: bytes) -> None:
        self.states[int(peek_fields(payload, ("seq",))["seq"])] = payload


def _final(out: str, name: str, verb: str = "stopped") -> dict:
    line = next(ln for ln in out.splitlines() if ln.startswith(f"{name} {verb}: "))
    return json.loads(line.split(": ", 1)[1].split(" in ")[0])


def _wait(predicate, timeout: float = 120.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.2)
    return predicate()


def _sink_statuses(bus) -> list[ServiceStatus]:
    return [ServiceStatus.from_bytes(r.payload)
            for r in bus.get(f"{KEYS.prefix}/status/*/rerun/*", timeout=2.0)]


def _free_port() -> int:
    return int(free_tcp_endpoint().rsplit(":", 1)[1])


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> dict:
    d = tmp_path_factory.mktemp("exports")
    files = {"rrd": d / "run.rrd", "mcap": d / "run.mcap", "layout": d / "robot1.json",
             "proxy_rrd": d / "proxy.rrd"}
    ep = free_tcp_endpoint()
    started = Started()

    def start(*args: str, ready: str) -> Service:
        return started.add(spawn(*args, "--connect", ep) if args[0] != "router"
                           else spawn(*args), ready=ready)

    port = _free_port()
    proxy = Service([*RERUN_CLI, "--serve-grpc", "--bind", "127.0.0.1", "--port",
                     str(port), "--save", str(files["proxy_rrd"])], env={"CI": "1"})
    start("router", "--listen", ep, ready="router ready")
    start("estimator", "--robot", ROBOT, ready="estimator ready")
    start("monitor", "--robot", ROBOT, ready="monitor ready")
    start("registration", "--camera", CAMERA, "--robot", ROBOT, "--source", "synthetic",
          "--fps", "20", ready="registration ready")
    rec = start("record", str(files["mcap"]), "--robot", ROBOT, "--camera", CAMERA,
                "--layout", str(files["layout"]), "--history", "120", ready="record ready")
    sink = start("rerun", "--robot", ROBOT, "--camera", CAMERA, "--save", str(files["rrd"]),
                 ready="rerun ready")
    streamer = start("rerun", "--robot", ROBOT, "--camera", CAMERA, "--viewer",
                     f"rerun+http://127.0.0.1:{port}/proxy", ready="rerun ready")
    live = Collected(ep)
    bus = open_bus(BusSettings(connect=(ep,)))
    try:
        sim = spawn("sim", "--robot", ROBOT, "--rate", "2", "--loops", "1", "--seed", "3",
                    "--hold", "3", "--connect", ep)
        out, err = sim.communicate(timeout=300)
        assert sim.returncode == 0, out + err
        counts = _final(out, "sim", "done")
        inputs = counts["Odometry"] + counts["Observations"]
        assert _wait(lambda: inputs in live.states)
        registration = bus.get(KEYS.registration(CAMERA, ROBOT), timeout=5.0)
        assert registration, "the camera never registered"
        # both sinks have drawn the final state and logged the camera
        assert _wait(lambda: [(s.counts["seq"], s.counts["cameras"] >= 1)
                              for s in _sink_statuses(bus)] == [(inputs, True)] * 2), \
            [s.counts for s in _sink_statuses(bus)]
        health_seq = lambda: int(peek_fields(  # noqa: E731
            bus.get(KEYS.health(ROBOT), timeout=2.0)[-1].payload, ("seq",))["seq"])
        assert _wait(lambda: health_seq() >= inputs)
    finally:
        bus.close()
        live.close()
        outputs = {name: stop(proc)[0] for name, proc in
                   (("rerun", sink), ("streamer", streamer), ("record", rec))}
        started.stop_all()
        proxy.send_signal(signal.SIGINT)  # Rerun's CLI finishes its file on Ctrl-C
        proxy.wait(60)
    return {**files, "inputs": inputs, "states": dict(live.states),
            "registration": Registration.from_bytes(registration[-1].payload),
            "summaries": {name: _final(text, "rerun") for name, text in outputs.items()
                          if name != "record"}}


def _check_final_picture(rows: dict, final: SlamState) -> None:
    """The final state's picture in a recording read back: one ellipsoid per pair at the
    pairs' midpoints, the features and the robot where the state has them."""
    n = final.n

    def at_final(entity: str) -> dict:
        hits = [r for r in rows[f"/world/{ROBOT}/{entity}"] if r.get("seq") == final.seq]
        assert hits, f"{entity}: no row at seq {final.seq}"
        return hits[-1]

    ell = at_final("ellipsoids")
    assert ell["stamp"] == pytest.approx(final.stamp)
    centres = np.array(ell["Ellipsoids3D:centers"])
    assert len(centres) == n * (n - 1) // 2 == len(ell["Ellipsoids3D:half_sizes"])
    ii, jj = np.triu_indices(n, k=1)
    xy = final.landmarks
    np.testing.assert_allclose(centres[:, :2], 0.5 * (xy[ii] + xy[jj]), atol=1e-6)
    np.testing.assert_allclose(centres[:, 2], 0.0, atol=1e-12)
    features = at_final("features")
    np.testing.assert_allclose(np.array(features["Points3D:positions"])[:, :2], xy, atol=1e-6)
    assert features["Points3D:labels"] == [str(i) for i in final.landmark_ids.tolist()]
    robot = at_final("robot")
    np.testing.assert_allclose(robot["Points3D:positions"][0][:2], final.pose[:2], atol=1e-6)
    assert len(at_final("pairs")["LineStrips3D:strips"]) == n * (n - 1) // 2


def test_the_saved_rrd_holds_the_run_as_rerun_reads_it(exported) -> None:
    rows = read_rrd(exported["rrd"])
    assert stores(exported["rrd"]) == (1, 1)  # the recording and its blueprint
    final = SlamState.from_bytes(exported["states"][exported["inputs"]])
    assert final.n >= 2
    _check_final_picture(rows, final)
    r = f"/world/{ROBOT}"
    expected = {f"{r}/{leaf}" for leaf in ("ellipsoids", "pairs", "features", "suspects",
                                           "robot", "path", "truth/robot", "truth/path",
                                           "truth/features")}
    expected |= {f"/world/camera/{CAMERA}", f"/world/camera/{CAMERA}/image", "/world",
                 f"/log/{ROBOT}"}
    expected |= {f"/plots/{ROBOT}/{s}" for s in ("nees/value", "nees/lo", "nees/hi",
                                                 "nis/value", "pd/min", "pd/mean", "pd/max")}
    assert expected <= set(rows), expected - set(rows)
    # the camera: where the registration puts it, K, and JPEG frames on the robot's clock
    reg = exported["registration"]
    pose = rows[f"/world/camera/{CAMERA}"][-1]
    T = reg.T_camera_from_map
    np.testing.assert_allclose(pose["Transform3D:translation"][0], T[:3, 3], atol=1e-5)
    np.testing.assert_allclose(np.array(pose["Transform3D:mat3x3"][0]).reshape(3, 3).T,
                               T[:3, :3], atol=1e-6)
    image_rows = rows[f"/world/camera/{CAMERA}/image"]
    pinhole = next(r for r in image_rows if "Pinhole:image_from_camera" in r)
    np.testing.assert_allclose(np.array(pinhole["Pinhole:image_from_camera"][0])
                               .reshape(3, 3).T, reg.K, rtol=1e-6)
    frames = [r for r in image_rows if "EncodedImage:blob" in r]
    assert len(frames) > 10
    assert all(bytes(r["EncodedImage:blob"][0][:3]) == b"\xff\xd8\xff" for r in frames)
    assert all(0.0 <= r["stamp"] <= final.stamp + 1.0 for r in frames)
    # the plots: NEES inside its band at the end of a consistent run; the verdict said
    nees = [r for r in rows[f"/plots/{ROBOT}/nees/value"] if "seq" in r]
    assert len(nees) > 10
    texts = [r["TextLog:text"][0] for r in rows[f"/log/{ROBOT}"] if "TextLog:text" in r]
    assert texts and texts[0].startswith("verdict at seq")
    truth = rows[f"{r}/truth/robot"][-1]["Points3D:positions"][0]
    assert math.dist(truth[:2], final.pose[:2]) < 0.5  # the estimate near the truth
    summary = exported["summaries"]["rerun"]
    assert summary["bad"] == 0 and summary["drawn"] >= 10, summary


def test_a_sink_streams_the_same_picture_to_rerun_s_own_proxy(exported) -> None:
    with warnings.catch_warnings():  # the CLI's file has no footer (a plain stream)
        warnings.simplefilter("ignore", RerunWarning)
        rows = read_rrd(exported["proxy_rrd"])
    final = SlamState.from_bytes(exported["states"][exported["inputs"]])
    _check_final_picture(rows, final)
    assert exported["summaries"]["streamer"]["bad"] == 0


def test_the_layout_names_only_channels_the_recording_has(exported) -> None:
    written = json.loads(exported["layout"].read_text(encoding="utf-8"))
    assert written == layout(ROBOT, (CAMERA,)) == json.loads(SHIPPED.read_text("utf-8"))
    topics = validate(exported["mcap"])
    named = layout_topics(written)
    assert named <= set(topics), named - set(topics)
    final = SlamState.from_bytes(exported["states"][exported["inputs"]])
    transform = topics[f"/foxglove/robot/{ROBOT}/transform"][-1][1]
    assert transform.child_frame_id == f"{ROBOT}/base_link"
    assert (transform.translation.x, transform.translation.y) == pytest.approx(
        tuple(final.pose[:2]))
    path = topics[f"/foxglove/robot/{ROBOT}/path"][-1][1]
    assert len(path.poses) > 10
    last = path.poses[-1]
    assert (last.position.x, last.position.y) == pytest.approx(tuple(final.pose[:2]))
    truth = {e.id: e for e in topics[f"/foxglove/robot/{ROBOT}/truth"][-1][1].entities}
    assert {f"{ROBOT}/truth/robot", f"{ROBOT}/truth/features", f"{ROBOT}/truth/path"} <= set(
        truth)
    assert len(truth[f"{ROBOT}/truth/features"].cylinders) >= final.n
