"""The base of every message: validation on construction, msgpack encoding, decoding.

A message is a frozen dataclass whose fields are declared with
:func:`~slamlens.common.fields.array_field` / :func:`~slamlens.common.fields.scalar_field`;
each field's kind (:mod:`slamlens.common.fields`) validates, encodes and decodes it, and a
message adds its cross-field checks in ``_check``. On the wire a message is a msgpack map
with ``"schema": 1``; decoders ignore unknown fields, and anything malformed raises
:class:`~slamlens.common.errors.MessageError` naming the field (``Type.field: expected X,
got Y``). Arrays held by a message are read-only copies, and equality compares their
contents.

Decoding has two paths with one outcome: a map whose every value has its field's exact
wire type is accepted in one pass (:meth:`Message._from_dict_fast`); anything else — and
anything the fast path does not vouch for — goes through the full validation
(:meth:`Message._from_dict_full`), which accepts or rejects it and words the error. The fast
path only ever accepts, and only what the full path accepts as the same message
(``tests/unit/test_decode_fast.py``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, Self

import msgpack
import numpy as np

from slamlens.common.arrays import values_equal
from slamlens.common.errors import MessageError
from slamlens.common.fields import REJECT, Spec
from slamlens.common.msgpack_walk import NOT_UNPACKED, bin_header, unpack_in_place

SCHEMA = 1
#: binary values of at least this many bytes are written as parts of their own (wire_parts)
BIG_BINARY = 1 << 20
#: a payload at least this large is unpacked in place (arrays as views into it)
IN_PLACE_ABOVE = 1 << 20
_add_reduce = np.add.reduce
#: a field default the decoder's fast path does not vouch for (it leaves the message to
#: the full path)
_NOT_VOUCHED = object()
_SPECS: dict[type, tuple[Spec, ...]] = {}
_DEFAULTS: dict[type, tuple[bool, ...]] = {}
_FAST_PLANS: dict[type, tuple[dict[str, Any], dict[str, Spec], int] | None] = {}


class Message:
    """Base of every message: validation, freezing, msgpack, value equality."""

    TYPE: ClassVar[str] = "Message"
    #: array fields sent flattened to one axis (the decoder restores the shape)
    _FLAT: ClassVar[tuple[str, ...]] = ()

    # -- construction -------------------------------------------------------------
    @classmethod
    def _specs(cls) -> tuple[Spec, ...]:
        """Per field, what its kind needs, read once per class (a hot path)."""
        specs = _SPECS.get(cls)
        if specs is None:
            specs = _SPECS[cls] = tuple(Spec(f.name, f.metadata)
                                        for f in dataclasses.fields(cls))  # type: ignore
        return specs

    def __post_init__(self) -> None:
        setattr_ = object.__setattr__
        message = self.TYPE
        for spec in self._specs():
            value = getattr(self, spec.name)
            if value is None and (spec.optional or spec.kind.none_ok):
                continue
            checked = spec.kind.construct(message, spec, value)
            if checked is not value:
                setattr_(self, spec.name, checked)
        self._check()

    def _check(self) -> None:
        """Cross-field checks (shapes consistent with counts and so on)."""

    # -- equality -----------------------------------------------------------------
    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(values_equal(getattr(self, s.name), getattr(other, s.name))
                   for s in self._specs())

    __hash__ = None  # type: ignore[assignment]

    # -- wire format --------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return self._wire_dict(views=False)

    def _wire_dict(self, *, views: bool) -> dict[str, Any]:
        """The wire map; with ``views`` large arrays' data are the arrays' own buffers
        (a ``bytearray`` behind the array, or a memoryview), not copies."""
        out: dict[str, Any] = {"schema": SCHEMA}
        flat = self._FLAT
        for spec in self._specs():
            value = getattr(self, spec.name)
            if (value is None and (spec.optional or spec.kind.none_ok)) \
                    or not spec.kind.on_wire:
                continue
            if flat and spec.name in flat:
                value = value.reshape(-1)
            out[spec.name] = spec.kind.encode(spec, value, views)
        return out

    def wire_parts(self) -> list[bytes | bytearray | memoryview]:
        """The msgpack encoding as consecutive parts: ``b"".join(parts) == to_bytes()``.

        Arrays of at least :data:`BIG_BINARY` bytes are parts of their own, their own memory
        (not copied), so a large message is copied once, wherever it goes (e.g. into shared
        memory). msgpack's packer would copy a 32 MB state through a growing buffer.
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
            small.append(bin_header(len(data)))
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
        raw: Any = NOT_UNPACKED
        if type(payload) is bytes and len(payload) >= IN_PLACE_ABOVE:
            raw = unpack_in_place(payload)  # the large arrays as views, not copies
        try:
            if raw is NOT_UNPACKED:
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
        """The message of a decoded msgpack map; raises MessageError naming the field
        (the fast path first, the full path for whatever it does not vouch for)."""
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

    # -- the fast path ------------------------------------------------------------------
    @classmethod
    def _fast_plan(cls) -> tuple[dict[str, Any], dict[str, Spec], int] | None:
        """What the fast path needs: the fields' defaults in field order (required ones
        :data:`_NOT_VOUCHED`), the specs by name, and how many fields are required; None
        if the class builds itself in ways the fast path does not repeat."""
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
            by_name: dict[str, Spec] = {}
            for spec, f in zip(cls._specs(), dataclasses.fields(cls),  # type: ignore
                               strict=True):
                default = _default_of(f)
                if default is not _NOT_VOUCHED and not (
                        (default is None and spec.optional)
                        or spec.kind.default_valid(spec, default)):
                    default = _NOT_VOUCHED
                defaults[spec.name] = default
                spec.own_shape = spec.dtype is not None and (shaped is None
                                                              or spec.name in shaped)
                by_name[spec.name] = spec
            plan = (defaults, by_name,
                    sum(1 for v in defaults.values() if v is _NOT_VOUCHED))
        _FAST_PLANS[cls] = plan
        return plan

    @classmethod
    def _from_dict_fast(cls, raw: Any, options: Mapping[str, Any]) -> Self | None:
        """The message, if every field is of its exact wire type and valid; else None
        (the full path decides, and words any rejection). Never raises."""
        plan = cls._fast_plan()
        if plan is None or type(raw) is not dict or raw.get("schema") != SCHEMA:
            return None
        defaults, specs, required = plan
        values = dict(defaults)  # field order; the wire's values replace the defaults
        sums = 0.0  # of every float array: finite iff each entry is (barring overflow)
        try:
            for name, value in raw.items():
                spec = specs.get(name)
                if spec is None or value is None or not spec.kind.on_wire:  # absent
                    continue
                shape = cls._wire_shape(name, raw, spec.shape) if spec.own_shape \
                    else spec.shape
                value = spec.kind.decode_fast(spec, value, shape)
                if value is REJECT:
                    return None
                if spec.floats:
                    sums += _add_reduce(value, None)
                if values[name] is _NOT_VOUCHED:
                    required -= 1
                values[name] = value
            if required or not math.isfinite(sums):  # a field missing; NaN, ∞, overflow
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

    # -- the full path ------------------------------------------------------------------
    @classmethod
    def _from_dict_full(cls, raw: Any, **options: Any) -> Self:
        """Decode with every field validated by the constructor (the reference path)."""
        if not isinstance(raw, Mapping):
            raise MessageError(cls.TYPE, "<payload>", "a msgpack map", type(raw).__name__)
        schema = raw.get("schema")
        if schema != SCHEMA:
            raise MessageError(cls.TYPE, "schema", str(SCHEMA), repr(schema))
        kwargs: dict[str, Any] = {}
        for spec, has_default in zip(cls._specs(), cls._defaults(), strict=True):
            value = raw.get(spec.name) if spec.kind.on_wire else None
            if value is None:
                if has_default:
                    continue
                raise MessageError(cls.TYPE, spec.name, "present", "missing")
            kwargs[spec.name] = spec.kind.decode_full(
                cls.TYPE, spec, value, cls._wire_shape(spec.name, raw, spec.shape))
        return cls._from_wire(kwargs, **options)

    @classmethod
    def _defaults(cls) -> tuple[bool, ...]:
        """Per field, whether it has a default (may be absent on the wire)."""
        cached = _DEFAULTS.get(cls)
        if cached is None:
            cached = _DEFAULTS[cls] = tuple(_default_of(f) is not _NOT_VOUCHED
                                            for f in dataclasses.fields(cls))  # type: ignore
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


def _default_of(f: dataclasses.Field[Any]) -> Any:
    """A field's default (a fresh one of a factory), or :data:`_NOT_VOUCHED` if required."""
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    if f.default is not dataclasses.MISSING:
        return f.default
    return _NOT_VOUCHED


def count_check(message: str, name: str, array: np.ndarray | None, expected: int,
                what: str) -> None:
    """An array field's first axis holds ``expected`` entries (a cross-field check)."""
    if array is not None and array.shape[0] != expected:
        raise MessageError(message, name, f"{expected} entries ({what})",
                           f"{array.shape[0]}")
