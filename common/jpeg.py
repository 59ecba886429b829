"""What a JPEG says it is, read from its header without decoding it (decode bombs).

A 719-byte JPEG can claim 20000 × 20000 pixels; decoding it allocates 1.2 GB. The size is
in the frame header (SOF marker), a few bytes in: :func:`jpeg_size` walks the marker
segments up to it (ITU-T T.81 B.1.1) and reads its height and width, touching no pixel.
"""

from __future__ import annotations

from slamlens.common.errors import SlamlensError


class JpegError(SlamlensError):
    """The data is not a JPEG whose frame header can be read."""


# SOF0-SOF15 carry the frame size; 0xC4 (DHT), 0xC8 (JPG extension) and 0xCC (DAC)
# share the range but are not frame headers
_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# markers without a length field: TEM and RST0-RST7 (SOI/EOI are handled apart)
_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8)})


def jpeg_size(data: bytes | bytearray | memoryview) -> tuple[int, int]:
    """(width, height) from the frame header of a JPEG; JpegError if there is none.

    Only the segments before the frame header are read (a few hundred bytes in practice);
    the entropy-coded data is never touched.
    """
    view = memoryview(data)
    if len(view) < 4 or view[0] != 0xFF or view[1] != 0xD8:
        raise JpegError("not a JPEG: it does not start with the SOI marker FF D8")
    i = 2
    while i < len(view):
        if view[i] != 0xFF:
            raise JpegError(f"not a JPEG: expected a marker at byte {i}, got "
                               f"0x{view[i]:02X}")
        while i < len(view) and view[i] == 0xFF:  # fill bytes (B.1.1.2)
            i += 1
        if i >= len(view):
            break
        marker = view[i]
        i += 1
        if marker in _STANDALONE:
            continue
        if marker in (0xD8, 0xD9, 0xDA):  # a second SOI, EOI, or scan data before any SOF
            raise JpegError(f"not a JPEG: marker 0x{marker:02X} before the frame header")
        if i + 2 > len(view):
            break
        length = (view[i] << 8) | view[i + 1]  # includes its own two bytes
        if length < 2:
            raise JpegError(f"not a JPEG: segment 0x{marker:02X} of length {length}")
        if marker in _SOF:
            if length < 8 or i + 7 > len(view):
                break
            height = (view[i + 3] << 8) | view[i + 4]
            width = (view[i + 5] << 8) | view[i + 6]
            return width, height
        i += length
    raise JpegError("not a JPEG: no frame header (SOF marker) before the end of the data")
