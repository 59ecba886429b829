"""Frame sources: an OpenCV capture (device, video file, stream), a folder, the synthetic camera.

A :class:`FrameSource` hands out ``(stamp, image_bgr)`` pairs. ``read`` returns ``None``
when no frame is ready right now; it raises :class:`SourceEnded` when a finite source
(a video file or a folder, without ``loop``) has nothing more, and
:class:`~slamlens.common.errors.SourceError` when the source failed (a device unplugged, a folder
deleted). :class:`ReconnectingSource` turns failures into one log line, a counter and a
capped exponential back-off of reopen attempts (:class:`~slamlens.common.backoff.Backoff`), so a
vanished camera never ends the service.

``live`` sources (devices, streams) pace themselves: ``read`` blocks until the next frame.
The others (files, folders, synthetic) are paced by the caller at the configured rate.
Stamps are wall-clock seconds at capture, except the synthetic camera's, which are the
stamps of the truth it renders (the picture shows the world at that instant).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from slamlens.common.backoff import Backoff
from slamlens.common.errors import ConfigError, SourceError
from slamlens.common.messages import Truth
from slamlens.services.registration.mjpeg import MjpegSource, redacted
from slamlens.services.registration.synthetic import SyntheticCamera

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm")

#: (stamp s, BGR image) or, from a source that received it encoded, (…, its JPEG)
Frame = tuple[float, np.ndarray] | tuple[float, np.ndarray, bytes]


class SourceEnded(SourceError):
    """A finite source (video file, image folder) has no more frames."""


class FrameSource(Protocol):
    @property
    def name(self) -> str:
        """What it reads, for log lines."""
        ...

    @property
    def live(self) -> bool:
        """True if it paces itself (a device, a stream)."""
        ...

    def read(self) -> Frame | None:
        """The next (stamp s, BGR uint8 image), or None if none is ready now."""
        ...

    def close(self) -> None: ...


def _as_bgr(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


@dataclass(frozen=True)
class DeviceOptions:
    """What a USB camera (a device index) is asked for; 0 / "" = its own choice."""

    width: int = 0
    height: int = 0
    fps: float = 0.0
    fourcc: str = ""  #: e.g. "MJPG": most USB cameras give 1280x720 at 30 Hz only as MJPEG
    buffer_size: int = 0  #: frames the driver queues (1: always the newest)


class CaptureSource:
    """``cv2.VideoCapture`` on a device index, a video file or a stream URL (RTSP …).

    A device is asked for ``options`` (the four-character code first: a camera's sizes
    and rates depend on it); a stream URL is opened through FFmpeg with open and read
    timeouts of ``timeout_s``, so a stalled stream fails a read instead of blocking it.
    """

    def __init__(self, target: int | str, *, loop: bool = False,
                 options: DeviceOptions = DeviceOptions(), timeout_s: float = 5.0,
                 clock: Callable[[], float] = time.time) -> None:
        self.target = target
        self.name = f"device {target}" if isinstance(target, int) else redacted(str(target))
        self.is_file = isinstance(target, str) and "://" not in target
        self.live = not self.is_file
        self.loop = loop
        self._clock = clock
        if isinstance(target, str) and not self.is_file:
            ms = int(timeout_s * 1000)
            self._cap = cv2.VideoCapture(target, cv2.CAP_FFMPEG, [
                cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, ms])
        else:
            self._cap = cv2.VideoCapture(target)
        if not self._cap.isOpened():
            self._cap.release()
            raise SourceError(f"cannot open {self.name}")
        if isinstance(target, int):  # a file or a stream has its own size
            self._ask(options)

    def _ask(self, options: DeviceOptions) -> None:
        if options.fourcc:
            self._cap.set(cv2.CAP_PROP_FOURCC, float(cv2.VideoWriter.fourcc(*options.fourcc)))
        for prop, value in ((cv2.CAP_PROP_FRAME_WIDTH, options.width),
                            (cv2.CAP_PROP_FRAME_HEIGHT, options.height),
                            (cv2.CAP_PROP_FPS, options.fps),
                            (cv2.CAP_PROP_BUFFERSIZE, options.buffer_size)):
            if value:
                self._cap.set(prop, float(value))
        got = (int(self._cap.get(cv2.CAP_PROP_FRAME_WIDTH)),
               int(self._cap.get(cv2.CAP_PROP_FRAME_HEIGHT)), self._cap.get(cv2.CAP_PROP_FPS))
        if (options.width and got[0] != options.width) or (
                options.height and got[1] != options.height):
            log.warning("%s gives %dx%d at %.3g Hz, not the %dx%d asked for (another "
                        "--fourcc, e.g. MJPG, may have it)", self.name, got[0], got[1],
                        got[2], options.width, options.height)

    def read(self) -> Frame | None:
        ok, image = self._cap.read()
        if not ok and self.is_file and self.loop:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            ok, image = self._cap.read()
        if not ok or image is None:
            if self.is_file:
                raise SourceEnded(f"{self.name} ended")
            raise SourceError(f"{self.name} stopped delivering frames")
        return self._clock(), _as_bgr(image)

    def close(self) -> None:
        self._cap.release()


class FolderSource:
    """The images of a folder in name order (PNG, JPEG, …), once or looping."""

    live = False

    def __init__(self, folder: str | Path, *, loop: bool = False,
                 clock: Callable[[], float] = time.time) -> None:
        self.folder = Path(folder)
        self.name = f"folder {self.folder}"
        self.loop = loop
        self._clock = clock
        if not self.folder.is_dir():
            raise SourceError(f"{self.name} does not exist")
        self.files = sorted(p for p in self.folder.iterdir()
                            if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise SourceError(f"{self.name} holds no images ({', '.join(IMAGE_SUFFIXES)})")
        self._next = 0

    def read(self) -> Frame | None:
        if self._next >= len(self.files):
            if not self.loop:
                raise SourceEnded(f"{self.name} ended after {len(self.files)} images")
            self._next = 0
        path = self.files[self._next]
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise SourceError(f"{path} is unreadable or gone")
        self._next += 1
        return self._clock(), image

    def close(self) -> None:
        pass


class SyntheticSource:
    """Frames of a :class:`SyntheticCamera` rendering the latest :class:`Truth` it was given.

    ``pose_at(stamp)`` moves the camera (head-mounted); ``last_T_world_from_camera`` is the
    exact pose of the last frame (the ground truth of the camera tracking).
    """

    live = False

    def __init__(self, camera: SyntheticCamera, *, name: str = "synthetic",
                 pose_at: Callable[[float], np.ndarray] | None = None,
                 clock: Callable[[], float] = time.time) -> None:
        self.camera = camera
        self.name = name
        self.pose_at = pose_at
        self._clock = clock
        self._truth: Truth | None = None
        self._lock = threading.Lock()
        self.frame_index = 0
        self.last_T_world_from_camera = camera.T_world_from_camera.copy()

    def set_truth(self, truth: Truth) -> None:
        """Render ``truth`` (robot pose and landmarks, map = world frame) from now on."""
        with self._lock:
            self._truth = truth

    def read(self) -> Frame | None:
        with self._lock:
            truth = self._truth
        stamp = truth.stamp if truth is not None else self._clock()
        T_wc = self.pose_at(stamp) if self.pose_at is not None else None
        image = self.camera.render(
            robot_pose=None if truth is None else truth.pose,
            landmarks_xy=None if truth is None else truth.landmarks,
            T_world_from_camera=T_wc, frame_index=self.frame_index)
        self.frame_index += 1
        self.last_T_world_from_camera = (self.camera.T_world_from_camera if T_wc is None
                                         else T_wc)
        return stamp, image

    def close(self) -> None:
        pass


class ReconnectingSource:
    """Wraps a source factory: a failing source is closed and reopened with back-off.

    The first failure of an outage is logged as one warning line, and the recovery as
    one info line; attempts in between are counted (``failures``) and logged at debug.
    ``read`` never sleeps: while waiting to retry it returns None.
    """

    def __init__(self, open_source: Callable[[], FrameSource], *, name: str,
                 initial: FrameSource | None = None, backoff_initial_s: float = 0.25,
                 backoff_max_s: float = 5.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._open = open_source
        self.name = name
        self._source = initial
        self._clock = clock
        self.backoff = Backoff(name, logger=log, initial_s=backoff_initial_s,
                               max_s=backoff_max_s, clock=clock)
        self.reason = ""  #: why the source was lost (the newest failure)
        self._lost_at: float | None = None

    @property
    def live(self) -> bool:
        return bool(getattr(self._source, "live", False))

    @property
    def source(self) -> FrameSource | None:
        return self._source

    @property
    def failures(self) -> int:
        """Failed reads and reopen attempts."""
        return self.backoff.failures

    def outage(self) -> str:
        """What is wrong, for the page and ``slamlens status`` ("" while it delivers)."""
        if not self.backoff.in_outage:
            return ""
        since = 0.0 if self._lost_at is None else self._clock() - self._lost_at
        return (f"source lost {since:.0f} s ago: {self.reason}; retrying "
                f"(attempt {self.backoff.failures}, next in {self.backoff.wait_s():.1f} s)")

    @property
    def outages(self) -> int:
        """Times the source vanished."""
        return self.backoff.outages

    @property
    def reconnects(self) -> int:
        """Times it came back."""
        return self.backoff.recoveries

    def read(self) -> Frame | None:
        if self._source is None:
            if self.backoff.wait_s() > 0:
                return None
            try:
                self._source = self._open()
            except SourceError as exc:
                self._failed(exc)
                return None
        try:
            frame = self._source.read()
        except SourceEnded:
            raise
        except (SourceError, cv2.error) as exc:
            self._close_inner()
            self._failed(exc)
            return None
        if frame is not None and self.backoff.in_outage:
            self.backoff.succeeded()  # frames flow again (opening alone is not enough)
            self._lost_at = None
        return frame

    def _failed(self, exc: Exception) -> None:
        if not self.backoff.in_outage:
            self._lost_at = self._clock()
        self.reason = str(exc)
        self.backoff.failed(exc)

    def _close_inner(self) -> None:
        if self._source is not None:
            try:
                self._source.close()
            except Exception:  # a half-dead device may fail to close; it is gone anyway
                log.debug("closing %s failed", self.name, exc_info=True)
            self._source = None

    def close(self) -> None:
        self._close_inner()


def parse_source(spec: str) -> int | Path | str:
    """What a ``--source`` string names: a device index, a path, or a URL (or 'synthetic')."""
    if spec.isdigit():
        return int(spec)
    if "://" in spec or spec == "synthetic":
        return spec
    return Path(spec)


def open_capture(spec: str, *, loop: bool = False, options: DeviceOptions = DeviceOptions(),
                 timeout_s: float = 5.0) -> Callable[[], FrameSource]:
    """A factory opening ``spec`` (device index, video file, URL or folder): an ``http://``
    or ``https://`` URL is an MJPEG stream (:class:`~slamlens.services.registration.mjpeg.
    MjpegSource`), any other URL (``rtsp://`` …) goes to OpenCV's FFmpeg; a stream that
    sends nothing for ``timeout_s`` has stalled.

    A path that does not exist when the service starts is a :class:`ConfigError` (a typo
    should fail at once); later disappearances are retried by :class:`ReconnectingSource`.
    """
    target = parse_source(spec)
    if target == "synthetic":
        raise ConfigError("open_capture: 'synthetic' needs a SyntheticCamera")
    if isinstance(target, Path):
        if not target.exists():
            raise ConfigError(f"source {target} does not exist")
        if target.is_dir():
            folder = target
            return lambda: FolderSource(folder, loop=loop)
        path = str(target)
        return lambda: CaptureSource(path, loop=loop)
    if isinstance(target, str):
        url = target
        if url.lower().startswith(("http://", "https://")):
            return lambda: MjpegSource(url, timeout_s=timeout_s)
        return lambda: CaptureSource(url, timeout_s=timeout_s)
    device = target
    return lambda: CaptureSource(device, options=options, timeout_s=timeout_s)
