"""The bus over real Zenoh on loopback: ordering, latest-wins, get, liveliness, shutdown."""

from __future__ import annotations

import subprocess
import sys
import time

from slamlens.common.session import BusSettings, build_config
from tests.routes import put_until_seen


def _wait(predicate, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


def test_one_channel_for_two_keys_gets_everything_each_key_in_order(make_client) -> None:
    """A burst on two keys: nothing lost (what congestion drops is recovered from the
    publishers' caches) and each key in its own order. The order *across* keys is not the
    channel's promise — Zenoh does not keep it — but the estimator's (input_order.py)."""
    a, b = make_client(), make_client()
    ch = b.channel("t/robot/r/odometry", also=("t/robot/r/observations",), recover=True)
    assert a.wait_for_subscriber("t/robot/r/odometry")
    assert a.wait_for_subscriber("t/robot/r/observations")
    odo = a.publisher("t/robot/r/odometry", cache=1000)
    obs = a.publisher("t/robot/r/observations", cache=1000)
    # a matched route may still drop the first samples for a few hundred ms under load
    # (zenoh 1.10; in CI the first 17 of a burst were gone, and recovery cannot know of
    # samples before the first it saw): put a first one on each key until it arrives
    for pub, key in ((odo, "odometry"), (obs, "observations")):
        before = ch.received  # type: ignore[attr-defined]
        put_until_seen(lambda p=pub: p.put(b"-1"),
                       lambda b=before: ch.received > b,  # type: ignore[attr-defined]
                       what=f"the first sample on {key}", timeout_s=20.0)
    for i in range(500):
        (odo if i % 3 else obs).put(str(i).encode())
    got: dict[str, list[int]] = {"odometry": [], "observations": []}
    while sum(map(len, got.values())) < 500:
        s = ch.recv(timeout=10.0)
        assert s is not None, f"only {got} arrived"
        if s.payload != b"-1":  # (a first one put again that arrived late)
            got[s.key.rsplit("/", 1)[1]].append(int(s.payload))
    assert got["odometry"] == [i for i in range(500) if i % 3]
    assert got["observations"] == [i for i in range(500) if not i % 3]


def test_samples_carry_the_publishing_sessions_clock(make_client) -> None:
    a, b = make_client(), make_client()
    ch = b.channel("t/robot/r/*", recover=True)
    odo, obs = a.publisher("t/robot/r/odometry"), a.publisher("t/robot/r/observations", cache=10)
    for pub, key in ((odo, "t/robot/r/odometry"), (obs, "t/robot/r/observations")):
        assert a.wait_for_subscriber(key)
        # a matched route may still drop the first samples for a few hundred ms under load
        # (zenoh 1.10): put a first one until it arrives, then the route is there
        before = ch.received  # type: ignore[attr-defined]
        put_until_seen(lambda p=pub: p.put(b"first"),
                       lambda b=before: ch.received > b,  # type: ignore[attr-defined]
                       what=f"the first sample on {key}", timeout_s=20.0)
    while ch.recv(timeout=0.5) is not None:  # a first one that arrived late
        pass
    for i in range(50):
        (odo if i % 2 else obs).put(b"x")
    samples = [ch.recv(timeout=5.0) for _ in range(50)]
    assert all(s is not None for s in samples)
    assert len({s.source for s in samples}) == 1 and samples[0].source
    times = [s.time for s in samples]
    assert times == sorted(times) and len(set(times)) == 50  # one clock over both keys


def test_a_callback_that_blocks_never_stops_the_channel_or_the_publisher(make_client) -> None:
    """docs/delivery.md: a consumer stalled 1 s per sample costs the publisher nothing."""
    import threading

    a, b, c = make_client(), make_client(), make_client()
    release = threading.Event()
    stalled = []

    def stall(key: str, payload: bytes) -> None:  # a badly written consumer
        stalled.append(payload)
        release.wait(1.0)

    b.subscribe("t/flood", stall)
    ch = c.channel("t/flood", recover=True)
    assert a.wait_for_subscriber("t/flood")  # (either subscriber: b's may match first)
    # the cache holds the whole burst: what congestion drops on a loaded machine (CI once
    # lost 585 of 2000 on the way to the channel) comes back from it, as docs/delivery.md's caches
    # of 10 000 inputs do for the drivers; a cache of 100 could only return the last 100
    pub = a.publisher("t/flood", cache=2000)
    # a first sample until the channel has it: its route is then open (tests/routes.py)
    put_until_seen(lambda: pub.put(b"w"), lambda: ch.received > 0,  # type: ignore[attr-defined]
                   what="the first sample", timeout_s=20.0)
    while ch.recv(timeout=0.5) is not None:
        pass
    release.set()  # the warm-up samples' stalls end; the flood's begin
    release.clear()
    started = time.monotonic()
    for i in range(2000):
        pub.put(i.to_bytes(4, "little"))
    put_s = time.monotonic() - started
    got = []
    while len(got) < 2000:
        s = ch.recv(timeout=10.0)
        assert s is not None, f"only {len(got)} of 2000 arrived beside the stalled consumer"
        got.append(int.from_bytes(s.payload, "little"))
    release.set()
    assert got == list(range(2000))
    assert put_s < 5.0, f"2000 puts took {put_s:.1f} s beside a stalled consumer"


def test_channel_push_never_waits_and_bounds_memory() -> None:
    from slamlens.common.bus import Sample
    from slamlens.common.channel import QueueChannel

    ch = QueueChannel(name="t", max_bytes=1000)
    for i in range(300):  # nobody reads: push must not block
        ch.push(Sample("k", bytes(10), time=i))
    assert ch.backlog == 100 and ch.dropped == 200 and ch.received == 300
    first = ch.recv(timeout=0)
    assert first is not None and first.time == 200  # the oldest went first
    latest = QueueChannel(name="l", capacity=1)
    for i in range(5):
        latest.push(Sample("k", b"x", time=i))
    s = latest.recv(timeout=0)
    assert s is not None and s.time == 4 and latest.dropped == 4


def test_recovering_channel_gets_what_the_publisher_cached_before_it(make_client) -> None:
    a, b = make_client(), make_client()
    pub = a.publisher("t/robot/r/state", cache=100)
    for i in range(20):
        pub.put(str(i).encode())
    ch = b.channel("t/robot/r/state", recover=True, history_s=60.0)
    got = []
    while len(got) < 25:
        if len(got) == 20:
            for i in range(20, 25):
                pub.put(str(i).encode())
        s = ch.recv(timeout=10.0)
        assert s is not None, f"history gave {got}"
        got.append(int(s.payload))
    assert got == list(range(25)) and ch.lost == 0


def test_latest_wins_channel_drops_backlog(make_client) -> None:
    a, b = make_client(), make_client()
    ch = b.channel("t/frame", latest_wins=True)
    # a reliable publisher, so that the newest sample surely arrives: what is tested here
    # is the subscriber side keeping only it (a latest-wins publisher may drop any sample)
    pub = a.publisher("t/frame")
    assert pub.wait_matched()  # type: ignore[attr-defined]
    put_until_seen(lambda: pub.put(b"-1"), lambda: ch.received > 0,  # type: ignore[attr-defined]
                   what="the first frame", timeout_s=20.0)
    assert ch.recv(timeout=2.0) is not None
    base = ch.received  # type: ignore[attr-defined]
    for i in range(200):
        pub.put(str(i).encode())
    assert _wait(lambda: ch.received == base + 200)  # type: ignore[attr-defined]
    first = ch.recv(timeout=2.0)
    assert first is not None and int(first.payload) == 199
    assert ch.recv(timeout=0.2) is None


def test_get_and_liveliness(make_client) -> None:
    a, b = make_client(), make_client()
    latest = {"v": b"one"}
    a.serve_latest("t/robot/r/state", lambda: latest["v"])
    a.declare_alive("t/robot/r/alive/estimator")
    # the token is declared after the queryable on the same session: once it is seen,
    # the queryable is known too
    assert _wait(lambda: b.alive("t/robot/*/alive/estimator", timeout=0.5) != [])
    assert [s.payload for s in b.get("t/robot/r/state")] == [b"one"]
    latest["v"] = b"two"
    assert [s.payload for s in b.get("t/robot/r/state")] == [b"two"]
    assert b.alive("t/robot/*/alive/estimator") == ["t/robot/r/alive/estimator"]
    a.close()
    assert _wait(lambda: b.alive("t/robot/*/alive/estimator", timeout=0.5) == [])


def test_unclosed_session_does_not_hang_interpreter(router_endpoint: str) -> None:
    """A process that forgets to close its bus still exits (atexit closes it)."""
    code = (
        "from slamlens.common.session import BusSettings, open_bus\n"
        f"bus = open_bus(BusSettings(connect=({router_endpoint!r},)))\n"
        "bus.subscribe('t/x', lambda k, p: None)\n"
        "ch = bus.channel('t/y')\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_explicit_endpoints_turn_multicast_off() -> None:
    conf = build_config(BusSettings(connect=("tcp/127.0.0.1:7447",)))
    assert conf.get_json("scouting/multicast/enabled") == "false"
    assert conf.get_json("mode") == '"client"'
    conf = build_config(BusSettings(listen=("tcp/127.0.0.1:7448",)))
    assert conf.get_json("mode") == '"peer"'
    assert conf.get_json("listen/endpoints") == '["tcp/127.0.0.1:7448"]'


def test_a_client_waits_for_a_router_that_starts_later() -> None:
    import threading

    from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus, router_settings

    endpoint = free_tcp_endpoint()
    routers = []
    starter = threading.Timer(1.5, lambda: routers.append(open_bus(router_settings([endpoint]))))
    starter.start()
    started = time.monotonic()
    client = open_bus(BusSettings(connect=(endpoint,)))
    try:
        assert time.monotonic() - started >= 1.0  # it really waited for the router
        other = open_bus(BusSettings(connect=(endpoint,)))
        got = []
        client.subscribe("t/late", lambda k, p: got.append(p))
        pub = other.publisher("t/late")
        assert pub.wait_matched()  # type: ignore[attr-defined]
        # (a plain publisher's first puts on a brand-new route may still be dropped: the
        # test is that the client works once its router came, so say it until heard)
        deadline = time.monotonic() + 10
        while not got and time.monotonic() < deadline:
            pub.put(b"hello")
            _wait(lambda: bool(got), timeout=0.1)
        assert got and set(got) == {b"hello"}
        other.close()
    finally:
        starter.join()
        client.close()
        for r in routers:
            r.close()


def test_large_payloads_go_through_shared_memory_on_one_host(router_endpoint) -> None:
    """a state-sized payload reaches a subscriber on the same host through
    shared memory and one that cannot map it (as across a network) as bytes."""
    from slamlens.common.session import BusSettings, open_bus

    pub_bus = open_bus(BusSettings(connect=(router_endpoint,)))
    local = open_bus(BusSettings(connect=(router_endpoint,)))
    remote = open_bus(BusSettings(connect=(router_endpoint,),
                                  extra={"transport/shared_memory/enabled": "false"}))
    try:
        got_local = local.channel("t/big", recover=True)
        got_remote = remote.channel("t/big", recover=True)
        kinds: dict[str, list[bool]] = {"local": [], "remote": []}
        firsts: list[bool] = []  # the small first samples that open the routes
        for name, bus in (("local", local), ("remote", remote)):
            bus.session.declare_subscriber(  # how each received it, straight from Zenoh
                "t/big", lambda s, n=name: (firsts if len(s.payload.to_bytes()) < 16
                                            else kinds[n]).append(s.payload.as_shm() is not None))
        assert pub_bus.wait_for_subscriber("t/big")
        pub = pub_bus.publisher("t/big", cache=4)
        # a small first sample until every route carried it (below the SHM threshold)
        put_until_seen(lambda: pub.put(b"w"), lambda: len(firsts) >= 2, what="the first sample",
                       timeout_s=20.0)
        for ch in (got_local, got_remote):
            while (s := ch.recv(timeout=0.5)) is not None:
                assert s.payload == b"w"
        payloads = [bytes([k]) * (4 << 20) for k in range(3)]  # 4 MB each
        payloads[2] = b"head" + payloads[2][4:-4] + b"tail"
        pub.put(payloads[0])
        pub.put(bytearray(payloads[1]))
        # in parts (Message.wire_parts): written one after the other into one buffer; a
        # large memoryview (an array's) is copied a chunk at a time, not a whole chunk long
        pub.put([b"head", memoryview(payloads[2])[4:-4], memoryview(b"tail")])
        for ch in (got_local, got_remote):
            received = [ch.recv(timeout=20.0) for _ in payloads]
            assert [s.payload if s else None for s in received] == payloads
        assert pub_bus.shm.shared == 3 and pub_bus.shm.plain == 0
        # how they came straight from Zenoh: by reference on this host, as bytes for the
        # session without SHM. Publishers drop under congestion and these raw subscribers do
        # not recover what was dropped (in CI under load one saw none of the three), so put
        # again until each has one: some may be missing, none may come the wrong way
        put_until_seen(lambda: pub.put(payloads[0]),
                       lambda: len(kinds["local"]) >= 1 and len(kinds["remote"]) >= 1,
                       what="a large sample on each raw subscriber", timeout_s=30.0)
        assert all(kinds["local"]) and not any(kinds["remote"]), kinds
    finally:
        for b in (pub_bus, local, remote):
            b.close()


def test_large_samples_wait_uncopied_and_only_the_newest_of_a_key(router_endpoint) -> None:
    """The monitor's intake on a large map (``newest_above``): small samples all come, in
    order; of the large ones only the newest still waiting is kept, the others counted as
    superseded, and what is taken is the payload that was put (from shared memory)."""
    from slamlens.common.session import BusSettings, open_bus

    pub_bus = open_bus(BusSettings(connect=(router_endpoint,)))
    sub_bus = open_bus(BusSettings(connect=(router_endpoint,)))
    try:
        ch = sub_bus.channel("t/big", recover=True, also=("t/small",), newest_above=1 << 20)
        assert pub_bus.wait_for_subscriber("t/big") and pub_bus.wait_for_subscriber("t/small")
        big, small = pub_bus.publisher("t/big", cache=16), pub_bus.publisher("t/small", cache=16)
        for pub in (big, small):  # a small first sample on each key until it came
            put_until_seen(lambda p=pub: p.put(b"w"), lambda: ch.backlog > 0,
                           what="the first sample", timeout_s=20.0)
            while ch.recv(timeout=0.5) is not None:
                pass
        base = ch.received  # type: ignore[attr-defined]
        larges = [bytes([k]) * (2 << 20) for k in range(5)]
        for k, payload in enumerate(larges):
            big.put(payload)
            small.put(str(k).encode())
        assert _wait(lambda: ch.received == base + 10, timeout=30.0)  # type: ignore[attr-defined]
        taken = ch.take_all()  # (each key in order; the two keys' order is Zenoh's)
        assert [s.payload for s in taken if s.key == "t/small"] == [b"0", b"1", b"2", b"3", b"4"]
        kept = [s for s in taken if s.key == "t/big"]
        assert len(kept) == 1 and kept[0].payload == larges[4] and kept[0].time is not None
        assert ch.superseded == 4 and ch.dropped == 0 and ch.backlog_bytes == 0
        big.put(larges[0])  # one waiting alone is taken as it is
        got = ch.recv(timeout=20.0)
        assert got is not None and got.payload == larges[0] and ch.superseded == 4
    finally:
        for b in (pub_bus, sub_bus):
            b.close()
