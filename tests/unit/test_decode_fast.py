"""The decoders' fast path (``Message._from_dict_fast``) accepts and
rejects exactly what the full validation does, with the same message or the same error.

``Message.decode_reference`` is the decoder without the fast path (every field through the
constructor's checks, as before the fast path existed); ``from_bytes`` is what services
call. Both are driven with the same payloads: every hostile payload of services/harness/fuzz.py
(random bytes, truncated msgpack, wrong types, dtype as a list or an unknown string,
70-dimensional or huge shapes, NaN/∞ …), valid messages of every type (with and without
their optional fields, covariance flat and square), and random mutations of those: a
field replaced by a value from a pool of near-misses (an int for a float, a bool for an
int, a float32 array for a float64 field, a NaN hidden in a large array, an overflowing
but finite array, a shape off by one), a field removed or set to nil, unknown fields
added. The results must be the same message (same field values, types, dtypes, shapes,
read-only arrays) or the same MessageError text.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import msgpack
import numpy as np
import pytest

from slamlens.common.errors import MessageError
from slamlens.common.messages import MESSAGE_TYPES, Message, SlamState, Truth
from slamlens.services.harness.fuzz import bad_payloads, valid
from tests.unit.monitor_runs import run
from tests.unit.test_messages import SAMPLES


def _outcome(decode: Any, payload: bytes, **options: Any) -> tuple[str, Any]:
    try:
        return "ok", decode(payload, **options)
    except MessageError as exc:
        return "error", str(exc)


def _same_message(a: Message, b: Message) -> None:
    assert type(a) is type(b)
    for f in dataclasses.fields(a):  # type: ignore[arg-type]
        x, y = getattr(a, f.name), getattr(b, f.name)
        assert type(x) is type(y), f.name
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, f.name
            assert not x.flags.writeable and not y.flags.writeable, f.name
            assert x.flags.c_contiguous and y.flags.c_contiguous, f.name
            assert x.tobytes() == y.tobytes(), f.name
        elif isinstance(x, dict):
            assert list(x.items()) == list(y.items()), f.name
            assert [type(v) for v in x.values()] == [type(v) for v in y.values()], f.name
        else:
            assert x == y, f.name
    assert a == b and a.to_bytes() == b.to_bytes()


def _assert_same(kind: type[Message], payload: bytes, **options: Any) -> str:
    ref = _outcome(kind.decode_reference, payload, **options)
    new = _outcome(kind.from_bytes, payload, **options)
    assert ref[0] == new[0], (payload[:200], ref, new)
    if ref[0] == "ok":
        _same_message(ref[1], new[1])
    else:
        assert ref[1] == new[1]
    return ref[0]


def _pool(field_value: Any, rng: np.random.Generator) -> list[Any]:
    """Near-misses of a wire value (and a few valid variants of it)."""
    out: list[Any] = [None, True, False, 0, 1, -1, 2 ** 63, 2 ** 64 - 1, -(2 ** 63) - 1,
                      1.5, math.nan, math.inf, -math.inf, "x", "update", "predict", b"raw",
                      [], [1, 2], {}, {"a": 1.0}, {"a": math.nan}, {1: 2.0}]
    if isinstance(field_value, float):
        out += [int(field_value) if math.isfinite(field_value) else 3, field_value * 2]
    if isinstance(field_value, int) and not isinstance(field_value, bool):
        out += [float(field_value), field_value + 1, str(field_value)]
    if isinstance(field_value, dict) and "dtype" in field_value:
        dtype, shape, data = field_value["dtype"], list(field_value["shape"]), \
            field_value["data"]
        count = math.prod(shape)
        a = np.frombuffer(data, dtype=dtype).reshape(shape) if count else \
            np.zeros(shape, dtype)
        out += [
            {**field_value, "dtype": [dtype]},
            {**field_value, "dtype": "<f4", "data": a.astype("<f4").tobytes()},
            {**field_value, "dtype": ">f8", "data": a.astype(">f8").tobytes()},
            {**field_value, "dtype": "<i8", "data": a.astype("<i8").tobytes()},
            {**field_value, "dtype": "<f8", "data": a.astype("<f8").tobytes()},
            {**field_value, "shape": [1] * 70, "data": data[:8]},
            {**field_value, "shape": [2 ** 40] * len(shape)},
            {**field_value, "shape": [s + 1 for s in shape]},
            {**field_value, "shape": [*shape, 1]},
            {**field_value, "shape": [-1, *shape[1:]]},
            {**field_value, "shape": [True] * len(shape)},
            {**field_value, "shape": tuple(shape)},
            {**field_value, "data": bytearray(data)},
            {**field_value, "data": data + b"\0"},
            {k: v for k, v in field_value.items() if k != "shape"},
            a.tolist(), a.reshape(-1).tolist(),
        ]
        if a.dtype.kind == "f" and a.size:
            big = float(np.finfo(a.dtype).max)
            for bad in (math.nan, math.inf, -math.inf, big):
                b = a.copy().reshape(-1)
                b[int(rng.integers(b.size))] = bad
                if bad == big:
                    b[:] = big  # finite, but its sum overflows
                out.append({**field_value, "data": b.tobytes()})
        if a.ndim == 1 and a.size == 9:  # a 3×3 block sent square instead of flat
            out.append({**field_value, "shape": [3, 3]})
    return out


def _valid_maps() -> list[tuple[type[Message], dict[str, Any]]]:
    out: list[tuple[type[Message], dict[str, Any]]] = []
    for kind in MESSAGE_TYPES:
        out.append((kind, valid(kind).to_dict()))
    for msg in SAMPLES:
        out.append((type(msg), msg.to_dict()))
    states, truths = run(seed=3, steps=40)
    out += [(SlamState, s.to_dict()) for s in states[::7]]
    out += [(Truth, t.to_dict()) for t in truths[::9]]
    square = states[-1].to_dict()
    N = states[-1].covariance.shape[0]
    square["covariance"] = dict(square["covariance"], shape=[N, N])
    out.append((SlamState, square))
    return out


@pytest.mark.parametrize("kind", MESSAGE_TYPES, ids=lambda k: k.__name__)
def test_hostile_payloads_are_rejected_alike(kind: type[Message]) -> None:
    rng = np.random.default_rng(11)
    outcomes = [_assert_same(kind, p) for p in bad_payloads(kind, rng, 3000)]
    assert set(outcomes) == {"error"}  # every one of them invalid, and refused alike


def test_valid_messages_decode_alike_through_the_fast_path() -> None:
    """The fast path really takes them (not only the full path), with the same result."""
    for kind, raw in _valid_maps():
        payload = msgpack.packb(raw, use_bin_type=True)
        assert _assert_same(kind, payload) == "ok"
        assert kind._from_dict_fast(msgpack.unpackb(payload, strict_map_key=False), {}) \
            is not None, kind.__name__
    state = SlamState.from_bytes(msgpack.packb(_valid_maps()[-1][1], use_bin_type=True))
    assert state.covariance.ndim == 2


def test_mutated_messages_are_decoded_or_rejected_alike() -> None:
    rng = np.random.default_rng(5)
    seen = {"ok": 0, "error": 0}
    for kind, raw in _valid_maps():
        for name, value in raw.items():
            for other in _pool(value, rng):
                broken = dict(raw)
                broken[name] = other
                try:
                    payload = msgpack.packb(broken, use_bin_type=True)
                except (TypeError, OverflowError, ValueError):
                    continue  # not packable: no such payload can arrive
                for options in ({}, {"check_symmetry": False}):
                    seen[_assert_same(kind, payload, **options)] += 1
        for _ in range(40):  # several fields at once: removed, nil, unknown ones added
            broken = dict(raw)
            for name in rng.choice(list(raw), size=int(rng.integers(1, 4))):
                choice = int(rng.integers(3))
                if choice == 0:
                    broken.pop(str(name), None)
                elif choice == 1:
                    broken[str(name)] = None
                else:
                    broken[f"extra_{name}"] = raw[str(name)]
            seen[_assert_same(kind, msgpack.packb(broken, use_bin_type=True))] += 1
    assert seen["ok"] > 200 and seen["error"] > 2000  # both sides of the line exercised


def test_symmetry_options_are_honoured_by_the_fast_path() -> None:
    states, _ = run(seed=4, steps=10)
    raw = states[-1].to_dict()
    P = states[-1].covariance.copy()
    P[3, 4] += 1e-3  # asymmetric
    raw["covariance"] = dict(raw["covariance"], data=P.reshape(-1).tobytes())
    payload = msgpack.packb(raw, use_bin_type=True)
    for options in ({}, {"check_symmetry": False}, {"symmetry_rtol": 1.0}):
        _assert_same(SlamState, payload, **options)
    with pytest.raises(MessageError, match="symmetric"):
        SlamState.from_bytes(payload)
    assert SlamState.from_bytes(payload, check_symmetry=False).covariance[3, 4] == P[3, 4]
