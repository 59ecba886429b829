"""What a JPEG says it is, without decoding it: :mod:`slamlens.common.jpeg` (the viewer's
frames and the registration service's browser frames are checked alike)."""

from __future__ import annotations

from slamlens.common.jpeg import JpegError, jpeg_size

__all__ = ["JpegError", "jpeg_size"]
