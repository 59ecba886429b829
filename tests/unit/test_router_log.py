"""The router's reading of Zenoh's log: lines as Zenoh 1.10 writes them (ANSI colours and
all), turned into one warning per refused kind, counts, and TLS refusals."""

from __future__ import annotations

import logging

from slamlens.services.commands.router_log import ZenohLogReader

ZID_R2 = "ef6c7c738976c5fdbb0d5ad08f26e971"
ZID_V = "5f3760ef872617ada4411fc578951a9c"
ACL = "\x1b[2mzenoh::net::routing::interceptor::access_control\x1b[0m\x1b[2m:\x1b[0m"
ICP = "\x1b[2mzenoh::net::routing::interceptor\x1b[0m\x1b[2m:\x1b[0m"


def _line(thread: int, target: str, text: str, level: str = "TRACE") -> str:
    return (f"\x1b[2m2026-12-01T18:35:38.357342Z\x1b[0m \x1b[35m{level}\x1b[0m rx-1 "
            f"ThreadId({thread:02d}) {target} {text}\n")


def _subject(zid: str, name: str) -> str:
    return f"{zid} on Interface(lo)+CertCommonName({name})+Transport(Tls)+{zid}"


def _reader() -> tuple[ZenohLogReader, list[tuple[int, str]]]:
    out: list[tuple[int, str]] = []

    class Sink(logging.Logger):
        def log(self, level, msg, *args, **kw):  # type: ignore[override]
            out.append((level, msg % args))

        def warning(self, msg, *args, **kw):  # type: ignore[override]
            out.append((logging.WARNING, msg % args))

    return ZenohLogReader(Sink("test")), out


def test_a_refusal_is_named_once_then_counted() -> None:
    reader, out = _reader()
    # the cache block a new key expression gets: all kinds evaluated, nothing dropped yet
    reader.line(_line(9, ACL, "ACL (ingress): caching permissions for "
                              "`slamlens/robot/r1/state` ..."))
    reader.line(_line(9, ACL, f"{_subject(ZID_V, 'viewer-lab')} is unauthorized to Put "
                              "(ingress) on slamlens/robot/r1/state"))
    reader.line(_line(9, ACL, f"{_subject(ZID_V, 'viewer-lab')} is authorized to Declare "
                              "Subscriber (ingress) on slamlens/robot/r1/state"))
    reader.line(_line(8, ACL, f"{_subject(ZID_R2, 'robot-r2')} is authorized to Query "
                              "(ingress) on slamlens/robot/r1/state"))
    reader.emit_pending(0)
    assert out == []
    # the message itself: a cached decision (no subject in it), then the drop
    for _ in range(3):
        reader.line(_line(9, ACL, f"Using cached result: {ZID_V} is unauthorized to Put "
                                  "(ingress) on slamlens/robot/r1/state"))
        reader.line(_line(9, ICP, "Msg intercepted!"))
    reader.emit_pending(0)
    assert out == [(logging.WARNING, "refused: viewer-lab may not Put (ingress) on "
                                     "slamlens/robot/r1/state (dropped; repeats are counted)")]
    reader.summarise()
    assert out[-1] == (logging.WARNING, "refused 2 more: viewer-lab may not Put (ingress) on "
                                        "slamlens/robot/r1/state (3 in all)")
    reader.summarise()
    assert len(out) == 2  # nothing new, nothing said
    assert reader.refused_total() == 3


#: what the reader says of robot-r2's refused odometry put
ROBOT_R2_REFUSED = ("refused: robot-r2 may not Put (ingress) on slamlens/robot/r1/odometry "
                    "(dropped; repeats are counted)")


def test_decisions_are_matched_by_thread() -> None:
    reader, out = _reader()
    reader.line(_line(8, ACL, f"{_subject(ZID_R2, 'robot-r2')} is unauthorized to Put "
                              "(ingress) on slamlens/robot/r1/odometry"))
    reader.line(_line(9, ACL, f"{_subject(ZID_V, 'viewer-lab')} is authorized to Put "
                              "(egress) on slamlens/robot/r1/odometry"))
    reader.line(_line(8, ICP, "Msg intercepted!"))
    reader.emit_pending(0)
    assert out == [(logging.WARNING, ROBOT_R2_REFUSED)]


def test_a_drop_without_a_refusal_is_a_client_of_no_identity() -> None:
    reader, out = _reader()
    reader.line(_line(8, ACL, f"{ZID_R2} did not match any configured ACL subject. Default "
                              "permission `Deny` will be applied on all messages", "INFO"))
    reader.line(_line(8, ICP, "Msg intercepted!"))
    reader.emit_pending(0)
    assert out[0] == (logging.WARNING, f"a client ({ZID_R2}) presented no identity this router "
                                       "knows: everything it sends is refused")
    assert out[1][1].startswith("refused: a client of no known identity may not send messages "
                                "on any key")


def test_tls_refusals_and_warnings_lose_rust_noise() -> None:
    reader, out = _reader()
    tls = "\x1b[2mzenoh_link_tls::unicast\x1b[0m\x1b[2m:\x1b[0m"
    reader.line(_line(5, tls, "received fatal alert: DecryptError. Hint: increase the system "
                              "open file limit.", " WARN"))
    reader.line(_line(5, tls, "received corrupt message of type InvalidContentType. Hint: "
                              "increase the system open file limit.", " WARN"))
    orch = "\x1b[2mzenoh::net::runtime::orchestrator\x1b[0m\x1b[2m:\x1b[0m"
    reader.line(_line(1, orch, "Unable to connect to any of [Single(tls/10.0.0.2:7447)]. "
                               "Timeout! at /root/.cargo/git/checkouts/zenoh-9c599d5ef3e0480e/"
                               "cc83980/zenoh/src/net/runtime/orchestrator.rs:388.", " WARN"))
    reader.line(_line(1, orch, "Zenoh can be reached at: tls/127.0.0.1:7447", " INFO"))
    reader.emit_pending(0)
    assert [m for _, m in out] == [
        "refused a TLS connection: received fatal alert: DecryptError.",
        "refused a TLS connection: received corrupt message of type InvalidContentType.",
        "zenoh: Unable to connect to any of [Single(tls/10.0.0.2:7447)]. Timeout!",
    ]


def test_spans_between_thread_and_target_are_understood() -> None:
    reader, out = _reader()
    reader.verbose = True
    reader.line("2026-12-01T18:55:40.242746Z DEBUG acc-0 ThreadId(04) rt{zid=7d35d371}:"
                "compute_region_of{transient_remote_bound=None peer.zid=ae6df821}: "
                "zenoh::net::runtime::region: return=Ok(North)\n")
    reader.emit_pending(0)
    assert out == [(logging.INFO, "zenoh debug zenoh::net::runtime::region: return=Ok(North)")]


#: raw log bytes: another thread's allowed put, robot-r2's name, its refusal and the drop
ALLOWED = _line(9, ACL, f"Using cached result: {ZID_V} is authorized to Put (egress) on "
                        "slamlens/robot/r1/state").encode()
NAMES = _line(8, ACL, f"{_subject(ZID_R2, 'robot-r2')} is authorized to Declare "
                      "Subscriber (ingress) on slamlens/robot/r2/state").encode()
REFUSAL = _line(8, ACL, f"Using cached result: {ZID_R2} is unauthorized to Put (ingress) "
                        "on slamlens/robot/r1/odometry").encode()
DROP = _line(8, ICP, "Msg intercepted!").encode()


def test_chunks_of_allowed_decisions_are_skipped_but_the_one_before_a_drop_is_kept() -> None:
    reader, out = _reader()
    reader.feed(NAMES)
    reader.feed(ALLOWED * 500 + REFUSAL[:40])  # a line split across reads
    reader.feed(REFUSAL[40:])  # a chunk of nothing but decisions: skipped
    reader.feed(ALLOWED * 3 + DROP)
    reader.emit_pending(0)
    assert out == [(logging.WARNING, ROBOT_R2_REFUSED)]


def test_a_refusal_far_before_its_drop_is_still_named() -> None:
    """The refused decision and its "Msg intercepted!" on one thread, with chunks of other
    threads' allowed decisions between them (a reader or a thread descheduled on a loaded
    machine): the drop is still named, never "a client of no known identity"."""
    reader, out = _reader()
    reader.feed(NAMES)
    reader.feed(REFUSAL + ALLOWED * 2000)  # ≫ the 8 KiB tail a reader once kept
    reader.feed(ALLOWED * 10 + DROP)
    reader.emit_pending(0)
    assert out == [(logging.WARNING, ROBOT_R2_REFUSED)]
