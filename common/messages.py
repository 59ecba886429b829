"""The messages of SPEC §7: frozen dataclasses with msgpack encoding and validation.

Every message is a msgpack map with ``"schema": 1``. Arrays travel as
``{"dtype", "shape", "data"}`` maps (see :mod:`slamlens.common.arrays`). Decoders ignore unknown
fields; anything malformed raises :class:`~slamlens.common.errors.MessageError` naming the field,
what was expected and what arrived. Arrays held by a message are read-only copies, and
equality compares array contents (a plain dataclass ``__eq__`` would not).

Decisions where SPEC §7 is silent (also in ``docs/protocol.md``):

* ``SlamState.covariance`` is sent flat, shape ``[(3+2n)²]`` as SPEC writes it; decoders
  accept it flat or as ``[3+2n, 3+2n]``. In memory it is always the square matrix.
* The observed and new ids of a state are the fields ``observed_ids`` and ``new_ids``.
* A ``SlamState`` may carry the innovations of its update (``innovation_ids``,
  ``innovations`` [k,2], ``innovation_covariances`` [k,2,2]) so a monitor can test NIS.
* A ``Health`` violation is ``{kind, ids, step, growth | statistic, bound, phase, detail}``.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self

import msgpack
import numpy as np

from slamlens.common.arrays import (
    check_finite,
    check_int,
    check_str,
    check_symmetric,
    decode_array,
    encode_array,
    frozen_array,
    is_frozen_view,
    values_equal,
)
from slamlens.common.errors import MessageError, SlamlensError

SCHEMA = 1
#: binary values of at least this many bytes are written as parts of their own (wire_parts)
BIG_BINARY = 1 << 20
_FIELDS: dict[type, tuple[dataclasses.Field[Any], ...]] = {}
_PLANS: dict[type, tuple[tuple[Any, ...], ...]] = {}
_DEFAULTS: dict[type, tuple[bool, ...]] = {}
_FAST_PLANS: dict[type, tuple[dict[str, Any], dict[str, tuple[Any, ...]], int] | None] = {}
_add_reduce = np.add.reduce
#: a field default the decoder's fast path does not vouch for (it leaves the message to
#: the full path)
_NOT_VOUCHED = object()
#: the one array a producer has proven finite (finite_by_construction), on this thread only
_PROVEN_FINITE: contextvars.ContextVar[object] = contextvars.ContextVar(
    "slamlens_proven_finite", default=None)
STEPS = ("init", "predict", "update")
VIOLATION_KINDS = ("pair", "feature", "symmetry", "psd", "correlation", "nees", "nis",
                   "prediction", "unobservable")

_INT64 = (-(2 ** 63), 2 ** 63 - 1)
_UINT64 = (0, 2 ** 64 - 1)
_F8: dict[str, Any] = {"kind": "array", "dtype": "<f8"}
_I8: dict[str, Any] = {"kind": "array", "dtype": "<i8"}


def _arr(dtype: dict[str, Any], shape: tuple[int | None, ...], doc: str,
         optional: bool = False) -> Any:
    meta = {**dtype, "shape": shape, "doc": doc}
    if optional:
        return field(default=None, metadata=meta)
    return field(metadata=meta)


def _scalar(kind: str, doc: str, *, choices: tuple[str, ...] | None = None,
            range: tuple[int, int] | None = None, optional: bool = False, **kw: Any) -> Any:
    meta: dict[str, Any] = {"kind": kind, "doc": doc}
    if choices is not None:
        meta["choices"] = choices
    if range is not None:
        meta["range"] = range
    if optional:
        meta["optional"] = True
        kw.setdefault("default", None)
    return field(metadata=meta, **kw)


@contextlib.contextmanager
def finite_by_construction(array: np.ndarray | None) -> Iterator[None]:
    """Messages built in this block (on this thread) take ``array`` as finite without
    reading it: its producer proves it finite by how it was made. Every other check (dtype,
    shape, read-only) still runs, and every consumer's decode checks it in full.

    For the estimator's own covariance, whose kernels refuse any step that would make it
    non-finite (``ekf.Guard``, docs/estimator.md): summing a 32 MB matrix cost 1.5–3.4 ms
    of every state at n = 1000 (docs/large_maps.md). ``None`` proves nothing."""
    token = _PROVEN_FINITE.set(array)
    try:
        yield
    finally:
        _PROVEN_FINITE.reset(token)


class Message:
    """Base of every message: validation, freezing, msgpack, value equality."""

    TYPE: ClassVar[str] = "Message"

    # -- construction -------------------------------------------------------------
    @classmethod
    def _fields(cls) -> tuple[dataclasses.Field[Any], ...]:
        """The dataclass fields, computed once per class (this is on every hot path)."""
        cached = _FIELDS.get(cls)
        if cached is None:
            cached = _FIELDS[cls] = dataclasses.fields(cls)  # type: ignore[arg-type]
        return cached

    @classmethod
    def _plan(cls) -> tuple[tuple[Any, ...], ...]:
        """Per field, what validation needs, computed once per class (a hot path: every
        message built or decoded): (name, kind, dtype, shape, optional, range, choices)."""
        plan = _PLANS.get(cls)
        if plan is None:
            rows = []
            for f in cls._fields():
                m = f.metadata
                shape = tuple(m.get("shape", ()))
                rows.append((f.name, m.get("kind"),
                             np.dtype(m["dtype"]) if m.get("kind") == "array" else None,
                             (shape, len(shape),
                              tuple((i, n) for i, n in enumerate(shape) if n is not None)),
                             bool(m.get("optional")), m.get("range", _INT64), m.get("choices")))
            plan = _PLANS[cls] = tuple(rows)
        return plan

    def __post_init__(self) -> None:
        setattr_ = object.__setattr__
        for name, kind, dtype, (shape, ndim, fixed), optional, (low, high), choices \
                in self._plan():
            value = getattr(self, name)
            if kind == "float":
                if type(value) is not float or not math.isfinite(value):
                    if value is None and optional:
                        continue
                    setattr_(self, name, check_finite(self.TYPE, name, value))
            elif kind == "int":
                if type(value) is not int:
                    if value is None and optional:
                        continue
                    value = check_int(self.TYPE, name, value)
                    setattr_(self, name, value)
                if not low <= value <= high:
                    raise MessageError(self.TYPE, name, f"an integer in [{low}, {high}]",
                                       str(value))
            elif kind == "str":
                if type(value) is not str or (choices is not None and value not in choices):
                    if value is None and optional:
                        continue
                    check_str(self.TYPE, name, value, choices=choices)
            elif kind == "array":
                if value is None:
                    continue
                if isinstance(value, np.ndarray) and not value.flags.writeable \
                        and value.dtype == dtype:
                    array = value  # already a frozen copy (decoded, or from another message)
                else:
                    array = frozen_array(value, dtype)
                dims = array.shape
                if len(dims) != ndim or any(dims[i] != n for i, n in fixed):
                    shown = ["n" if s is None else s for s in shape]
                    raise MessageError(self.TYPE, name, f"shape {shown}", str(list(dims)))
                # the sum is finite iff every entry is (barring overflow, then check each)
                if dtype.kind == "f" and array.size and value is not _PROVEN_FINITE.get() \
                        and not (math.isfinite(float(array.sum()))
                                 or np.isfinite(array).all()):
                    raise MessageError(self.TYPE, name, "finite values", "NaN or infinity")
                setattr_(self, name, array)
            elif value is None and optional:
                continue
            elif kind == "bool":
                if not isinstance(value, bool):
                    raise MessageError(self.TYPE, name, "a boolean", type(value).__name__)
            elif kind == "bytes":
                if not isinstance(value, (bytes, bytearray, memoryview)):
                    raise MessageError(self.TYPE, name, "bytes", type(value).__name__)
                setattr_(self, name, bytes(value))
        self._check()

    def _check(self) -> None:
        """Cross-field checks (shapes consistent with counts and so on)."""

    # -- equality -----------------------------------------------------------------
    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(values_equal(getattr(self, f.name), getattr(other, f.name))
                   for f in self._fields())

    __hash__ = None  # type: ignore[assignment]

    # -- wire format --------------------------------------------------------------
    #: array fields sent flattened to one axis (the decoder restores the shape)
    _FLAT: ClassVar[tuple[str, ...]] = ()

    def to_dict(self) -> dict[str, Any]:
        return self._wire_dict(views=False)

    def _wire_dict(self, *, views: bool) -> dict[str, Any]:
        """The wire map; with ``views`` large arrays' data are the arrays' own buffers
        (a ``bytearray`` behind the array, or a memoryview), not copies."""
        out: dict[str, Any] = {"schema": SCHEMA}
        for name, kind, dtype, _shape, optional, _range, _choices in self._plan():
            value = getattr(self, name)
            if value is None and (optional or kind == "array"):
                continue
            if kind == "array":
                if name in self._FLAT:
                    value = value.reshape(-1)
                out[name] = encode_array(value, dtype.str, view=views)
            elif kind == "violations":
                out[name] = [v.to_dict() for v in value]
            elif kind == "stats":
                out[name] = dict(value)
            else:
                out[name] = value
        return out

    def wire_parts(self) -> list[bytes | bytearray | memoryview]:
        """The msgpack encoding as consecutive parts: ``b"".join(parts) == to_bytes()``.

        Arrays of at least :data:`BIG_BINARY` bytes are parts of their own, their own memory
        (not copied), so a large message is copied once, wherever it goes (e.g. into shared
        memory). msgpack's packer would copy a 32 MB state through a growing buffer (30 ms
        measured at n = 1000, against 3 ms for one copy).
        """
        raw = self._wire_dict(views=True)
        if not any(isinstance(v, dict) and isinstance(v.get("data"), (bytearray, memoryview))
                   and len(v["data"]) >= BIG_BINARY for v in raw.values()):
            # msgpack packs a bytearray or memoryview as the same bin value as bytes
            return [msgpack.packb(raw, use_bin_type=True)]
        packer = msgpack.Packer(use_bin_type=True)
        parts: list[bytes | bytearray | memoryview] = []
        small: list[bytes] = [packer.pack_map_header(len(raw))]
        for key, value in raw.items():
            small.append(packer.pack(key))
            data = value.get("data") if isinstance(value, dict) else None
            if not isinstance(data, (bytearray, memoryview)) or len(data) < BIG_BINARY:
                if isinstance(data, (bytearray, memoryview)):
                    value = dict(value, data=bytes(data))
                small.append(packer.pack(value))
                continue
            small.append(packer.pack_map_header(len(value)))
            for k, v in value.items():
                small.append(packer.pack(k))
                if k != "data":
                    small.append(packer.pack(v))
            small.append(_bin_header(len(data)))
            parts.append(b"".join(small))
            parts.append(data)
            small = []
        if small:
            parts.append(b"".join(small))
        return parts

    def to_bytes(self) -> bytes:
        parts = self.wire_parts()
        return parts[0] if len(parts) == 1 and isinstance(parts[0], bytes) \
            else b"".join(parts)

    @classmethod
    def from_bytes(cls, payload: bytes | bytearray | memoryview, **options: Any) -> Self:
        return cls._decoded(payload, cls.from_dict, options)

    @classmethod
    def _decoded(cls, payload: bytes | bytearray | memoryview,
                 build: Callable[..., Self], options: dict[str, Any]) -> Self:
        """``build(map, **options)`` of the msgpack map in ``payload``; every failure one
        MessageError (undecodable bytes, or a case the validators missed)."""
        raw: Any = _NOT_UNPACKED
        if type(payload) is bytes and len(payload) >= IN_PLACE_ABOVE:
            raw = unpack_in_place(payload)  # the large arrays as views, not copies
        try:
            if raw is _NOT_UNPACKED:
                raw = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=False)
        except Exception as exc:  # msgpack raises several unrelated types
            raise MessageError(cls.TYPE, "<payload>", "a msgpack map",
                               f"undecodable bytes ({type(exc).__name__})") from None
        try:
            return build(raw, **options)
        except MessageError:
            raise
        except Exception as exc:  # a case the validators missed: still one error type
            raise MessageError(cls.TYPE, "<payload>", "a well-formed message",
                               f"{type(exc).__name__}: {str(exc)[:80]}") from None

    @classmethod
    def from_dict(cls, raw: Any, **options: Any) -> Self:
        """The message of a decoded msgpack map; raises MessageError naming the field.

        A well-formed map (every value of its field's exact wire type, arrays as maps of
        the field's own dtype) is accepted by a fast path in one pass; anything else it
        does not vouch for goes through :meth:`_from_dict_full`, which then accepts or
        rejects it as the only path would. The fast path only ever *accepts*, and only
        what the full path accepts as the same message (tests/unit/test_decode_fast.py
        holds the two to it on hostile payloads).
        """
        message = cls._from_dict_fast(raw, options)
        if message is not None:
            return message
        return cls._from_dict_full(raw, **options)

    @classmethod
    def decode_reference(cls, payload: bytes | bytearray | memoryview,
                         **options: Any) -> Self:
        """:meth:`from_bytes` without the fast path: every message through the full
        validation (what tests compare the fast path with)."""
        return cls._decoded(payload, cls._from_dict_full, options)

    @classmethod
    def _fast_plan(cls) -> tuple[dict[str, Any], dict[str, tuple[Any, ...]], int] | None:
        """What the fast path needs: the fields' defaults in field order (required ones
        :data:`_NOT_VOUCHED`), per field name (kind, dtype, dtype string, itemsize, wire
        shape, low, high, choices, whether the class has its own wire shape), and how
        many fields are required; None if the class builds itself in ways the fast path
        does not repeat."""
        try:
            return _FAST_PLANS[cls]
        except KeyError:
            pass
        plan = None
        # a class whose construction or wire hooks differ from Message's says how the
        # fast path finishes it (_fast_finish), or it has none
        owners = {next(k for k in cls.__mro__ if hook in k.__dict__)
                  for hook in ("__post_init__", "_from_wire", "_wire_shape")}
        if all(k is Message or "_fast_finish" in k.__dict__ for k in owners):
            # the fields whose wire shape the class decides (_wire_shape): all arrays,
            # unless the class that overrides it names them (_WIRE_SHAPED)
            owner = next(k for k in cls.__mro__ if "_wire_shape" in k.__dict__)
            shaped = (() if owner is Message else owner.__dict__.get("_WIRE_SHAPED"))
            defaults: dict[str, Any] = {}
            rows: dict[str, tuple[Any, ...]] = {}
            for (name, kind, dtype, (shape, _, _), optional, (low, high), choices), f \
                    in zip(cls._plan(), cls._fields(), strict=True):
                if f.default_factory is not dataclasses.MISSING:
                    default = f.default_factory()  # (empty containers: one is shared)
                elif f.default is not dataclasses.MISSING:
                    default = f.default
                else:
                    default = _NOT_VOUCHED  # required: missing is the full path's error
                if default is not _NOT_VOUCHED and not _default_valid(
                        kind, default, optional, low, high, choices):
                    default = _NOT_VOUCHED
                defaults[name] = default
                rows[name] = (kind, dtype, None if dtype is None else dtype.str,
                              0 if dtype is None else dtype.itemsize, shape, low, high,
                              choices, kind == "array" and (shaped is None
                                                            or name in shaped))
            plan = (defaults, rows, sum(1 for v in defaults.values() if v is _NOT_VOUCHED))
        _FAST_PLANS[cls] = plan
        return plan

    @classmethod
    def _from_dict_fast(cls, raw: Any, options: Mapping[str, Any]) -> Self | None:
        """The message, if every field is of its exact wire type and valid; else None
        (the full path decides, and words any rejection). Never raises."""
        plan = cls._fast_plan()
        if plan is None or type(raw) is not dict or raw.get("schema") != SCHEMA:
            return None
        defaults, rows, required = plan
        values = dict(defaults)  # field order; the wire's values replace the defaults
        isfinite = math.isfinite
        sums = 0.0  # of every float array: finite iff each entry is (barring overflow)
        try:
            for name, value in raw.items():
                row = rows.get(name)
                if row is None or value is None:  # not a field / nil: absent
                    continue
                kind, dtype, dstr, itemsize, shape, low, high, choices, own_shape = row
                if kind == "array":
                    # decode_array's own fast case, and the constructor's finiteness test
                    if type(value) is not dict or value.get("dtype") != dstr:
                        return None
                    wire_shape, data = value.get("shape"), value.get("data")
                    if not (type(data) is bytes or is_frozen_view(data)) or type(
                            wire_shape) is not list:
                        return None
                    if own_shape:
                        shape = cls._wire_shape(name, raw, shape)
                    if len(wire_shape) != len(shape):
                        return None
                    if len(shape) == 1:  # (most fields: one axis)
                        count, w = wire_shape[0], shape[0]
                        if type(count) is not int or count < 0 or (w is not None
                                                                   and count != w):
                            return None
                    else:
                        count = 1
                        for d, w in zip(wire_shape, shape, strict=True):
                            if type(d) is not int or d < 0 or (w is not None and d != w):
                                return None
                            count *= d
                    if len(data) != count * itemsize:
                        return None
                    value = np.frombuffer(data, dtype=dtype)  # read-only: immutable bytes
                    if len(wire_shape) != 1:  # (1-D: already the shape)
                        value = value.reshape(wire_shape)
                    if dtype.kind == "f" and count:
                        sums += _add_reduce(value, None)
                elif kind == "float":
                    if type(value) is not float or not isfinite(value):
                        return None
                elif kind == "int":
                    if type(value) is not int or not low <= value <= high:
                        return None
                elif kind == "str":
                    if type(value) is not str or (choices is not None
                                                  and value not in choices):
                        return None
                elif kind == "bool":
                    if type(value) is not bool:
                        return None
                elif kind == "bytes":
                    if type(value) is not bytes:
                        return None
                elif kind == "violations":
                    if type(value) is not list:
                        return None
                    value = tuple(Violation.from_dict(v) for v in value)
                elif kind == "stats":
                    if type(value) is not dict:
                        return None
                    value = {str(k): check_finite(cls.TYPE, f"{name}.{k}", v)
                             for k, v in value.items()}
                else:
                    return None
                if values[name] is _NOT_VOUCHED:
                    required -= 1
                values[name] = value
            if required or not isfinite(sums):  # a field missing; NaN, ∞ or an overflow
                return None
            for name, default in defaults.items():  # fresh containers, as the factories
                if type(default) is dict and values[name] is default:
                    values[name] = {}
            message = object.__new__(cls)
            message.__dict__.update(values)
            cls._fast_finish(message, options)
            message._check()
        except Exception:  # whatever it is, the full path says it (or accepts it)
            return None
        return message

    @classmethod
    def _fast_finish(cls, message: Any, options: Mapping[str, Any]) -> None:
        """What :meth:`_from_wire` and ``__post_init__`` add to the fields of a message
        the fast path decoded (before ``_check``); may raise MessageError."""

    @classmethod
    def _from_dict_full(cls, raw: Any, **options: Any) -> Self:
        """Decode with every field validated by the constructor (the reference path)."""
        if not isinstance(raw, Mapping):
            raise MessageError(cls.TYPE, "<payload>", "a msgpack map", type(raw).__name__)
        schema = raw.get("schema")
        if schema != SCHEMA:
            raise MessageError(cls.TYPE, "schema", str(SCHEMA), repr(schema))
        kwargs: dict[str, Any] = {}
        for (name, kind, dtype, (shape, _, _), _opt, _rng, _ch), has_default in zip(
                cls._plan(), cls._defaults(), strict=True):
            value = raw.get(name)
            if value is None:
                if has_default:
                    continue
                raise MessageError(cls.TYPE, name, "present", "missing")
            if kind == "array":
                # finiteness is checked once, by the constructor
                value = decode_array(value, message=cls.TYPE, field=name, dtype=dtype.str,
                                     shape=cls._wire_shape(name, raw, shape), finite=False)
            elif kind == "violations":
                if not isinstance(value, list):
                    raise MessageError(cls.TYPE, name, "a list", type(value).__name__)
                value = tuple(Violation.from_dict(v) for v in value)
            elif kind == "stats":
                if not isinstance(value, Mapping):
                    raise MessageError(cls.TYPE, name, "a map", type(value).__name__)
                value = {str(k): check_finite(cls.TYPE, f"{name}.{k}", v)
                         for k, v in value.items()}
            elif kind == "float" and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            kwargs[name] = value
        return cls._from_wire(kwargs, **options)

    @classmethod
    def _defaults(cls) -> tuple[bool, ...]:
        """Per field, whether it has a default (may be absent on the wire)."""
        cached = _DEFAULTS.get(cls)
        if cached is None:
            cached = _DEFAULTS[cls] = tuple(
                f.default is not dataclasses.MISSING or f.default_factory is not
                dataclasses.MISSING for f in cls._fields())
        return cached

    @classmethod
    def _wire_shape(cls, name: str, raw: Mapping[str, Any],
                    shape: tuple[int | None, ...]) -> tuple[int | None, ...]:
        """The shape field ``name`` travels in (its declared ``shape`` unless a message
        says otherwise)."""
        return shape

    @classmethod
    def _from_wire(cls, kwargs: dict[str, Any], **options: Any) -> Self:
        return cls(**kwargs)


def _default_valid(kind: str, value: Any, optional: bool, low: int, high: int,
                   choices: tuple[str, ...] | None) -> bool:
    """Whether the constructor accepts a field default as it is (the fast path then
    uses it without the constructor's checks)."""
    if value is None:
        return optional or kind in ("array", "stats", "violations")
    if kind == "float":
        return type(value) is float and math.isfinite(value)
    if kind == "int":
        return type(value) is int and low <= value <= high
    if kind == "str":
        return type(value) is str and (choices is None or value in choices)
    if kind == "bool":
        return type(value) is bool
    return (kind == "violations" and value == ()) or (kind == "stats" and value == {})


def _count_check(message: str, name: str, array: np.ndarray | None, expected: int,
                 what: str) -> None:
    if array is not None and array.shape[0] != expected:
        raise MessageError(message, name, f"{expected} entries ({what})",
                           f"{array.shape[0]}")


@dataclass(frozen=True, eq=False)
class Odometry(Message):
    """Odometry of one time step: forward speed and turn rate held over ``dt``."""

    TYPE: ClassVar[str] = "Odometry"
    robot: str = _scalar("str", "robot name")
    stamp: float = _scalar("float", "time of the end of the step, s")
    dt: float = _scalar("float", "duration of the step, s (≥ 0)")
    v: float = _scalar("float", "forward speed, m/s")
    w: float = _scalar("float", "turn rate, rad/s")
    input_seq: int | None = _scalar(
        "int", "optional: the driver's input counter, +1 per odometry or observations "
        "message on either key (SPEC §7a ordering; docs/protocol.md)", optional=True,
        range=_UINT64)

    def _check(self) -> None:
        if self.dt < 0:
            raise MessageError(self.TYPE, "dt", "≥ 0", repr(self.dt))


@dataclass(frozen=True, eq=False)
class Observations(Message):
    """One batch of range-bearing observations taken at ``stamp``."""

    TYPE: ClassVar[str] = "Observations"
    robot: str = _scalar("str", "robot name")
    stamp: float = _scalar("float", "sensor time, s")
    ids: np.ndarray = _arr(_I8, (None,),
                           "landmark ids int64[k]; −1 = unknown (the estimator associates)")
    ranges: np.ndarray = _arr(_F8, (None,), "ranges, m, float64[k] (≥ 0)")
    bearings: np.ndarray = _arr(_F8, (None,), "bearings, rad, float64[k], robot frame")
    input_seq: int | None = _scalar(
        "int", "optional: the driver's input counter (see Odometry.input_seq)",
        optional=True, range=_UINT64)

    def _check(self) -> None:
        k = self.ids.shape[0]
        _count_check(self.TYPE, "ranges", self.ranges, k, "one per id")
        _count_check(self.TYPE, "bearings", self.bearings, k, "one per id")
        if np.any(self.ranges < 0):
            raise MessageError(self.TYPE, "ranges", "non-negative ranges", "a negative range")
        if np.any(self.ids < -1):
            raise MessageError(self.TYPE, "ids", "ids ≥ −1", str(int(self.ids.min())))


@dataclass(frozen=True, eq=False)
class Truth(Message):
    """Ground truth: the robot's true pose and the true landmarks, in the map frame."""

    TYPE: ClassVar[str] = "Truth"
    robot: str = _scalar("str", "robot name")
    stamp: float = _scalar("float", "time, s")
    pose: np.ndarray = _arr(_F8, (3,), "true pose (x m, y m, θ rad) in the map frame")
    landmark_ids: np.ndarray = _arr(_I8, (None,), "landmark ids int64[n]")
    landmarks: np.ndarray = _arr(_F8, (None, 2), "true landmark positions [n,2], m, map frame")
    marker_id: int | None = _scalar(
        "int", "optional: the id of the fiducial marker the robot carries (the simulator "
        "says it, so a synthetic camera can draw each robot's own marker)", optional=True,
        range=(0, 2 ** 31 - 1))

    def _check(self) -> None:
        _count_check(self.TYPE, "landmarks", self.landmarks, self.landmark_ids.shape[0],
                     "one per landmark id")


@dataclass(frozen=True, eq=False)
class SlamState(Message):
    """The estimator's full state after one event (SPEC §7)."""

    TYPE: ClassVar[str] = "SlamState"
    robot: str = _scalar("str", "robot name")
    seq: int = _scalar("int", "state sequence number, +1 per event applied")
    stamp: float = _scalar("float", "time of the event applied, s")
    step: str = _scalar("str", "what produced this state: init / predict / update",
                        choices=STEPS)
    pose: np.ndarray = _arr(_F8, (3,), "estimated robot pose (x m, y m, θ rad), map frame")
    landmark_ids: np.ndarray = _arr(_I8, (None,), "landmark ids int64[n], state order")
    landmarks: np.ndarray = _arr(_F8, (None, 2), "estimated landmarks [n,2], m, map frame")
    covariance: np.ndarray = _arr(_F8, (None, None),
                                  "state covariance [(3+2n),(3+2n)] (flat on the wire)")
    observed_ids: np.ndarray = _arr(_I8, (None,), "ids observed in this event", optional=True)
    new_ids: np.ndarray = _arr(_I8, (None,), "ids initialised in this event", optional=True)
    innovation_ids: np.ndarray = _arr(_I8, (None,), "ids of the innovations below",
                                      optional=True)
    innovations: np.ndarray = _arr(_F8, (None, 2), "innovations ν [k,2] (m, rad)", optional=True)
    innovation_covariances: np.ndarray = _arr(_F8, (None, 2, 2), "innovation covariances S",
                                              optional=True)
    epoch: int = _scalar("int", "uint64 fixed for the life of one map (kept across a restart "
                         "from a checkpoint, new when a map starts from scratch); 0 = unknown "
                         "(a third-party estimator that does not say)", range=_UINT64,
                         default=0)
    input_stamp: float | None = _scalar(
        "float", "stamp of the newest input folded in, s (what drivers pace on); "
        "defaults to ``stamp``", optional=True)
    origin_stamp: float | None = _scalar(
        "float", "optional: when the robot stood at this epoch's map origin (the start of "
        "the first input folded in), s; None until an input is applied", optional=True)
    gated_ids: np.ndarray | None = _arr(
        _I8, (None,), "optional: landmarks of the observations of this update refused by the "
        "innovation gate (NIS above it)", optional=True)
    gated_observations: np.ndarray | None = _arr(
        _F8, (None, 2), "optional: those observations as measured [g,2] (range m, bearing rad)",
        optional=True)
    gated_nis: np.ndarray | None = _arr(_F8, (None,), "optional: their NIS νᵀS⁻¹ν",
                                        optional=True)
    diagnostics: dict[str, float] | None = field(
        default=None, metadata={"kind": "stats", "optional": True,
                                "doc": "optional: the estimator's running counts (gated, "
                                       "refused_updates, refused.<reason>); docs/protocol.md"})

    def __post_init__(self) -> None:
        self._fill_defaults()
        super().__post_init__()

    def _fill_defaults(self) -> None:
        for name in ("observed_ids", "new_ids"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, frozen_array(np.zeros(0), "<i8"))
        if self.input_stamp is None:
            object.__setattr__(self, "input_stamp", self.stamp)

    @property
    def n(self) -> int:
        """Number of landmarks."""
        return int(self.landmark_ids.shape[0])

    def _check(self) -> None:
        n = self.n
        _count_check(self.TYPE, "landmarks", self.landmarks, n, "one per landmark id")
        N = 3 + 2 * n
        if self.covariance.shape != (N, N):
            raise MessageError(self.TYPE, "covariance", f"[{N}, {N}] for n = {n}",
                               str(list(self.covariance.shape)))
        if len(set(self.landmark_ids.tolist())) != n:
            raise MessageError(self.TYPE, "landmark_ids", "distinct ids", "duplicates")
        if self.innovations is not None or self.innovation_covariances is not None:
            k = 0 if self.innovation_ids is None else self.innovation_ids.shape[0]
            _count_check(self.TYPE, "innovations", self.innovations, k, "one per innovation id")
            _count_check(self.TYPE, "innovation_covariances", self.innovation_covariances, k,
                         "one per innovation id")
        if self.gated_observations is not None or self.gated_nis is not None:
            g = 0 if self.gated_ids is None else self.gated_ids.shape[0]
            _count_check(self.TYPE, "gated_observations", self.gated_observations, g,
                         "one per gated id")
            _count_check(self.TYPE, "gated_nis", self.gated_nis, g, "one per gated id")
        if self.diagnostics is not None:
            if not isinstance(self.diagnostics, Mapping):
                raise MessageError(self.TYPE, "diagnostics", "a map",
                                   type(self.diagnostics).__name__)
            for key, value in self.diagnostics.items():
                check_finite(self.TYPE, f"diagnostics.{key}", value)

    _FLAT = ("covariance",)
    #: the fields whose wire shape _wire_shape decides (the decoder's fast path asks it
    #: for these only)
    _WIRE_SHAPED: ClassVar[tuple[str, ...]] = ("covariance",)

    @classmethod
    def _wire_shape(cls, name: str, raw: Mapping[str, Any],
                    shape: tuple[int | None, ...]) -> tuple[int | None, ...]:
        if name == "covariance":
            cov = raw.get("covariance")
            wire = cov.get("shape") if isinstance(cov, Mapping) else None
            if isinstance(wire, list) and len(wire) == 1:
                return (None,)
        return shape

    @classmethod
    def _from_wire(cls, kwargs: dict[str, Any], **options: Any) -> Self:
        kwargs["covariance"] = cls._square(kwargs["covariance"])
        state = cls(**kwargs)
        cls._check_symmetry(state, options)
        return state

    @classmethod
    def _fast_finish(cls, message: Any, options: Mapping[str, Any]) -> None:
        object.__setattr__(message, "covariance", cls._square(message.covariance))
        message._fill_defaults()  # as __post_init__
        cls._check_symmetry(message, options)

    @classmethod
    def _square(cls, cov: np.ndarray) -> np.ndarray:
        """The wire's flat covariance as its N×N matrix (a 2-D one as it is)."""
        if cov.ndim != 1:
            return cov
        N = math.isqrt(cov.shape[0])
        if N * N != cov.shape[0]:
            raise MessageError(cls.TYPE, "covariance", "(3+2n)² entries",
                               f"{cov.shape[0]} (not a square)")
        return cov.reshape(N, N)

    @classmethod
    def _check_symmetry(cls, state: Any, options: Mapping[str, Any]) -> None:
        """A decoded state's symmetry test, unless the decoder was asked not to."""
        if options.get("check_symmetry", True):
            check_symmetric(cls.TYPE, "covariance", state.covariance,
                            rtol=options.get("symmetry_rtol", 1e-6))


_F4: dict[str, Any] = {"kind": "array", "dtype": "<f4"}
SUMMARY_WHATS = ("blocks", "clusters", "pairs")


@dataclass(frozen=True, eq=False)
class StateSummary(Message):
    """What a remote viewer draws of one ``SlamState``, not the whole matrix (issue 13;
    key ``robot/R/summary``, a queryable; docs/protocol.md, docs/remote_viewers.md).

    Always the map's blocks (pose and its 3×3 covariance, each feature's mean and 2×2
    marginal covariance); with ``what = "clusters"`` the min / mean / max of the relative
    covariances P_d = P_ii + P_jj − P_ij − P_ji between every two groups of features; with
    ``what = "pairs"`` the P_d of every pair of one cluster, or of one feature. Reals are
    float32 on the wire but for ``pose`` and the stamps; indices are into the state's
    landmarks (``landmark_ids`` order)."""

    TYPE: ClassVar[str] = "StateSummary"
    robot: str = _scalar("str", "robot name")
    seq: int = _scalar("int", "seq of the state summarised")
    stamp: float = _scalar("float", "its stamp, s")
    step: str = _scalar("str", "its step: init / predict / update", choices=STEPS)
    pose: np.ndarray = _arr(_F8, (3,), "estimated robot pose (x m, y m, θ rad), map frame")
    pose_covariance: np.ndarray = _arr(_F4, (3, 3), "its covariance P_vv (m², m·rad, rad²)")
    landmark_ids: np.ndarray = _arr(_I8, (None,), "landmark ids int64[n], state order")
    landmarks: np.ndarray = _arr(_F4, (None, 2), "feature means float32[n,2], m, map frame")
    landmark_covariances: np.ndarray = _arr(_F4, (None, 2, 2),
                                            "marginal covariances P_ii float32[n,2,2], m²")
    epoch: int = _scalar("int", "its map epoch (uint64; 0 = unknown)", range=_UINT64,
                         default=0)
    input_stamp: float | None = _scalar("float", "its input_stamp, s", optional=True)
    what: str = _scalar("str", "what it holds beyond the blocks: blocks / clusters / pairs",
                        choices=SUMMARY_WHATS, default="blocks")
    state_bytes: int = _scalar("int", "size of the full state's payload summarised, bytes",
                               default=0, range=_UINT64)
    cluster_threshold_m: float | None = _scalar(
        "float", "clusters: the single-linkage cut used, m", optional=True)
    cluster_count: int | None = _scalar(
        "int", "clusters: the cluster count asked for (0 = cut at the threshold)",
        optional=True, range=(0, 2 ** 31 - 1))
    tile_m: float | None = _scalar(
        "float", "clusters: the groups are square map tiles of this side, m (the budget "
        "rule); absent: they are the clusters", optional=True)
    groups: np.ndarray | None = _arr(
        _I8, (None,), "clusters, pairs: group per landmark int64[n]: stable cluster id "
        "(or tile id with tile_m)", optional=True)
    group_pairs: np.ndarray | None = _arr(_I8, (None, 2), "clusters: (A, B) group ids, A < "
                                          "B, int64[c,2]", optional=True)
    pair_count: np.ndarray | None = _arr(_I8, (None,), "clusters: feature pairs between A "
                                         "and B, int64[c]", optional=True)
    min_pair: np.ndarray | None = _arr(_I8, (None, 2), "clusters: landmark indices (i < j) "
                                       "of the smallest P_d (by √λmax), int64[c,2]",
                                       optional=True)
    max_pair: np.ndarray | None = _arr(_I8, (None, 2), "clusters: those of the largest",
                                       optional=True)
    min_Pd: np.ndarray | None = _arr(_F4, (None, 2, 2), "clusters: the smallest P_d, m²",
                                     optional=True)
    mean_Pd: np.ndarray | None = _arr(_F4, (None, 2, 2), "clusters: the element-wise mean "
                                      "P_d over the pairs between A and B, m²", optional=True)
    max_Pd: np.ndarray | None = _arr(_F4, (None, 2, 2), "clusters: the largest P_d, m²",
                                     optional=True)
    selected_cluster: int | None = _scalar("int", "pairs: the cluster whose pairs these are",
                                           optional=True)
    selected_feature: int | None = _scalar("int", "pairs: the feature id whose pairs these "
                                           "are", optional=True)
    pairs: np.ndarray | None = _arr(_I8, (None, 2), "pairs: landmark indices (i < j), "
                                    "int64[m,2]", optional=True)
    pairs_Pd: np.ndarray | None = _arr(_F4, (None, 2, 2), "pairs: their P_d, m²",
                                       optional=True)
    pairs_total: int | None = _scalar("int", "pairs: how many there were before the cap "
                                      "(the largest are kept)", optional=True, range=_UINT64)
    compute_s: float | None = _scalar("float", "robot side: time to make it, s",
                                      optional=True)

    @property
    def n(self) -> int:
        return int(self.landmark_ids.shape[0])

    def _check(self) -> None:
        n = self.n
        for name in ("landmarks", "landmark_covariances", "groups"):
            _count_check(self.TYPE, name, getattr(self, name), n, "one per landmark id")
        c = None if self.group_pairs is None else self.group_pairs.shape[0]
        for name in ("pair_count", "min_pair", "max_pair", "min_Pd", "mean_Pd", "max_Pd"):
            value = getattr(self, name)
            if (value is None) != (c is None):
                raise MessageError(self.TYPE, name, "present with group_pairs",
                                   "missing" if value is None else "without group_pairs")
            _count_check(self.TYPE, name, value, c or 0, "one per group pair")
        m = None if self.pairs is None else self.pairs.shape[0]
        if (self.pairs_Pd is None) != (m is None):
            raise MessageError(self.TYPE, "pairs_Pd", "present with pairs", "alone")
        _count_check(self.TYPE, "pairs_Pd", self.pairs_Pd, m or 0, "one per pair")
        for name in ("min_pair", "max_pair", "pairs"):
            value = getattr(self, name)
            if value is not None and value.size and (value.min() < 0 or value.max() >= n):
                raise MessageError(self.TYPE, name, f"landmark indices in [0, {n})",
                                   f"[{int(value.min())}, {int(value.max())}]")
        if self.what == "clusters" and (self.groups is None or self.group_pairs is None):
            raise MessageError(self.TYPE, "groups", "groups and group_pairs (what = "
                               "clusters)", "missing")
        if self.what == "pairs" and self.pairs is None:
            raise MessageError(self.TYPE, "pairs", "present (what = pairs)", "missing")


@dataclass(frozen=True)
class Violation:
    """One broken expectation found by the monitor (an entry of ``Health.violations``)."""

    kind: str  #: one of VIOLATION_KINDS
    ids: tuple[int, ...]  #: feature ids involved (a pair, one feature, or none)
    step: int  #: seq of the state where it was seen
    value: float  #: growth (covariance kinds) or the test statistic (nees, nis)
    bound: float | None = None  #: tolerance or χ² bound it was held against
    phase: str = ""  #: "predict" / "update" when the step type matters
    detail: str = ""  #: one human sentence
    first_step: int | None = None  #: standing violations: seq where it was first seen
    count: int | None = None  #: standing violations: states that showed it

    _STAT_KINDS: ClassVar[tuple[str, ...]] = ("nees", "nis")

    def to_dict(self) -> dict[str, Any]:
        key = "statistic" if self.kind in self._STAT_KINDS else "growth"
        out: dict[str, Any] = {"kind": self.kind, "ids": list(self.ids), "step": self.step,
                               key: self.value}
        if self.bound is not None:
            out["bound"] = self.bound
        if self.phase:
            out["phase"] = self.phase
        if self.detail:
            out["detail"] = self.detail
        if self.first_step is not None:
            out["first_step"] = self.first_step
        if self.count is not None:
            out["count"] = self.count
        return out

    @classmethod
    def from_dict(cls, raw: Any) -> Violation:
        m = "Health.violation"
        if not isinstance(raw, Mapping):
            raise MessageError(m, "<entry>", "a map", type(raw).__name__)
        kind = check_str(m, "kind", raw.get("kind"), choices=VIOLATION_KINDS)
        ids_raw = raw.get("ids", [])
        if not isinstance(ids_raw, list):
            raise MessageError(m, "ids", "a list of ints", type(ids_raw).__name__)
        ids = tuple(check_int(m, "ids", i) for i in ids_raw)
        key = "statistic" if kind in cls._STAT_KINDS else "growth"
        value = check_finite(m, key, raw.get(key, raw.get("growth", raw.get("statistic"))))
        bound = raw.get("bound")
        first, count = raw.get("first_step"), raw.get("count")
        return cls(kind=kind, ids=ids, step=check_int(m, "step", raw.get("step")), value=value,
                   bound=None if bound is None else check_finite(m, "bound", bound),
                   phase=str(raw.get("phase", "")), detail=str(raw.get("detail", "")),
                   first_step=None if first is None else check_int(m, "first_step", first),
                   count=None if count is None else check_int(m, "count", count))


@dataclass(frozen=True, eq=False)
class Health(Message):
    """The monitor's verdict on one state (SPEC §5, §7)."""

    TYPE: ClassVar[str] = "Health"
    robot: str = _scalar("str", "robot name")
    seq: int = _scalar("int", "seq of the state checked")
    stamp: float = _scalar("float", "stamp of the state checked, s")
    ok: bool = _scalar("bool", "no violation in this state")
    suspects: np.ndarray = _arr(_I8, (None,), "feature ids blamed, int64[]")
    violations: tuple[Violation, ...] = field(
        default=(), metadata={"kind": "violations", "doc": "violations found in this state"})
    statistics: dict[str, float] = field(
        default_factory=dict, metadata={"kind": "stats",
                                        "doc": "named statistics: nees_pose, nis, bounds…"})
    verdict: str = field(default="ok", metadata={
        "kind": "str", "choices": ("ok", "fault", "tuning"),
        "doc": "the robot's verdict now (not only this state): ok / fault (a covariance "
               "theorem broken: an estimator fault) / tuning (only NEES/NIS outside their "
               "bands: inconsistent tuning or model mismatch); docs/monitor.md"})
    verdict_since: int | None = _scalar("int", "seq where the current verdict began",
                                        optional=True)
    standing: tuple[Violation, ...] = field(
        default=(), metadata={"kind": "violations",
                              "doc": "the violations that keep the verdict up (each once, "
                                     "with first_step and count)"})


@dataclass(frozen=True, eq=False)
class CameraFrame(Message):
    """One encoded camera image."""

    TYPE: ClassVar[str] = "CameraFrame"
    camera: str = _scalar("str", "camera name")
    seq: int = _scalar("int", "frame number")
    stamp: float = _scalar("float", "capture time, s")
    encoding: str = _scalar("str", "image codec", choices=("jpeg",))
    width: int = _scalar("int", "pixels")
    height: int = _scalar("int", "pixels")
    data: bytes = _scalar("bytes", "the encoded image")


@dataclass(frozen=True, eq=False)
class Registration(Message):
    """Where the map frame sits in a camera, with that camera's intrinsics."""

    TYPE: ClassVar[str] = "Registration"
    camera: str = _scalar("str", "camera name")
    robot: str = _scalar("str", "robot name")
    stamp: float = _scalar("float", "time of the frame it was computed from, s")
    K: np.ndarray = _arr(_F8, (3, 3), "camera matrix, pixels")
    dist: np.ndarray = _arr(_F8, (None,), "OpenCV distortion coefficients")
    width: int = _scalar("int", "image width, pixels")
    height: int = _scalar("int", "image height, pixels")
    T_camera_from_map: np.ndarray = _arr(_F8, (4, 4), "map frame → camera frame, m")
    reprojection_error_px: float = _scalar("float", "RMS reprojection error of the marker, px")
    status: str = field(default="registered", metadata={
        "kind": "str", "doc": "registered / tracking / marker not found …"})
    epoch: int | None = _scalar(
        "int", "optional: the epoch of the map this registration is for (SPEC §7a: a new "
        "map has a new frame); absent: whichever map the camera saw the robot start",
        optional=True, range=_UINT64)
    reason: str | None = _scalar(
        "str", "optional: why this registration was made: 'start', 'new map', or "
        "'requested by …' (who asked, as the request said)", optional=True)
    moved_m: float | None = _scalar(
        "float", "optional: how far this registration moved the map origin from the "
        "previous one, m", optional=True)
    moved_deg: float | None = _scalar(
        "float", "optional: how far it turned the map frame, degrees", optional=True)


@dataclass(frozen=True, eq=False)
class CameraPose(Message):
    """Pose of a moving camera in the world (tracker or fiducial board)."""

    TYPE: ClassVar[str] = "CameraPose"
    camera: str = _scalar("str", "camera name")
    stamp: float = _scalar("float", "time, s")
    T_world_from_camera: np.ndarray = _arr(_F8, (4, 4), "camera frame → world frame, m")


@dataclass(frozen=True, eq=False)
class CameraControl(Message):
    """A request to the registration service of the camera named in its key (docs/protocol.md)."""

    TYPE: ClassVar[str] = "CameraControl"
    COMMANDS: ClassVar[tuple[str, ...]] = ("reregister",)
    command: str = _scalar("str", "what to do: reregister (from the next frames)",
                           choices=COMMANDS)
    robot: str | None = _scalar("str", "only the service registering this robot obeys; "
                                "absent: any", optional=True)
    requester: str | None = _scalar(
        "str", "optional: who asks (a person or program, as it says; shown with the "
        "registration it causes)", optional=True)


@dataclass(frozen=True, eq=False)
class ServiceStatus(Message):
    """What one running service says about itself, answered to a ``get`` on its status key
    (``slamlens status``; docs/protocol.md)."""

    TYPE: ClassVar[str] = "ServiceStatus"
    service: str = _scalar("str", "the slamlens command it runs: router, estimator, sim …")
    name: str = _scalar("str", "its identity: the certificate name with --secure, else the "
                               "name of its role (robot-R, camera-C, monitor-R, viewer-…, "
                               "router-…)")
    host: str = _scalar("str", "host name of its machine")
    pid: int = _scalar("int", "process id on that host", range=(0, 2 ** 63 - 1))
    version: str = _scalar("str", "slamlens version")
    started: float = _scalar("float", "when it started, s since the Unix epoch")
    uptime_s: float = _scalar("float", "seconds since it started")
    state: str = _scalar("str", "what it is doing, in a few words: running, waiting for "
                                "an estimator, registered, fault …")
    robot: str | None = _scalar("str", "the robot(s) it serves, comma-separated",
                                optional=True)
    camera: str | None = _scalar("str", "the camera(s) it serves, comma-separated",
                                 optional=True)
    epoch: int | None = _scalar("int", "the map epoch it is on (SPEC §7a)", optional=True,
                                range=_UINT64)
    counts: dict[str, float] = field(
        default_factory=dict, metadata={"kind": "stats",
                                        "doc": "running totals: states, frames, inputs …; "
                                               "the first is its main output"})
    rates: dict[str, float] = field(
        default_factory=dict, metadata={"kind": "stats",
                                        "doc": "per second over the last few seconds, one per "
                                               "count"})
    dropped: int = _scalar("int", "messages it discarded: malformed, foreign or refused",
                           default=0, range=_UINT64)
    lost: int = _scalar("int", "samples it knows it missed and could not recover",
                        default=0, range=_UINT64)


def _bin_header(length: int) -> bytes:
    """msgpack's bin 8/16/32 header for ``length`` bytes (what Packer.pack(bytes) writes)."""
    if length < 1 << 8:
        return b"\xc4" + length.to_bytes(1, "big")
    if length < 1 << 16:
        return b"\xc5" + length.to_bytes(2, "big")
    return b"\xc6" + length.to_bytes(4, "big")


#: bytes after the format byte of each fixed-size msgpack type (nil, bools, numbers, fixext)
_FIXED_AFTER = {0xC0: 0, 0xC2: 0, 0xC3: 0, 0xCA: 4, 0xCB: 8, 0xCC: 1, 0xCD: 2, 0xCE: 4,
                0xCF: 8, 0xD0: 1, 0xD1: 2, 0xD2: 4, 0xD3: 8, 0xD4: 2, 0xD5: 3, 0xD6: 5,
                0xD7: 9, 0xD8: 17}
#: the length field's size of each sized type: bin, ext (+ 1 type byte), str
_SIZED = {0xC4: 1, 0xC5: 2, 0xC6: 4, 0xC7: 1, 0xC8: 2, 0xC9: 4, 0xD9: 1, 0xDA: 2, 0xDB: 4}
#: the count field's size of each container type: array16/32, map16/32 (a map: 2 per entry)
_COUNTED = {0xDC: (2, 1), 0xDD: (4, 1), 0xDE: (2, 2), 0xDF: (4, 2)}
#: items a peek walks before it hands the payload to msgpack itself (a hostile flat list)
_PEEK_ITEMS = 100_000


class _NotWalked(SlamlensError):
    """The payload is not one the peek walks (malformed, or beyond _PEEK_ITEMS items)."""


def _skip(buf: memoryview, pos: int, budget: list[int]) -> int:
    """The offset just past the msgpack object at ``pos`` (its bytes are not copied)."""
    pending = 1
    end = len(buf)
    while pending:
        if pos >= end or budget[0] <= 0:
            raise _NotWalked
        budget[0] -= 1
        pending -= 1
        b = buf[pos]
        pos += 1
        if b <= 0x7F or b >= 0xE0:  # fixint
            continue
        if b <= 0x8F:  # fixmap
            pending += 2 * (b & 0x0F)
        elif b <= 0x9F:  # fixarray
            pending += b & 0x0F
        elif b <= 0xBF:  # fixstr
            pos += b & 0x1F
        elif b in _FIXED_AFTER:
            pos += _FIXED_AFTER[b]
        elif b in _SIZED:
            width = _SIZED[b]
            pos += width + int.from_bytes(buf[pos:pos + width], "big") + (b in (0xC7, 0xC8, 0xC9))
        elif b in _COUNTED:
            width, per = _COUNTED[b]
            pending += per * int.from_bytes(buf[pos:pos + width], "big")
            pos += width
        else:  # 0xC1: never used
            raise _NotWalked
    if pos > end:
        raise _NotWalked
    return pos


def _map_header(view: memoryview, pos: int) -> tuple[int, int]:
    """(entries, offset of the first key) of the msgpack map at ``pos``."""
    b = view[pos] if pos < len(view) else 0xC1
    if 0x80 <= b <= 0x8F:
        return b & 0x0F, pos + 1
    if b in (0xDE, 0xDF):
        width = _COUNTED[b][0]
        return int.from_bytes(view[pos + 1:pos + 1 + width], "big"), pos + 1 + width
    raise _NotWalked


def _entries(view: memoryview, pos: int, budget: list[int]
             ) -> Iterator[tuple[Any, int, int]]:
    """(key, value start, value end) of each entry of the msgpack map at ``pos``; the
    keys decoded, the values only stepped over. The offset past the map is the last
    value end (``pos`` past the header for an empty map)."""
    count, pos = _map_header(view, pos)
    for _ in range(count):
        key_end = _skip(view, pos, budget)
        value_end = _skip(view, key_end, budget)
        yield _unpack(view, pos, key_end), key_end, value_end
        pos = value_end


def _unpack(view: memoryview, start: int, end: int) -> Any:
    """msgpack's value of view[start:end]."""
    return msgpack.unpackb(view[start:end], raw=False, strict_map_key=False)


def _peek_walked(view: memoryview, names: tuple[str, ...]) -> dict[str, Any]:
    """peek_fields by walking the top-level map over ``view``: only the fields wanted (and
    the keys) are decoded, every other value is stepped over in place."""
    return {key: _unpack(view, start, end) for key, start, end in
            _entries(view, 0, [_PEEK_ITEMS]) if isinstance(key, str) and key in names}


#: a payload at least this large is unpacked in place (:func:`unpack_in_place`)
IN_PLACE_ABOVE = 1 << 20
#: a bin at least this large, one level down (an array's data), stays in the payload
IN_PLACE_BIN = 1 << 16
_NOT_UNPACKED = object()
#: the length field's size of bin 8/16/32
_BIN_WIDTH = {0xC4: 1, 0xC5: 2, 0xC6: 4}


def _in_place(view: memoryview, start: int, end: int, budget: list[int]) -> Any:
    """The msgpack value at view[start:end]; a map's large bin values as views."""
    if not (0x80 <= view[start] <= 0x8F or view[start] in (0xDE, 0xDF)):
        return _unpack(view, start, end)
    out: dict[Any, Any] = {}
    last = _map_header(view, start)[1]  # an empty map ends after its header
    for key, value_start, last in _entries(view, start, budget):
        width = _BIN_WIDTH.get(view[value_start], 0)
        if width and last - value_start - 1 - width >= IN_PLACE_BIN:
            out[key] = view[value_start + 1 + width:last]  # read-only: bytes underneath
        else:
            out[key] = _unpack(view, value_start, last)
    if last != end:
        raise _NotWalked
    return out


def unpack_in_place(payload: bytes) -> Any:
    """``msgpack.unpackb(payload)`` of a map, but the large bins of its values' maps (the
    arrays' ``data``, at least :data:`IN_PLACE_BIN` bytes) are read-only memoryviews into
    ``payload`` instead of copies: a 32 MB state's covariance is decoded without copying
    it. Anything the walk does not take (not a map, malformed, trailing bytes, a huge flat
    list) is :data:`_NOT_UNPACKED`, for msgpack itself to decode or refuse."""
    view = memoryview(payload)
    budget = [_PEEK_ITEMS]
    try:
        out: dict[Any, Any] = {}
        last = _map_header(view, 0)[1]  # an empty map ends after its header
        for key, value_start, last in _entries(view, 0, budget):
            out[key] = _in_place(view, value_start, last, budget)
        if last != len(view):
            raise _NotWalked  # msgpack refuses trailing bytes (ExtraData)
        return out
    except Exception:  # malformed, or not walked: msgpack itself decides
        return _NOT_UNPACKED


def peek_fields(payload: bytes | bytearray | memoryview,
                names: tuple[str, ...]) -> dict[str, Any]:
    """The top-level fields ``names`` of a msgpack map, without decoding the others.

    For consumers that need a state's header (seq, epoch, input_stamp) and not its map: the
    big arrays are stepped over in place, never copied (a 32 MB state at n = 1000 is peeked
    in microseconds; msgpack's own Unpacker would copy it into its buffer first). A payload
    the walk does not take (malformed, or a huge flat list) goes to msgpack's Unpacker, so
    the answer is always msgpack's. Raises MessageError if the payload is not a map.
    """
    view = memoryview(payload).cast("B")
    try:
        return _peek_walked(view, names)
    except Exception:  # malformed, or not walked: msgpack itself decides (same answer or
        pass  # the same error as ever)
    unpacker = msgpack.Unpacker(raw=False, strict_map_key=False,
                                max_buffer_size=max(len(view), 1))
    unpacker.feed(view)
    out: dict[str, Any] = {}
    try:
        for _ in range(unpacker.read_map_header()):
            key = unpacker.unpack()
            if key in names and isinstance(key, str):
                out[key] = unpacker.unpack()
            else:
                unpacker.skip()
    except Exception as exc:
        raise MessageError("Message", "<payload>", "a msgpack map",
                           f"undecodable bytes ({type(exc).__name__})") from None
    return out


MESSAGE_TYPES: tuple[type[Message], ...] = (
    Odometry, Observations, Truth, SlamState, Health, CameraFrame, Registration, CameraPose,
    CameraControl, ServiceStatus, StateSummary,
)
