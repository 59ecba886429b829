"""Large payloads decode their arrays in place: against msgpack and the full validation.

``unpack_in_place`` must give msgpack's map (its large array data as read-only views into
the payload, equal to msgpack's bytes), and ``from_bytes`` of a large payload the message
that msgpack's decode through the full validation gives — or refuse what it refuses.
"""
from __future__ import annotations

import random
import tracemalloc

import msgpack
import numpy as np
import pytest

from slamlens.common.codec import IN_PLACE_ABOVE
from slamlens.common.errors import MessageError
from slamlens.common.messages import SlamState
from slamlens.common.msgpack_walk import NOT_UNPACKED, unpack_in_place


def _state(n: int, seed: int = 0) -> SlamState:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3 + 2 * n, 3 + 2 * n))
    return SlamState(robot="r1", seq=7, stamp=1.5, step="update", pose=np.array([1.0, 2, 3]),
                     landmark_ids=np.arange(n), landmarks=rng.normal(size=(n, 2)),
                     covariance=A @ A.T, epoch=11, origin_stamp=0.5,
                     observed_ids=np.arange(3), innovation_ids=np.arange(2),
                     innovations=rng.normal(size=(2, 2)),
                     innovation_covariances=np.tile(np.eye(2), (2, 1, 1)))


def _reference(payload: bytes) -> SlamState | None:
    """msgpack's decode (copies) through the full validation only; None if refused."""
    try:
        raw = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception:
        return None
    try:
        return SlamState._from_dict_full(raw)
    except Exception:  # MessageError, or what the validators missed (from_bytes: one error)
        return None


def test_a_large_state_decodes_to_the_same_message_without_copying_its_matrix() -> None:
    payload = _state(300).to_bytes()  # 2.9 MB
    assert len(payload) > IN_PLACE_ABOVE
    want = _reference(payload)
    assert want is not None

    def peak(data: bytes | bytearray) -> tuple[SlamState, int]:
        tracemalloc.start()
        try:
            return SlamState.from_bytes(data), tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    got, in_place = peak(payload)
    copied, with_copy = peak(bytearray(payload))  # not immutable: msgpack copies it
    assert got == want and copied == want
    np.testing.assert_array_equal(got.covariance, want.covariance)
    # the same validation's temporaries either way; in place saves the payload's copy
    assert with_copy - in_place > 0.9 * len(payload), (with_copy, in_place)
    assert not got.covariance.flags.writeable  # a view of immutable bytes, as before


def test_unpack_in_place_is_msgpacks_map() -> None:
    rng = random.Random(5)
    for _ in range(40):
        value = {f"f{i}": rng.choice([
            {"dtype": "<f8", "shape": [3], "data": bytes(rng.choice([24, 70000, 1 << 17]))},
            {"data": bytes(1 << 16), "x": [1, 2, {"y": b"z" * 70000}]},
            rng.random(), "s" * rng.choice([3, 40, 300]), None, [bytes(70000)],
            bytes(rng.choice([5, 70000]))]) for i in range(rng.choice([1, 16, 20]))}
        value["big"] = {"data": bytes(IN_PLACE_ABOVE)}
        payload = msgpack.packb(value, use_bin_type=True)
        got = unpack_in_place(payload)
        assert got == msgpack.unpackb(payload, raw=False, strict_map_key=False)
        assert isinstance(got["big"]["data"], memoryview)  # in place, one level down
    assert unpack_in_place(payload + b"\x00") is NOT_UNPACKED  # trailing: msgpack decides
    assert unpack_in_place(msgpack.packb([1, 2])) is NOT_UNPACKED  # not a map


@pytest.mark.parametrize("seed", range(3))
def test_hostile_large_payloads_are_refused_or_taken_as_the_full_validation_does(
        seed: int) -> None:
    """Bytes flipped in the headers and small fields of a large state (the matrix's data
    is just numbers), truncations, and appended bytes: the same refusal or the same
    message as msgpack + the full validation."""
    rng = random.Random(seed)
    good = _state(200, seed).to_bytes()
    cov_at = good.index(b"covariance")
    head = list(range(0, cov_at + 40)) + list(range(len(good) - 400, len(good)))
    cases = []
    for _ in range(150):
        bad = bytearray(good)
        bad[rng.choice(head)] = rng.randrange(256)
        cases.append(bytes(bad))
    cases += [good[:rng.randrange(len(good))] for _ in range(20)]
    cases += [good + b"\xc0", good[:-1], good.replace(b"<f8", b"<f4", 1)]
    for payload in cases:
        want = _reference(payload)
        if want is None:
            with pytest.raises(MessageError):
                SlamState.from_bytes(payload)
        else:
            assert SlamState.from_bytes(payload) == want
