"""Little-endian plain CDR (XCDR1) as ROS 2 serialises it, written fast (pure).

A payload is the encapsulation header ``00 01 00 00`` and the body; every primitive is
aligned to its own size counted from the body's start (the header does not count), a
string is a uint32 length (with its NUL) and the bytes and NUL, a sequence a uint32 count
and the elements (aligned only if there is one).

:class:`Writer` writes one message field by field. Arrays of messages of one shape (the
markers of a MarkerArray, the poses of a Path) are written by :func:`repeat` without a
Python loop: the element is written once as a template at each alignment phase it can start
at, and the fields that differ (ids, poses, colours …) are patched in with numpy. The
result is the bytes a field-by-field writer gives (tests read them back with ``rosbags``).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from slamlens.services.ros2.wire import CDR_LE

_I32, _U32, _I64, _U64 = struct.Struct("<i"), struct.Struct("<I"), struct.Struct("<q"), \
    struct.Struct("<Q")
_F32, _F64 = struct.Struct("<f"), struct.Struct("<d")


class Writer:
    """One CDR payload (or, with ``phase``, a piece of one starting at that body offset)."""

    def __init__(self, *, phase: int | None = None) -> None:
        if phase is None:
            self.buf = bytearray(CDR_LE)
            self._base = -len(CDR_LE)
        else:
            self.buf = bytearray()
            self._base = phase
        self.marks: dict[str, int] = {}

    @property
    def offset(self) -> int:
        """The body offset of the next byte."""
        return self._base + len(self.buf)

    def align(self, n: int) -> None:
        pad = -self.offset % n
        if pad:
            self.buf += bytes(pad)

    def mark(self, name: str | None) -> None:
        if name is not None:
            self.marks[name] = len(self.buf)

    def bool(self, value: bool) -> None:
        self.buf.append(1 if value else 0)

    def u8(self, value: int) -> None:
        self.buf.append(value & 0xFF)

    def i32(self, value: int, mark: str | None = None) -> None:
        self.align(4)
        self.mark(mark)
        self.buf += _I32.pack(value)

    def u32(self, value: int) -> None:
        self.align(4)
        self.buf += _U32.pack(value)

    def i64(self, value: int) -> None:
        self.align(8)
        self.buf += _I64.pack(value)

    def u64(self, value: int) -> None:
        self.align(8)
        self.buf += _U64.pack(value)

    def f32(self, value: float) -> None:
        self.align(4)
        self.buf += _F32.pack(value)

    def f64(self, value: float) -> None:
        self.align(8)
        self.buf += _F64.pack(value)

    def f64s(self, values: np.ndarray | tuple[float, ...], mark: str | None = None) -> None:
        """Consecutive float64 fields (a Point, a Pose, a 36-element covariance)."""
        self.align(8)
        self.mark(mark)
        self.buf += np.asarray(values, dtype="<f8").tobytes()

    def f32s(self, values: np.ndarray | tuple[float, ...], mark: str | None = None) -> None:
        self.align(4)
        self.mark(mark)
        self.buf += np.asarray(values, dtype="<f4").tobytes()

    def string(self, text: str, mark: str | None = None) -> None:
        data = text.encode()
        self.u32(len(data) + 1)
        self.mark(mark)
        self.buf += data + b"\x00"

    def sequence(self, values: np.ndarray, dtype: str, width: int = 1) -> None:
        """A sequence of ``len(values)`` elements of ``width`` primitives of ``dtype``
        (``<f8`` with width 3: geometry_msgs/Point[])."""
        array = np.ascontiguousarray(values, dtype=dtype).reshape(-1)
        count = array.size // width
        self.u32(count)
        if count:
            self.align(np.dtype(dtype).itemsize)
            self.buf += array.tobytes()

    def stamp(self, stamp_ns: int, mark: str | None = None) -> None:
        """builtin_interfaces/Time (int32 sec, uint32 nanosec)."""
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        self.i32(sec, mark=mark)
        self.u32(nsec)

    def header(self, stamp_ns: int, frame_id: str) -> None:
        """std_msgs/Header."""
        self.stamp(stamp_ns)
        self.string(frame_id)

    def bytes(self) -> bytes:
        return bytes(self.buf)


def stamp_ns(seconds: float) -> int:
    """Seconds (a slamlens stamp) as integer nanoseconds, rounded (whole seconds and the
    fraction apart: 1.2 × 10⁹ s × 10⁹ is beyond float64's integers)."""
    whole = math.floor(float(seconds))
    return whole * 1_000_000_000 + int(round((float(seconds) - whole) * 1e9))


@dataclass
class Template:
    """An element written once per alignment phase (0 or 4), padded to 4 bytes, with the
    byte offsets of the fields :func:`repeat` patches."""

    write: Callable[[Writer], None]
    _cache: dict[int, tuple[np.ndarray, dict[str, int]]] = field(default_factory=dict)

    def at(self, phase: int) -> tuple[np.ndarray, dict[str, int]]:
        if phase not in self._cache:
            w = Writer(phase=phase)
            self.write(w)
            w.align(4)  # the next element starts with a 4-byte field, or the payload ends
            self._cache[phase] = (np.frombuffer(w.bytes(), dtype=np.uint8), dict(w.marks))
        return self._cache[phase]


def _patch_bytes(patches: Mapping[str, np.ndarray], count: int) -> dict[str, np.ndarray]:
    return {name: np.ascontiguousarray(values).view(np.uint8).reshape(count, -1)
            for name, values in patches.items()}


def repeat(template: Template, count: int, phase: int,
           patches: Mapping[str, np.ndarray]) -> tuple[bytes, int]:
    """``count`` elements written from ``template`` starting at body offset ``phase``
    (mod 8), each with its row of every patch (arrays of ``count`` rows, little-endian),
    and the phase after them."""
    if count == 0:
        return b"", phase
    rows = _patch_bytes(patches, count)
    a, marks_a = template.at(phase % 8)
    phase_b = (phase + len(a)) % 8
    if phase_b == phase % 8 or count == 1:  # one shape for all
        out = np.empty((count, len(a)), dtype=np.uint8)
        out[:] = a
        for name, data in rows.items():
            out[:, marks_a[name]:marks_a[name] + data.shape[1]] = data
        return out.tobytes(), phase_b
    b, marks_b = template.at(phase_b)
    if (phase_b + len(b)) % 8 != phase % 8:  # the first differs, then all alike
        head, mid = repeat(template, 1, phase, {k: v[:1] for k, v in patches.items()})
        tail, end = repeat(template, count - 1, mid, {k: v[1:] for k, v in patches.items()})
        return head + tail, end
    pairs, odd = divmod(count, 2)
    out = np.empty((pairs, len(a) + len(b)), dtype=np.uint8)
    out[:, :len(a)] = a
    out[:, len(a):] = b
    for name, data in rows.items():
        width = data.shape[1]
        out[:, marks_a[name]:marks_a[name] + width] = data[0:2 * pairs:2]
        start = len(a) + marks_b[name]
        out[:, start:start + width] = data[1:2 * pairs:2]
    body = out.tobytes()
    if odd:
        last = a.copy()
        for name, data in rows.items():
            last[marks_a[name]:marks_a[name] + data.shape[1]] = data[-1]
        return body + last.tobytes(), phase_b
    return body, phase % 8
