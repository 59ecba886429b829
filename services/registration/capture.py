"""One camera's capture thread: read the source at its pace, publish each frame, hand it on.

:class:`FrameCapture` reads a :class:`~slamlens.services.registration.sources.FrameSource`
(files, folders and the synthetic camera at ``fps``; live sources — devices, streams, a
browser's frames — at their own pace), publishes every frame as a ``CameraFrame``
latest-wins (congestion *drop*: a slow subscriber gets the newest frame and never slows
the camera), and leaves it in a keep-newest slot (:class:`~slamlens.common.latest.Latest`)
for the processing thread. A source that hands over the JPEG it received (an MJPEG
stream, a browser) is published as it came: no second encoding.

A failed read is one counted line; a source that ended (a file without ``loop``) says so
and the capture stops; a source that is lost or stalls says why and how long until the
next attempt (:attr:`FrameCapture.source_state`, shown by ``slamlens status`` and the
viewer's page).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time

import cv2
import numpy as np

from slamlens.common.drops import DropCounter
from slamlens.common.latest import Latest
from slamlens.common.messages import CameraFrame
from slamlens.services.registration.sources import FrameSource, SourceEnded

log = logging.getLogger("slamlens.services.registration.service")

#: (seq, stamp, image) handed from the capture thread to the processing thread
Captured = tuple[int, float, np.ndarray]


@dataclasses.dataclass
class PipelineStats:
    """Counters of one camera (read by tests, benchmarks and the status log)."""

    captured: int = 0
    published: int = 0
    processed: int = 0
    skipped: int = 0  #: frames the processing thread had no time for (replaced unseen)
    registrations: int = 0
    tracked: int = 0
    camera_poses: int = 0
    size_mismatches: int = 0  #: frames of another size than the calibration's
    refused: int = 0  #: re-registration requests refused (they would move the frame too far)
    ended: bool = False
    publish_times: collections.deque = dataclasses.field(
        default_factory=lambda: collections.deque(maxlen=600))


class FrameCapture:
    """The capture thread of one camera (module docstring)."""

    def __init__(self, *, camera: str, source: FrameSource, publisher: object,
                 fps: float, jpeg_quality: int, stats: PipelineStats,
                 stop: threading.Event) -> None:
        self.camera = camera
        self.source = source
        self._publisher = publisher
        self.fps = fps
        self.jpeg_quality = jpeg_quality
        self.stats = stats
        self._stop = stop
        self.read_errors = DropCounter(log, burst=1)  #: failed reads of the source
        self.frames: Latest[Captured] = Latest()  #: the newest frame, for processing

    @property
    def source_state(self) -> str:
        """What the source is doing, in a few words ("" when it delivers)."""
        if self.stats.ended:
            return "source ended"
        describe = getattr(self.source, "outage", None)
        return describe() if callable(describe) else ""

    def run(self) -> None:
        period = 1.0 / self.fps
        next_t = time.monotonic()
        seq = 0
        while not self._stop.is_set():
            if not getattr(self.source, "live", False):
                delay = next_t - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    break
            try:
                frame = self.source.read()
            except SourceEnded as exc:
                self.stats.ended = True
                log.warning("camera %s: %s; no more frames, still serving the last "
                            "registration", self.camera, exc)
                return
            except Exception as exc:  # an unexpected source failure: count, keep going
                self.read_errors.drop(f"frame of camera {self.camera}", f"reading failed: {exc}")
                self._stop.wait(period)
                continue
            now = time.monotonic()
            if frame is None:
                self._stop.wait(min(period, 0.02))
                continue
            # keep the cadence, but after a stall restart it instead of bursting to catch up
            next_t = next_t + period if next_t + period > now - period else now + period
            stamp, image = frame[0], frame[1]
            jpeg = frame[2] if len(frame) == 3 else None
            self.stats.captured += 1
            seq += 1
            self.publish(seq, stamp, image, jpeg)
            self.frames.put((seq, stamp, image))

    def publish(self, seq: int, stamp: float, image: np.ndarray,
                jpeg: bytes | None = None) -> None:
        """Publish one frame (``jpeg``: its encoding as received, published as it is)."""
        if jpeg is None:
            ok, encoded = cv2.imencode(".jpg", image,
                                       [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
            if not ok:
                log.error("camera %s: JPEG encoding of frame %d failed", self.camera, seq)
                return
            jpeg = encoded.tobytes()
        h, w = image.shape[:2]
        msg = CameraFrame(camera=self.camera, seq=seq, stamp=float(stamp), encoding="jpeg",
                          width=w, height=h, data=jpeg)
        self._publisher.put(msg.to_bytes())  # type: ignore[attr-defined]
        self.stats.published += 1
        self.stats.publish_times.append(time.monotonic())
