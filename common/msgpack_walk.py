"""Reading msgpack maps without decoding what is not needed.

* :func:`peek_fields`: a few top-level fields of a map (a state's header) without decoding
  or copying the others (a 32 MB state's covariance is stepped over in place);
* :func:`unpack_in_place`: a whole map, but its large binary values (arrays' ``data``) as
  read-only views into the payload instead of copies;
* :func:`bin_header`: msgpack's header of a binary value, for writers that send a large
  array's bytes as a part of their own (``Message.wire_parts``).

Anything the walk does not take (malformed, a huge flat list, trailing bytes) is left to
msgpack itself, so every answer is msgpack's.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import msgpack

from slamlens.common.errors import MessageError, SlamlensError


def bin_header(length: int) -> bytes:
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
NOT_UNPACKED = object()  #: what unpack_in_place returns for what it does not walk
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
    list) is :data:`NOT_UNPACKED`, for msgpack itself to decode or refuse."""
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
        return NOT_UNPACKED


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

