"""An HTTP MJPEG stream as a frame source (IP cameras, ``mjpg-streamer``, a phone app, another
slamlens viewer's ``/stream.mjpg``).

The stream is one HTTP response of type ``multipart/x-mixed-replace; boundary=B``: parts
separated by ``--B``, each with its headers (``Content-Type: image/jpeg``, usually
``Content-Length``) and a JPEG. :class:`MjpegSource` reads it with a socket timeout, so a
stream that stalls — the server keeps the connection open and sends nothing — is noticed
after ``timeout_s`` instead of blocking the capture thread for ever: it raises
:class:`~slamlens.common.errors.SourceError` naming the stall, and
:class:`~slamlens.services.registration.sources.ReconnectingSource` reopens it with
back-off, as it does a stream that ended or a server that went away. Each JPEG is handed
on as received (published without a second encoding).
"""

from __future__ import annotations

import re
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import cv2
import numpy as np

from slamlens.common.errors import SourceError

MAX_PART_BYTES = 16 << 20  #: a part larger than this is not a camera frame
MAX_HEADER_BYTES = 16 << 10
_BOUNDARY = re.compile(r'boundary="?([^";]+)"?', re.IGNORECASE)


def redacted(url: str) -> str:
    """``url`` without a password (for log lines and the page)."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    host = parts.hostname or ""
    netloc = f"{parts.username}:***@{host}" + (f":{parts.port}" if parts.port else "")
    return urlunsplit(parts._replace(netloc=netloc))


class MjpegSource:
    """Frames of an HTTP MJPEG stream (module docstring)."""

    live = True

    def __init__(self, url: str, *, timeout_s: float = 5.0,
                 clock: Callable[[], float] = time.time) -> None:
        self.url = url
        self.name = redacted(url)
        self.timeout_s = timeout_s
        self._clock = clock
        self._buf = b""
        try:
            self._response: Any = urllib.request.urlopen(url, timeout=timeout_s)
        except (urllib.error.URLError, OSError, ValueError) as exc:
            raise SourceError(f"cannot open {self.name}: {exc}") from None
        kind = self._response.headers.get("Content-Type", "")
        found = _BOUNDARY.search(kind)
        if not kind.lower().startswith("multipart/") or found is None:
            self._response.close()
            raise SourceError(f"{self.name} is not an MJPEG stream (Content-Type {kind!r}, "
                              "expected multipart/x-mixed-replace; boundary=…)")
        boundary = found.group(1)
        self._delimiter = b"--" + (boundary[2:] if boundary.startswith("--")
                                   else boundary).encode()

    # -- reading ----------------------------------------------------------------------
    def _fill(self) -> None:
        try:
            chunk = self._response.read1(65536)
        except TimeoutError:
            raise SourceError(f"{self.name} stalled: no data for {self.timeout_s:g} s") \
                from None
        except (OSError, ValueError) as exc:
            raise SourceError(f"{self.name} broke: {exc}") from None
        if not chunk:
            raise SourceError(f"{self.name} ended (the server closed the stream)")
        self._buf += chunk

    def _until(self, token: bytes, limit: int) -> bytes:
        """The bytes before the next ``token`` (consumed with it)."""
        start = 0
        while True:
            at = self._buf.find(token, start)
            if at >= 0:
                out, self._buf = self._buf[:at], self._buf[at + len(token):]
                return out
            if len(self._buf) > limit:
                raise SourceError(f"{self.name}: no {token[:40]!r} within {limit} bytes")
            start = max(0, len(self._buf) - len(token) + 1)
            self._fill()

    def _part(self) -> bytes:
        self._until(self._delimiter, MAX_PART_BYTES)
        headers = self._until(b"\r\n\r\n", MAX_HEADER_BYTES).decode("latin-1")
        length = None
        for line in headers.split("\r\n"):
            name, _, value = line.partition(":")
            if name.strip().lower() == "content-length" and value.strip().isdigit():
                length = int(value.strip())
        if length is None:  # no length: the part ends where the next delimiter begins
            data = self._until(b"\r\n" + self._delimiter, MAX_PART_BYTES)
            self._buf = self._delimiter + self._buf
            return data
        if length > MAX_PART_BYTES:
            raise SourceError(f"{self.name}: a part of {length} bytes")
        while len(self._buf) < length:
            self._fill()
        data, self._buf = self._buf[:length], self._buf[length:]
        return data

    def read(self) -> tuple[float, np.ndarray, bytes] | None:
        data = self._part()
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        if image is None:
            return None  # a part that is not a JPEG (a text keep-alive): the next one
        return self._clock(), image, data

    def close(self) -> None:
        try:
            self._response.close()
        except Exception:  # a broken connection may fail to close; it is gone anyway
            pass
