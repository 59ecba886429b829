"""PNG snapshots and video recordings of a view.

A :class:`Recorder` writes the newest picture of its view at a fixed frame rate on its own
thread, so the video plays in real time whatever the render rate (a picture is repeated
when nothing changed, skipped when several came within one frame period) and a slow disk
never slows rendering. ``mp4v`` in ``.mp4`` (small files) and ``MJPG`` in ``.avi`` both
work with the headless OpenCV wheel; browsers do not play ``mp4v``, so the file is offered
as a download.

A recording is bounded: it does not start when the disk holding the folder has less than
``min_free_bytes`` free, and stops by itself (saying why in :meth:`Recorder.info`) after
``max_seconds``, at ``max_bytes``, or when the free space falls below ``min_free_bytes``
(checked about once a second).
"""

from __future__ import annotations

import logging
import re
import shutil
import threading
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slamlens.common.errors import ConfigError, RenderError, SlamlensError

log = logging.getLogger("slamlens.viewer")

EXTENSIONS = {"mp4v": ".mp4", "MJPG": ".avi"}
_SAFE = re.compile(r"[^A-Za-z0-9_.-]+")
NAME_PATTERN = re.compile(r"^[A-Za-z0-9_.-]+\.(mp4|avi)$")
CHECK_EVERY_S = 1.0  # how often a recording looks at its file size and the free space
MB = 1_000_000


class RecordingRefused(SlamlensError):
    """A recording cannot start: too many running, or too little disk space (HTTP 503)."""


def free_bytes(directory: Path) -> int:
    """Free space for an unprivileged writer on the disk holding ``directory``."""
    return shutil.disk_usage(directory).free


def encode_png(image_bgr: np.ndarray) -> bytes:
    """PNG bytes of a BGR picture (fast compression: a snapshot should come back at once)."""
    ok, data = cv2.imencode(".png", image_bgr, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise RenderError("PNG encoding failed")
    return data.tobytes()


def recording_name(robot: str, client: str, codec: str) -> str:
    """A file name that says what and when: ``slamlens-R-20250101-120000-client.mp4``."""
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    return _SAFE.sub("_", f"slamlens-{robot}-{stamp}-{client[:12]}") + EXTENSIONS[codec]


class Recorder:
    """Writes ``source()`` to a video file ``fps`` times a second until ``stop``."""

    def __init__(self, *, directory: str | Path, name: str, fps: float, codec: str,
                 source: Callable[[], np.ndarray | None], settings: Callable[[], Any],
                 max_seconds: float = float("inf"), max_bytes: float = float("inf"),
                 min_free_bytes: float = 0.0,
                 free: Callable[[Path], int] = free_bytes) -> None:
        if codec not in EXTENSIONS:
            raise ConfigError(f"codec {codec!r} is not one of {list(EXTENSIONS)}")
        self.path = Path(directory) / name
        self.fps = fps
        self.codec = codec
        self.max_seconds = max_seconds
        self.max_bytes = max_bytes
        self.min_free_bytes = min_free_bytes
        self._free = free
        self._source = source
        self.settings = settings  #: the view being recorded (kept rendering while recording)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"recorder-{name}", daemon=True)
        self._writer: cv2.VideoWriter | None = None
        self._size: tuple[int, int] | None = None
        self.frames = 0
        self.error = ""
        self.limit = ""  #: why it stopped by itself (a limit), empty otherwise
        self.started = time.time()
        self.stopped: float | None = None

    def start(self) -> None:
        """Start writing; RecordingRefused (nothing started) if the disk is short of space."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        free = self._free(self.path.parent)
        if free < self.min_free_bytes:
            raise RecordingRefused(f"not recording: {free / MB:.0f} MB free on the disk of "
                           f"{self.path.parent}, below min_free_disk_mb "
                           f"{self.min_free_bytes / MB:.0f}")
        self._thread.start()

    @property
    def running(self) -> bool:
        """Writing still (neither stopped nor stopped by itself at a limit)."""
        return self.stopped is None and not self._stop.is_set()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=10.0)
        if self.stopped is None:
            self.stopped = time.time()

    def info(self) -> dict[str, Any]:
        return {"file": self.path.name, "frames": self.frames, "fps": self.fps,
                "codec": self.codec, "recording": self.running, "error": self.error,
                "limit": self.limit, "seconds": (self.stopped or time.time()) - self.started}

    def _over_limit(self) -> str:
        """Why the recording must stop now (a limit reached), or ""."""
        if time.time() - self.started >= self.max_seconds:
            return f"stopped after max_recording_s {self.max_seconds:g} s"
        size = self.path.stat().st_size if self.path.exists() else 0
        if size >= self.max_bytes:
            return f"stopped at max_recording_mb {self.max_bytes / MB:g} MB"
        free = self._free(self.path.parent)
        if free < self.min_free_bytes:
            return (f"stopped: {free / MB:.0f} MB free on the disk, below "
                    f"min_free_disk_mb {self.min_free_bytes / MB:g}")
        return ""

    def _run(self) -> None:
        period = 1.0 / self.fps
        next_t = time.monotonic()
        next_check = next_t + CHECK_EVERY_S
        try:
            while not self._stop.is_set():
                image = self._source()
                if image is not None:
                    self._write(image)
                if time.monotonic() >= next_check:
                    next_check = time.monotonic() + CHECK_EVERY_S
                    self.limit = self._over_limit()
                    if self.limit:
                        log.warning("recording %s %s", self.path.name, self.limit)
                        break
                next_t += period
                delay = next_t - time.monotonic()
                if delay < -period:  # fell behind (busy machine): do not write a burst
                    next_t = time.monotonic()
                    delay = 0.0
                self._stop.wait(max(delay, 0.0))
        except Exception as exc:  # a failing disk must not take the viewer down
            self.error = str(exc)
            log.error("recording %s failed: %s", self.path, exc)
        finally:
            if self._writer is not None:
                self._writer.release()
                self._writer = None  # its buffers go now, not when the recorder does
            self.stopped = self.stopped or time.time()
        log.info("recorded %d frames to %s", self.frames, self.path)

    def _write(self, image: np.ndarray) -> None:
        height, width = image.shape[:2]
        if self._writer is None:
            self._size = (width, height)
            self._writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter.fourcc(*self.codec),
                                           self.fps, self._size)
            if not self._writer.isOpened():
                raise OSError(f"cannot open a {self.codec} video writer on {self.path}")
        if (width, height) != self._size:
            assert self._size is not None
            image = cv2.resize(image, self._size)
        self._writer.write(np.ascontiguousarray(image))
        self.frames += 1
