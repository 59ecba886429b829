"""``slamlens summary`` over real Zenoh on loopback (docs/remote_viewers.md):
the answer is the newest state's summary, a pull waits for a newer state, bad parameters
get an error reply and the service goes on, and the process exits cleanly."""

from __future__ import annotations

import signal
import threading
import time

import numpy as np

from slamlens.common.keys import Keys
from slamlens.common.messages import StateSummary
from slamlens.common.summary import SummaryQuery
from slamlens.common.summary_pull import SummaryPuller, error_text
from slamlens.services.harness.procs import spawn, stop, wait_for_line
from slamlens.services.slam.settings import SummarySettings
from slamlens.services.slam.summary_service import SummaryService
from tests.routes import put_until_seen
from tests.unit.test_summary import consistent_state, oracle_pd

KEYS = Keys()


def _service(make_client, **settings) -> tuple[SummaryService, threading.Event,
                                                threading.Thread]:
    bus = make_client()
    service = SummaryService(bus, keys=KEYS, robot="r1",
                             settings=SummarySettings(robot="r1", **settings))
    halt = threading.Event()
    thread = threading.Thread(target=service.run, args=(halt,), daemon=True)
    thread.start()
    return service, halt, thread


def _publish(make_client):
    bus = make_client()
    pub = bus.publisher(KEYS.state("r1"), cache=4)
    assert bus.wait_for_subscriber(KEYS.state("r1"), timeout=30.0)
    return bus, pub


def _wait_received(service: SummaryService, count: int, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while service.received < count:
        assert time.monotonic() < deadline, f"only {service.received} states arrived"
        time.sleep(0.01)


def test_the_answer_is_the_newest_state_s_summary(make_client) -> None:
    service, halt, thread = _service(make_client)
    try:
        _, pub = _publish(make_client)
        first = consistent_state(30, seq=1, seed=1).to_bytes()
        put_until_seen(lambda: pub.put(first), lambda: service.received >= 1,
                       what="the first state")
        for seq in (2, 3):
            pub.put(consistent_state(30, seq=seq, seed=seq).to_bytes())
        _wait_received(service, 3)
        client = make_client()
        replies = client.get(KEYS.summary("r1") + "?what=clusters;threshold=0.6",
                             timeout=30.0)
        assert len(replies) == 1
        s = StateSummary.from_bytes(replies[0].payload)
        state = consistent_state(30, seq=3, seed=3)
        assert (s.seq, s.what, s.n) == (3, "clusters", 30)
        assert s.state_bytes == len(state.to_bytes())
        scale = float(np.abs(state.covariance).max())
        for pair, Pd in zip(s.max_pair, s.max_Pd, strict=True):
            np.testing.assert_allclose(Pd, oracle_pd(state.covariance, *map(int, pair)),
                                       atol=1e-5 * scale)
        # only the state a query needed was decoded, not each of the three published
        assert service.decoded == 1
    finally:
        halt.set()
        thread.join(5.0)


def test_a_pull_waits_for_a_newer_state_and_gets_the_newest(make_client) -> None:
    service, halt, thread = _service(make_client, hold_s=20.0)
    try:
        _, pub = _publish(make_client)
        first = consistent_state(12, seq=1).to_bytes()
        put_until_seen(lambda: pub.put(first), lambda: service.received >= 1,
                       what="the first state")
        got: list[int] = []
        puller = SummaryPuller(make_client(), KEYS.summary("r1"),
                               SummaryQuery(what="blocks"),
                               lambda payload, _t: got.append(StateSummary.from_bytes(
                                   payload).seq), timeout_s=30.0)
        assert puller.pull_once() is not None and got == [1]
        assert "after=1" in puller.selector() and "epoch=7" in puller.selector()
        answer: list[bytes | None] = []
        waiting = threading.Thread(target=lambda: answer.append(puller.pull_once()))
        waiting.start()
        deadline = time.monotonic() + 10.0
        while not service._pending:  # the query is held by the service, not answered
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert not answer
        for seq in (2, 3):
            pub.put(consistent_state(12, seq=seq).to_bytes())
        waiting.join(30.0)
        assert answer and answer[0] is not None
        assert got[-1] in (2, 3)  # the newest there was when it answered
    finally:
        halt.set()
        thread.join(5.0)


def test_bad_parameters_get_an_error_reply_and_the_service_goes_on(make_client) -> None:
    service, halt, thread = _service(make_client)
    try:
        client = make_client()
        errors: list[bytes] = []
        assert client.get(KEYS.summary("r1") + "?what=everything", timeout=30.0,
                          errors=errors) == []
        assert len(errors) == 1 and "what='everything'" in error_text(errors[0])
        errors.clear()
        assert client.get(KEYS.summary("r1") + "?what=blocks", timeout=30.0,
                          errors=errors) == []
        assert "no state of robot r1 yet" in error_text(errors[0])
        _, pub = _publish(make_client)
        first = consistent_state(12, seq=5).to_bytes()
        put_until_seen(lambda: pub.put(first), lambda: service.received >= 1,
                       what="the first state")
        errors.clear()
        assert client.get(KEYS.summary("r1") + "?feature=999", timeout=30.0,
                          errors=errors) == []
        assert "feature 999 is not in the map" in error_text(errors[0])
        replies = client.get(KEYS.summary("r1") + "?what=blocks", timeout=30.0)
        assert StateSummary.from_bytes(replies[0].payload).seq == 5
        assert service.refused == 3 and service.drops.total == 3
    finally:
        halt.set()
        thread.join(5.0)


def test_the_summary_process_answers_and_exits_cleanly(router_endpoint, make_client) -> None:
    proc = spawn("summary", "--robot", "r1", "--connect", router_endpoint)
    try:
        wait_for_line(proc, "summary ready", timeout=60.0)
        _, pub = _publish(make_client)
        pub.put(consistent_state(20, seq=4).to_bytes())
        client = make_client()
        deadline = time.monotonic() + 30.0
        while True:  # the state may reach it just after the query: ask until it has one
            replies = client.get(KEYS.summary("r1") + "?what=clusters", timeout=30.0)
            if replies:
                break
            assert time.monotonic() < deadline, "no summary from the process"
            time.sleep(0.1)
        assert StateSummary.from_bytes(replies[0].payload).seq == 4
        start = time.monotonic()
        out, _ = stop(proc, sig=signal.SIGINT)
        assert time.monotonic() - start < 2.0
        assert proc.returncode == 0
        assert "summary stopped:" in out and '"answered": 1' in out
    finally:
        if proc.poll() is None:
            proc.kill()


def test_malformed_states_are_dropped_counted_and_the_service_goes_on(make_client) -> None:
    service, halt, thread = _service(make_client)
    try:
        _, pub = _publish(make_client)
        client = make_client()
        pub.put(b"\x93not a state")
        _wait_received(service, 1)
        errors: list[bytes] = []
        assert client.get(KEYS.summary("r1") + "?what=blocks", timeout=30.0,
                          errors=errors) == []
        assert "no state of robot r1 yet" in error_text(errors[0])
        other = consistent_state(5, seq=2)
        pub.put(type(other)(**{**{f: getattr(other, f) for f in (
            "seq", "stamp", "step", "pose", "landmark_ids", "landmarks", "covariance")},
            "robot": "someone-else"}).to_bytes())
        _wait_received(service, 2)
        errors.clear()
        assert client.get(KEYS.summary("r1") + "?what=blocks", timeout=30.0,
                          errors=errors) == []
        assert "no state of robot r1 yet" in error_text(errors[0])
        assert service.drops.counts["SlamState"] == 1 and service.drops.counts["robot"] == 1
        pub.put(consistent_state(5, seq=3).to_bytes())
        _wait_received(service, 3)
        replies = client.get(KEYS.summary("r1") + "?what=blocks", timeout=30.0)
        assert StateSummary.from_bytes(replies[0].payload).seq == 3
    finally:
        halt.set()
        thread.join(5.0)
