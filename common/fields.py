"""The kinds of message fields: one object per kind says how a field of that kind is
declared, validated on construction, encoded, and decoded on the full and the fast path.

A message field is a dataclass field whose metadata names its kind and what the kind needs
(dtype and shape of an array, the range of an integer, the choices of a string, …):
:func:`array_field` and :func:`scalar_field` declare them. :class:`Spec` is that metadata
read once per class; the codec (:mod:`slamlens.common.codec`) walks a message's specs and
asks each field's kind. Adding a kind means one new :class:`FieldKind` here, registered in
:data:`KINDS`.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from collections.abc import Iterator, Mapping
from dataclasses import field
from typing import Any

import numpy as np

from slamlens.common.arrays import (
    check_finite,
    check_int,
    check_str,
    decode_array,
    encode_array,
    frozen_array,
    well_formed,
)
from slamlens.common.errors import MessageError

INT64 = (-(2 ** 63), 2 ** 63 - 1)
UINT64 = (0, 2 ** 64 - 1)
COUNT = (0, 2 ** 63 - 1)  #: sequence numbers, counts: never negative
PIXELS = (0, 2 ** 31 - 1)  #: image widths and heights: never negative
#: what a kind's fast decoder returns for a value it does not vouch for (the full path
#: then decides, and words any rejection)
REJECT = object()
#: the one array a producer has proven finite (:func:`finite_by_construction`), on this
#: thread only
_PROVEN_FINITE: contextvars.ContextVar[object] = contextvars.ContextVar(
    "slamlens_proven_finite", default=None)


@contextlib.contextmanager
def finite_by_construction(array: np.ndarray | None) -> Iterator[None]:
    """Messages built in this block (on this thread) take ``array`` as finite without
    reading it: its producer proves it finite by how it was made. Every other check (dtype,
    shape, read-only) still runs, and every consumer's decode checks it in full.

    For the estimator's own covariance, whose kernels refuse any step that would make it
    non-finite (``ekf.Guard``, docs/estimator.md): summing a 32 MB matrix costs milliseconds
    of every state at n = 1000. ``None`` proves nothing."""
    token = _PROVEN_FINITE.set(array)
    try:
        yield
    finally:
        _PROVEN_FINITE.reset(token)


class Spec:
    """One field of a message class, as its kind needs it (read once per class)."""

    __slots__ = ("name", "kind", "dtype", "shape", "ndim", "fixed", "optional", "low",
                 "high", "choices", "record", "own_shape", "floats")

    def __init__(self, name: str, metadata: Mapping[str, Any]) -> None:
        self.name = name
        self.kind: FieldKind = KINDS[metadata["kind"]]
        dtype = metadata.get("dtype")
        self.dtype = None if dtype is None else np.dtype(dtype)
        self.shape: tuple[int | None, ...] = tuple(metadata.get("shape", ()))
        self.ndim = len(self.shape)
        self.fixed = tuple((i, n) for i, n in enumerate(self.shape) if n is not None)
        self.optional = bool(metadata.get("optional"))
        self.low, self.high = metadata.get("range", INT64)
        self.choices: tuple[str, ...] | None = metadata.get("choices")
        self.record: Any = metadata.get("record")  #: the records kind's item class
        self.own_shape = False  #: the message class decides its wire shape (codec sets it)
        self.floats = self.dtype is not None and self.dtype.kind == "f"


class FieldKind:
    """How fields of one kind are validated, encoded and decoded (subclasses)."""

    #: None is a valid value even when the field is not optional (arrays: checked by the
    #: message's own cross-field checks)
    none_ok = False
    #: the field travels on the wire (a ``local`` one is held in memory only)
    on_wire = True

    def construct(self, message: str, spec: Spec, value: Any) -> Any:
        """The value the message holds for ``value`` given to its constructor (converted,
        frozen); raises MessageError naming the field."""
        return value

    def default_valid(self, spec: Spec, value: Any) -> bool:
        """Whether the constructor accepts the field's default as it is."""
        return False

    def encode(self, spec: Spec, value: Any, views: bool) -> Any:
        """The wire value (views: large arrays as their own buffers, not copies)."""
        return value

    def decode_full(self, message: str, spec: Spec, value: Any, wire_shape: tuple) -> Any:
        """The constructor's argument for a wire value (the constructor validates it)."""
        return value

    def decode_fast(self, spec: Spec, value: Any, wire_shape: tuple) -> Any:
        """The message's value for a wire value of exactly this kind's wire type and
        valid, else :data:`REJECT`. Never raises."""
        return REJECT


class _Float(FieldKind):
    def construct(self, message: str, spec: Spec, value: Any) -> Any:
        if type(value) is float and math.isfinite(value):
            return value
        return check_finite(message, spec.name, value)

    def default_valid(self, spec: Spec, value: Any) -> bool:
        return type(value) is float and math.isfinite(value)

    def decode_full(self, message: str, spec: Spec, value: Any, wire_shape: tuple) -> Any:
        return float(value) if isinstance(value, int) and not isinstance(value, bool) \
            else value

    def decode_fast(self, spec: Spec, value: Any, wire_shape: tuple) -> Any:
        return value if type(value) is float and math.isfinite(value) else REJECT


class _Int(FieldKind):
    def construct(self, message: str, spec: Spec, value: Any) -> Any:
        if type(value) is not int:
            value = check_int(message, spec.name, value)
        if not spec.low <= value <= spec.high:
            raise MessageError(message, spec.name, f"an integer in [{spec.low}, {spec.high}]",
                               str(value))
        return value

    def default_valid(self, spec: Spec, value: Any) -> bool:
        return type(value) is int and spec.low <= value <= spec.high

    def decode_fast(self, spec: Spec, value: Any, wire_shape: tuple) -> Any:
        return value if type(value) is int and spec.low <= value <= spec.high else REJECT


class _Str(FieldKind):
    def construct(self, message: str, spec: Spec, value: Any) -> Any:
        if type(value) is not str or (spec.choices is not None and value not in spec.choices):
            check_str(message, spec.name, value, choices=spec.choices)
        return value

    def default_valid(self, spec: Spec, value: Any) -> bool:
        return type(value) is str and (spec.choices is None or value in spec.choices)

    def decode_fast(self, spec: Spec, value: Any, wire_shape: tuple) -> Any:
        return value if type(value) is str and (spec.choices is None
                                                or value in spec.choices) else REJECT


class _Bool(FieldKind):
    def construct(self, message: str, spec: Spec, value: Any) -> Any:
        if not isinstance(value, bool):
            raise MessageError(message, spec.name, "a boolean", type(value).__name__)
        return value

    def default_valid(self, spec: Spec, value: Any) -> bool:
        return type(value) is bool

    def decode_fast(self, spec: Spec, value: Any, wire_shape: tuple) -> Any:
        return value if type(value) is bool else REJECT


class _Bytes(FieldKind):
    def construct(self, message: str, spec: Spec, value: Any) -> Any:
        if not isinstance(value, (bytes, bytearray, memoryview)):
            raise MessageError(message, spec.name, "bytes", type(value).__name__)
        return bytes(value)

    def decode_fast(self, spec: Spec, value: Any, wire_shape: tuple) -> Any:
        return value if type(value) is bytes else REJECT


class _Array(FieldKind):
    """A numpy array: ``{"dtype", "shape", "data"}`` on the wire (common/arrays.py), held
    read-only; float arrays must be finite."""

    none_ok = True

    def construct(self, message: str, spec: Spec, value: Any) -> Any:
        dtype = spec.dtype
        assert dtype is not None
        if isinstance(value, np.ndarray) and not value.flags.writeable \
                and value.dtype == dtype:
            array = value  # already a frozen copy (decoded, or from another message)
        else:
            array = frozen_array(value, dtype)
        dims = array.shape
        if len(dims) != spec.ndim or any(dims[i] != n for i, n in spec.fixed):
            shown = ["n" if s is None else s for s in spec.shape]
            raise MessageError(message, spec.name, f"shape {shown}", str(list(dims)))
        # the sum is finite iff every entry is (barring overflow, then check each)
        if spec.floats and array.size and value is not _PROVEN_FINITE.get() \
                and not (math.isfinite(float(array.sum())) or np.isfinite(array).all()):
            raise MessageError(message, spec.name, "finite values", "NaN or infinity")
        return array

    def default_valid(self, spec: Spec, value: Any) -> bool:
        return value is None

    def encode(self, spec: Spec, value: Any, views: bool) -> Any:
        assert spec.dtype is not None
        return encode_array(value, spec.dtype.str, view=views)

    def decode_full(self, message: str, spec: Spec, value: Any, wire_shape: tuple) -> Any:
        assert spec.dtype is not None
        # finiteness is checked once, by the constructor
        return decode_array(value, message=message, field=spec.name, dtype=spec.dtype.str,
                            shape=wire_shape, finite=False)

    def decode_fast(self, spec: Spec, value: Any, wire_shape: tuple) -> Any:
        dtype = spec.dtype
        assert dtype is not None
        # decode_array's own fast case (read-only: a view of immutable bytes); the caller
        # sums float arrays for finiteness
        array = well_formed(value, dtype, dtype.str, wire_shape)
        return REJECT if array is None else array


class _Records(FieldKind):
    """A list of maps, each one record (``Spec.record``: ``to_dict``/``from_dict``)."""

    none_ok = True

    def default_valid(self, spec: Spec, value: Any) -> bool:
        return value is None or value == ()

    def encode(self, spec: Spec, value: Any, views: bool) -> Any:
        return [v.to_dict() for v in value]

    def decode_full(self, message: str, spec: Spec, value: Any, wire_shape: tuple) -> Any:
        if not isinstance(value, list):
            raise MessageError(message, spec.name, "a list", type(value).__name__)
        return tuple(spec.record.from_dict(v) for v in value)

    def decode_fast(self, spec: Spec, value: Any, wire_shape: tuple) -> Any:
        if type(value) is not list:
            return REJECT
        return tuple(spec.record.from_dict(v) for v in value)  # raises: the full path


class _Stats(FieldKind):
    """A map of named finite numbers."""

    none_ok = True

    def default_valid(self, spec: Spec, value: Any) -> bool:
        return value is None or value == {}

    def encode(self, spec: Spec, value: Any, views: bool) -> Any:
        return dict(value)

    def decode_full(self, message: str, spec: Spec, value: Any, wire_shape: tuple) -> Any:
        if not isinstance(value, Mapping):
            raise MessageError(message, spec.name, "a map", type(value).__name__)
        return self._numbers(message, spec, value)

    def decode_fast(self, spec: Spec, value: Any, wire_shape: tuple) -> Any:
        if type(value) is not dict:
            return REJECT
        return self._numbers("", spec, value)  # raises: the full path words it

    @staticmethod
    def _numbers(message: str, spec: Spec, value: Mapping[Any, Any]) -> dict[str, float]:
        return {str(k): check_finite(message, f"{spec.name}.{k}", v) for k, v in value.items()}


class _Local(FieldKind):
    """A value a message holds in memory only (what a consumer derived it from): never
    sent, never read from the wire, not validated."""

    none_ok = True
    on_wire = False

    def default_valid(self, spec: Spec, value: Any) -> bool:
        return value is None


#: every field kind by the name its fields' metadata gives
KINDS: dict[str, FieldKind] = {
    "float": _Float(), "int": _Int(), "str": _Str(), "bool": _Bool(), "bytes": _Bytes(),
    "array": _Array(), "records": _Records(), "stats": _Stats(), "local": _Local(),
}


def array_field(dtype: str, shape: tuple[int | None, ...], doc: str, *,
                optional: bool = False) -> Any:
    """A numpy array field of ``dtype`` (e.g. ``"<f8"``); None in ``shape`` is any size."""
    meta = {"kind": "array", "dtype": dtype, "shape": shape, "doc": doc}
    if optional:
        return field(default=None, metadata=meta)
    return field(metadata=meta)


def scalar_field(kind: str, doc: str, *, choices: tuple[str, ...] | None = None,
                 range: tuple[int, int] | None = None, optional: bool = False,
                 **kw: Any) -> Any:
    """A field of kind ``float``, ``int``, ``str``, ``bool`` or ``bytes``; ``optional``
    ones default to None (absent on the wire)."""
    meta: dict[str, Any] = {"kind": kind, "doc": doc}
    if choices is not None:
        meta["choices"] = choices
    if range is not None:
        meta["range"] = range
    if optional:
        meta["optional"] = True
        kw.setdefault("default", None)
    return field(metadata=meta, **kw)
