"""Pictures without an image library: a uniform grey baseline JPEG for a third-party
camera's frames, and a PNG decoder for the viewer's snapshots (zlib and numpy only)."""

from __future__ import annotations

import struct
import zlib

import numpy as np

#: the JPEG's one grey level (128: every block's DC coefficient is 0 after the level shift)
GREY = 128


def _segment(marker: int, body: bytes) -> bytes:
    return struct.pack(">HH", 0xFF00 | marker, len(body) + 2) + body


def grey_jpeg(width: int, height: int) -> bytes:
    """A baseline JPEG, one component, every pixel :data:`GREY`: each 8×8 block is a DC
    difference of 0 and an end of block, each coded by a one-bit Huffman code."""
    assert width % 8 == 0 and height % 8 == 0
    dqt = _segment(0xDB, b"\x00" + b"\x01" * 64)
    sof = _segment(0xC0, struct.pack(">BHHB", 8, height, width, 1) + b"\x01\x11\x00")
    one_code = b"\x01" + b"\x00" * 15  # one code of length 1 ('0') ...
    dht = _segment(0xC4, b"\x00" + one_code + b"\x00"  # ... DC: category 0
                   + b"\x10" + one_code + b"\x00")  # ... AC: end of block
    sos = _segment(0xDA, b"\x01\x01\x00\x00\x3f\x00")
    bits = 2 * (width // 8) * (height // 8)  # '0' + '0' per block
    data = b"\x00" * (bits // 8) + (b"" if bits % 8 == 0 else bytes([0xFF >> (bits % 8)]))
    return b"\xff\xd8" + dqt + sof + dht + sos + data + b"\xff\xd9"


def _unfilter_row(kind: int, line: bytearray, prev: bytes, step: int) -> bytes:
    """One PNG scanline without its filter (RFC 2083 §6); ``step`` bytes per pixel."""
    if kind == 0:
        return bytes(line)
    if kind == 2:
        return bytes(((np.frombuffer(line, np.uint8).astype(np.uint16)
                       + np.frombuffer(prev, np.uint8)) & 0xFF).astype(np.uint8))
    if kind == 1:
        pixels = np.frombuffer(line, np.uint8).reshape(-1, step).astype(np.int64)
        return bytes((np.cumsum(pixels, axis=0) & 0xFF).astype(np.uint8).reshape(-1))
    for x in range(len(line)):  # average (3) or Paeth (4): sequential along the row
        left = line[x - step] if x >= step else 0
        up = prev[x]
        if kind == 3:
            line[x] = (line[x] + ((left + up) >> 1)) & 0xFF
            continue
        upleft = prev[x - step] if x >= step else 0
        p = left + up - upleft
        pa, pb, pc = abs(p - left), abs(p - up), abs(p - upleft)
        best = left if pa <= pb and pa <= pc else (up if pb <= pc else upleft)
        line[x] = (line[x] + best) & 0xFF
    return bytes(line)


def png_pixels(data: bytes) -> np.ndarray:
    """The pixels of an 8-bit RGB / RGBA / grey PNG, non-interlaced: [H, W, channels]."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    pos, idat, head = 8, b"", None
    while pos < len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + length]
        if kind == b"IHDR":
            head = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    assert head is not None
    width, height, depth, colour, _, _, interlace = head
    assert depth == 8 and interlace == 0, f"PNG depth {depth}, interlace {interlace}"
    channels = {0: 1, 2: 3, 4: 2, 6: 4}[colour]
    raw = zlib.decompress(idat)
    stride = width * channels
    rows: list[bytes] = []
    prev = bytes(stride)
    for y in range(height):
        at = y * (stride + 1)
        prev = _unfilter_row(raw[at], bytearray(raw[at + 1:at + 1 + stride]), prev, channels)
        rows.append(prev)
    return np.frombuffer(b"".join(rows), np.uint8).reshape(height, width, channels)
