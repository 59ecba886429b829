"""peek_fields steps over a payload's other values in place: against msgpack's own decoder.

The oracle is msgpack itself: the full ``unpackb`` of a well-formed map, and for malformed
bytes the Unpacker-based peek slamlens used before (it fed the whole payload to msgpack's
buffer): the walk must give the same fields, or fail where that fails, on every input.
"""
from __future__ import annotations

import random
import tracemalloc
from typing import Any

import msgpack
import numpy as np
import pytest

from slamlens.common.errors import MessageError
from slamlens.common.messages import SlamState, peek_fields

NAMES = ("epoch", "seq", "pose", "k3", "k7", "x")


def _unpacker_peek(payload: bytes, names: tuple[str, ...]) -> dict[str, Any]:
    """The previous peek: msgpack's Unpacker over a copy of the whole payload."""
    unpacker = msgpack.Unpacker(raw=False, strict_map_key=False,
                                max_buffer_size=max(len(payload), 1))
    unpacker.feed(payload)
    out: dict[str, Any] = {}
    try:
        for _ in range(unpacker.read_map_header()):
            key = unpacker.unpack()
            if key in names and isinstance(key, str):
                out[key] = unpacker.unpack()
            else:
                unpacker.skip()
    except Exception as exc:
        raise MessageError("Message", "<payload>", "a msgpack map", type(exc).__name__) from None
    return out


def _value(rng: random.Random, depth: int = 0) -> Any:
    """A random msgpack value of every wire type: each int width, float32/64, str and bin
    at each length boundary, ext and fixext, nested arrays and maps (16/32-bit counts)."""
    kind = rng.randrange(12 if depth < 3 else 8)
    if kind == 0:
        return rng.choice([0, 1, 127, 128, 255, 256, 65535, 65536, 2 ** 32 - 1, 2 ** 32,
                           2 ** 64 - 1, -1, -32, -33, -128, -129, -32768, -32769, -2 ** 31,
                           -2 ** 31 - 1, -2 ** 63])
    if kind == 1:
        return rng.choice([0.5, -1e30, float("inf"), 1.5])
    if kind == 2:
        return "é" * rng.choice([0, 1, 15, 16, 200]) + "a" * rng.choice([0, 31, 32, 255, 256])
    if kind == 3:
        return bytes(rng.choice([0, 1, 255, 256, 65535, 65536, 70000]))
    if kind == 4:
        return msgpack.ExtType(rng.randrange(128), bytes(rng.choice([1, 2, 4, 8, 16, 3, 300,
                                                                     70000])))
    if kind == 5:
        return rng.choice([None, True, False])
    if kind == 6:
        return rng.random()
    if kind == 7:
        return rng.randrange(-2 ** 40, 2 ** 40)
    if kind in (8, 9):
        return [_value(rng, depth + 1) for _ in range(rng.choice([0, 1, 15, 16, 17]))]
    return {rng.choice(["a", "b", 1, 2.5, "x"]) if rng.random() < 0.3 else f"k{i}":
            _value(rng, depth + 1) for i in range(rng.choice([0, 1, 15, 16, 17]))}


def _payload(rng: random.Random) -> bytes:
    fields = {f"k{i}": _value(rng) for i in range(rng.choice([0, 3, 15, 16, 40]))}
    fields[rng.choice(["x", 7, "k3"])] = _value(rng)
    return msgpack.packb(fields, use_bin_type=True, use_single_float=rng.random() < 0.5)


def test_the_fields_of_well_formed_maps_are_msgpacks() -> None:
    rng = random.Random(7)
    for _ in range(200):
        payload = _payload(rng)
        full = msgpack.unpackb(payload, raw=False, strict_map_key=False)
        want = {k: v for k, v in full.items() if isinstance(k, str) and k in NAMES}
        assert peek_fields(payload, NAMES) == want
        assert peek_fields(memoryview(payload), NAMES) == want
        assert peek_fields(bytearray(payload), NAMES) == want


def test_a_real_state_is_peeked_without_decoding_its_matrix() -> None:
    n = 300
    rng = np.random.default_rng(3)
    A = rng.normal(size=(3 + 2 * n, 3 + 2 * n))
    state = SlamState(robot="r1", seq=41, stamp=2.5, step="update", pose=np.array([1.0, 2, 3]),
                      landmark_ids=np.arange(n), landmarks=rng.normal(size=(n, 2)),
                      covariance=A @ A.T, epoch=2 ** 63 + 5, origin_stamp=0.25)
    payload = state.to_bytes()
    head = peek_fields(payload, ("seq", "epoch", "origin_stamp", "robot"))
    assert head == {"seq": 41, "epoch": 2 ** 63 + 5, "origin_stamp": 0.25, "robot": "r1"}
    assert peek_fields(payload, ()) == {}


@pytest.mark.parametrize("seed", range(4))
def test_malformed_bytes_give_what_msgpacks_unpacker_gives(seed: int) -> None:
    """Every truncation of a payload, bytes flipped to every format byte (0xc1 included),
    and random garbage: the same fields, or the same refusal, as msgpack's Unpacker."""
    rng = random.Random(seed)
    cases: list[bytes] = [b"", b"\xc1", b"\x80", b"\x81", b"\xdf\xff\xff\xff\xff",
                          b"\x91\xa1a", b"\xa1a"]
    for _ in range(6):
        good = _payload(rng)
        cuts = sorted(rng.sample(range(len(good)), min(len(good), 60)))
        cases += [good[:c] for c in cuts]
        for _ in range(60):
            bad = bytearray(good)
            bad[rng.randrange(len(bad))] = rng.randrange(256)
            cases.append(bytes(bad))
    cases += [bytes(rng.randrange(256) for _ in range(rng.randrange(1, 64))) for _ in range(300)]
    for payload in cases:
        try:
            want: dict[str, Any] | None = _unpacker_peek(payload, NAMES)
        except MessageError:
            want = None
        if want is None:
            with pytest.raises(MessageError):
                peek_fields(payload, NAMES)
        else:
            assert peek_fields(payload, NAMES) == want, payload[:40]


def test_a_huge_flat_list_is_left_to_msgpack_and_still_answered() -> None:
    """Beyond the walk's item budget a payload goes to msgpack's Unpacker: the same fields."""
    payload = msgpack.packb({"k0": [None] * 300_000, "seq": 5})
    assert peek_fields(payload, ("seq",)) == {"seq": 5}


def test_peeking_a_32_mb_state_copies_nothing() -> None:
    """The walk reads the headers in place: peeking a 32 MB state allocates well under a
    megabyte (the Unpacker's copy allocated the whole payload; tracemalloc sees both)."""
    n = 1000
    payload = SlamState(robot="r1", seq=1, stamp=0.0, step="update", pose=np.zeros(3),
                        landmark_ids=np.arange(n), landmarks=np.zeros((n, 2)),
                        covariance=np.eye(3 + 2 * n), epoch=3).to_bytes()
    assert len(payload) > 30 << 20

    def peak(peek: Any) -> int:
        tracemalloc.start()
        try:
            assert peek(payload, ("epoch", "seq")) == {"epoch": 3, "seq": 1}
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    assert peak(_unpacker_peek) > 30 << 20  # the oracle proves tracemalloc sees the copy
    assert peak(peek_fields) < 1 << 20
