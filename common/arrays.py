"""numpy arrays on the wire, and the validators every message uses.

docs/protocol.md: an array travels as ``{"dtype": "<f8", "shape": [...], "data": <bytes>}``,
little-endian. Decoding also accepts a plain (nested) list of numbers, which is what
a hand-written third-party client most often sends; the dtype is then the field's.
Every array a message holds is a read-only, C-contiguous copy.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from typing import Any, TypeGuard

import numpy as np

from slamlens.common.errors import MessageError

_WIRE_DTYPES = {"<f8", "<f4", "<i8", "<i4", "|u1", "<u1", "|b1"}
_DTYPES: dict[str, np.dtype] = {}
#: no message field has more axes; a deeper shape is refused before numpy sees it
MAX_DIMS = 4


def encode_array(array: np.ndarray, dtype: str, *, view: bool = False) -> dict[str, Any]:
    """Encode ``array`` as the docs/protocol.md map with the little-endian ``dtype`` given; with
    ``view`` the data is the array's own memory (its bytearray, or a memoryview), which
    msgpack packs as the same bin value without a copy first."""
    a = np.ascontiguousarray(array, dtype=np.dtype(dtype))
    if view and a.nbytes:
        own = buffer_of(a)
        return {"dtype": dtype, "shape": list(a.shape),
                "data": a.data.cast("B") if own is None else own}
    return {"dtype": dtype, "shape": list(a.shape), "data": a.tobytes()}


def bytes_backed_array(shape: tuple[int, ...], dtype: str) -> np.ndarray:
    """A new zeroed, writable array whose memory is a ``bytearray`` (its ``base``).

    A message holding it can be written out by consumers that take only bytes-like
    objects (Zenoh's shared memory, ``common/bus.py``) without another copy of the array;
    :func:`buffer_of` gives that bytearray back.
    """
    want = np.dtype(dtype)
    count = math.prod(shape)
    return np.frombuffer(bytearray(count * want.itemsize), dtype=want).reshape(shape)


class RecycledBuffers:
    """:func:`bytes_backed_array` s whose bytearrays are reused once nothing refers to
    them any more: no message, array or view (CPython's reference count says so).

    A new 32 MB bytearray (a state at n = 1000) is zero-filled and its pages faulted in on
    first write: ~3 ms and more each, measured; a reused one costs nothing. ``keep`` bounds
    the buffers held (the oldest are dropped to the garbage collector).
    """

    def __init__(self, keep: int = 4) -> None:
        self.keep = keep
        self._buffers: list[bytearray] = []
        self.reused = 0  #: arrays served from a recycled buffer

    def array(self, shape: tuple[int, ...], dtype: str) -> np.ndarray:
        """A writable array of ``shape`` (contents undefined), backed by a bytearray."""
        want = np.dtype(dtype)
        size = math.prod(shape) * want.itemsize
        for k in range(len(self._buffers)):
            # referred to only by this list (and getrefcount's argument): nothing else can
            # see it (a numpy view holds a memoryview, which refers to it)
            if len(self._buffers[k]) == size and sys.getrefcount(self._buffers[k]) <= 2:
                buf = self._buffers.pop(k)
                self._buffers.append(buf)  # newest last
                self.reused += 1
                return np.frombuffer(buf, dtype=want).reshape(shape)
        out = bytes_backed_array(shape, dtype)
        self._buffers.append(buffer_of(out))  # type: ignore[arg-type]
        if len(self._buffers) > self.keep:
            del self._buffers[0]
        return out

    def reclaim(self, array: np.ndarray, *, holders: int) -> np.ndarray | None:
        """A writable array over ``array``'s own buffer — the same memory, to change in
        place — if nothing but the caller refers to that memory: ``array`` is one of this
        pool's, referred to only by the caller's ``holders`` references (its variables and
        attributes; the argument is counted here), with no view, memoryview or other array
        on its buffer. Else None (something may still read it: copy instead). The caller
        must drop ``array`` and keep only what is returned."""
        buf = buffer_of(array)
        if buf is None or not any(b is buf for b in self._buffers):
            return None
        root = array.base  # the 1-D array np.frombuffer made (every view's base)
        view = root.base if isinstance(root, np.ndarray) else None  # its memoryview
        # the counts: getrefcount's argument, this frame's name, then who else holds it
        if (not isinstance(view, memoryview)
                or sys.getrefcount(array) > holders + 2  # the argument, getrefcount's
                or sys.getrefcount(root) > 3  # array.base, `root`, getrefcount's
                or sys.getrefcount(view) > 3  # root.base, `view`, getrefcount's
                or sys.getrefcount(buf) > 4):  # the list, the memoryview, `buf`, getrefcount's
            return None
        self.reused += 1
        return np.frombuffer(buf, dtype=array.dtype).reshape(array.shape)


def buffer_of(array: np.ndarray) -> bytes | bytearray | None:
    """The ``bytes``/``bytearray`` holding exactly ``array``'s data in order, or None."""
    root: Any = array
    while isinstance(root, np.ndarray) and root.base is not None:
        root = root.base
    if isinstance(root, memoryview):
        root = root.obj
    if isinstance(root, (bytes, bytearray)) and array.flags.c_contiguous \
            and len(root) == array.nbytes \
            and np.frombuffer(root, dtype=np.uint8).ctypes.data == array.ctypes.data:
        return root
    return None


def _describe(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def is_frozen_view(data: Any) -> TypeGuard[memoryview]:
    """A read-only byte memoryview (into an immutable payload: slamlens.common.messages'
    ``unpack_in_place``), taken as array data without a copy, as ``bytes`` is."""
    return (type(data) is memoryview and data.readonly and data.ndim == 1
            and data.format == "B" and isinstance(data.obj, bytes))


def decode_array(
    raw: Any, *, message: str, field: str, dtype: str, shape: Sequence[int | None],
    finite: bool = True,
) -> np.ndarray:
    """Decode and validate one array field.

    ``shape`` entries of ``None`` accept any length along that axis. Float arrays must be
    finite (unless ``finite=False``: the caller checks). Raises :class:`MessageError`
    naming the field on any mismatch.
    """
    want = _DTYPES.get(dtype) or _DTYPES.setdefault(dtype, np.dtype(dtype))
    # the common case first (a well-formed map of the field's own dtype): checked in full,
    # in a few operations, without a copy — every state a consumer decodes goes this way
    array = well_formed(raw, want, dtype, shape)
    if array is not None:
        if finite and want.kind == "f" and array.size and not (
                math.isfinite(float(array.sum())) or np.isfinite(array).all()):
            raise MessageError(message, field, "finite values", "NaN or infinity")
        return array  # read-only: a view of immutable bytes
    if isinstance(raw, dict):
        array = _from_wire_map(raw, message, field, shape)
    elif isinstance(raw, (list, tuple)):
        array = _from_list(raw, message, field)
    else:
        raise MessageError(message, field, "an array map or list", type(raw).__name__)
    array = _as_dtype(array, want, message, field)
    dims: tuple[int, ...] = array.shape
    if len(shape) != array.ndim or any(
        s is not None and s != d for s, d in zip(shape, dims, strict=False)
    ):
        shown = ["n" if s is None else s for s in shape]
        raise MessageError(message, field, f"shape {shown}", str(list(array.shape)))
    if finite and want.kind == "f" and not np.isfinite(array).all():
        raise MessageError(message, field, "finite values", "NaN or infinity")
    array.setflags(write=False)
    return array


def well_formed(raw: Any, want: np.dtype, dtype: str,
                shape: Sequence[int | None]) -> np.ndarray | None:
    """The array of a map of exactly the field's dtype, shape and data size (a view of
    its bytes), else None (the full checks decide)."""
    if type(raw) is not dict or raw.get("dtype") != dtype:
        return None
    wire_shape, data = raw.get("shape"), raw.get("data")
    if not (type(data) is bytes or is_frozen_view(data)) or type(wire_shape) is not list \
            or len(wire_shape) != len(shape):
        return None
    count = 1
    for d, s in zip(wire_shape, shape, strict=True):
        if type(d) is not int or d < 0 or (s is not None and d != s):
            return None
        count *= d
    if len(data) != count * want.itemsize:
        return None
    return np.frombuffer(data, dtype=want).reshape(wire_shape)


def _from_wire_map(raw: dict[Any, Any], message: str, field: str,
                   shape: Sequence[int | None]) -> np.ndarray:
    """The array of a ``{"dtype", "shape", "data"}`` map in its wire dtype, validated."""
    try:
        wire_dtype = raw["dtype"]
        wire_shape = raw["shape"]
        data = raw["data"]
    except KeyError as exc:
        raise MessageError(message, field, "array map with dtype, shape, data",
                           f"missing {exc.args[0]!r}") from None
    if not isinstance(wire_dtype, str) or wire_dtype not in _WIRE_DTYPES:
        raise MessageError(message, field, "little-endian dtype such as '<f8'",
                           _describe(wire_dtype))
    if not isinstance(wire_shape, (list, tuple)) or not all(
        isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in wire_shape
    ):
        raise MessageError(message, field, "shape as a list of non-negative ints",
                           _describe(wire_shape))
    if len(wire_shape) != len(shape):
        shown = ["n" if s is None else s for s in shape]
        raise MessageError(message, field, f"shape {shown}", f"{len(wire_shape)} dimensions")
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise MessageError(message, field, "data as bytes", type(data).__name__)
    wire = np.dtype(wire_dtype)
    count = math.prod(wire_shape)
    if len(data) != count * wire.itemsize:
        raise MessageError(message, field,
                           f"{count * wire.itemsize} data bytes for shape {list(wire_shape)}",
                           f"{len(data)} bytes")
    # a read-only view of the (immutable) bytes: no copy when the dtype is the field's
    return np.frombuffer(data if isinstance(data, bytes) or is_frozen_view(data)
                         else bytes(data), dtype=wire).reshape(wire_shape)


def _from_list(raw: list[Any] | tuple[Any, ...], message: str, field: str) -> np.ndarray:
    """The array of a (nested) list of numbers: rectangular, at most MAX_DIMS deep."""
    depth = 0
    inner: Any = raw
    while isinstance(inner, (list, tuple)) and depth <= MAX_DIMS:
        depth += 1
        inner = inner[0] if inner else None
    if depth > MAX_DIMS:
        raise MessageError(message, field, f"at most {MAX_DIMS} nested lists", "a deeper list")
    try:
        array = np.asarray(raw)
    except (ValueError, TypeError, OverflowError):
        raise MessageError(message, field, "a rectangular list of numbers",
                           "a ragged or mixed list") from None
    if array.size and array.dtype.kind not in "biuf":
        raise MessageError(message, field, "numbers", f"elements of kind {array.dtype}")
    return array


def _as_dtype(array: np.ndarray, want: np.dtype, message: str, field: str) -> np.ndarray:
    """``array`` in the field's dtype, C-contiguous, owned (integers from floats only if
    integral and within 64 bits)."""
    if array.dtype != want:
        if want.kind in "iu" and array.dtype.kind == "f":
            if array.size and not np.all(np.isfinite(array) & (array == np.round(array))):
                raise MessageError(message, field, "integers", "non-integral values")
            if array.size and float(np.max(np.abs(array))) >= 2.0 ** 63:
                raise MessageError(message, field, "64-bit integers", "values beyond ±2⁶³")
        if want.kind == "b" and array.dtype.kind not in "bui":
            raise MessageError(message, field, "booleans", str(array.dtype))
        return np.array(array, dtype=want, order="C")
    if not array.flags.c_contiguous or array.flags.writeable:
        return np.array(array, dtype=want, order="C")  # a list's array: own, then freeze
    return array


def values_equal(a: Any, b: Any) -> bool:
    """Equality for dataclass fields that may hold arrays (``==`` on arrays is elementwise)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (a is not None and b is not None and a.shape == b.shape
                and bool(np.array_equal(a, b)))
    return bool(a == b)


def frozen_array(value: Any, dtype: str | np.dtype) -> np.ndarray:
    """A read-only C-contiguous copy, for message construction from Python values."""
    array = np.array(value, dtype=dtype, order="C")
    array.setflags(write=False)
    return array


def check_finite(message: str, field: str, value: float) -> float:
    """Validate a scalar float field."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise MessageError(message, field, "a number", type(value).__name__)
    number = float(value)
    if not math.isfinite(number):
        raise MessageError(message, field, "a finite number", repr(number))
    return number


def check_int(message: str, field: str, value: Any) -> int:
    """Validate an integer scalar field."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise MessageError(message, field, "an integer", type(value).__name__)
    return int(value)


def check_str(message: str, field: str, value: Any, *, choices: Sequence[str] | None = None) -> str:
    """Validate a string field, optionally one of ``choices``."""
    if not isinstance(value, str):
        raise MessageError(message, field, "a string", type(value).__name__)
    if choices is not None and value not in choices:
        raise MessageError(message, field, f"one of {list(choices)}", repr(value))
    return value


def check_symmetric(message: str, field: str, matrix: np.ndarray, *, rtol: float = 1e-6) -> None:
    """A covariance must be square and symmetric to ``rtol`` of its largest entry."""
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1]:
        raise MessageError(message, field, "a square matrix", str(list(matrix.shape)))
    if matrix.size == 0:
        return
    scale = float(np.max(np.abs(matrix)))
    asym = float(np.max(np.abs(matrix - matrix.T)))
    if asym > rtol * max(scale, 1e-300):
        raise MessageError(message, field, f"symmetric within {rtol:g} relative",
                           f"asymmetry {asym:.3g} at scale {scale:.3g}")
