"""Browser cameras: frames that arrive on the bus (``slamlens/camera/C/capture``), one
pipeline per camera while it sends.

``slamlens registration --source browser --camera phone`` serves every camera named
``phone`` or ``phone-…`` whose frames a viewer's ``/ar`` page forwards (docs/viewer.md,
"AR on a phone"): a browser camera is registered like any other — its frames, registration,
tracked pose and camera pose are published under its own name — from its first frame on,
and released (threads stopped, everything it declared on the bus undeclared) when it has
sent nothing for ``idle_s``: a phone that leaves frees its camera. At most ``max_cameras``
at once; more are refused (one counted line each).

A camera that joins after another browser camera of this service registered the robot's
map starts from that registration (every head-mounted camera is anchored in the world of
the marker board, so the map's place in it is theirs to share): a phone that comes late
needs no view of the robot standing at its map origin.

Frames are checked before they cost anything: a payload over ``max_bytes``, a message
that is not a ``CameraFrame``, a JPEG whose header claims more than ``max_pixels`` pixels
or another size than its message says, and a JPEG OpenCV cannot decode are refused, one
counted line each (the first few of a kind); a camera sending faster than it is processed
loses the older frames (a keep-newest slot), so memory stays bounded whatever it sends.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from slamlens.common.bus import Bus
from slamlens.common.drops import DropCounter
from slamlens.common.errors import MessageError, SlamlensError
from slamlens.common.jpeg import JpegError, jpeg_size
from slamlens.common.keys import Keys
from slamlens.common.latest import Latest
from slamlens.common.messages import CameraFrame
from slamlens.services.registration.pipeline import CameraPipeline
from slamlens.services.registration.sources import Frame

log = logging.getLogger(__name__)


class FrameRefused(SlamlensError):
    """A browser frame that is not used (the reason says why)."""


def check_header(payload: bytes, *, max_pixels: int) -> CameraFrame:
    """The frame, if its message and its JPEG's header (read without decoding) are sound;
    FrameRefused naming what is wrong."""
    try:
        frame = CameraFrame.from_bytes(payload)
    except MessageError as exc:
        raise FrameRefused(f"not a CameraFrame: {exc}") from None
    try:
        width, height = jpeg_size(frame.data)
    except JpegError as exc:
        raise FrameRefused(str(exc)) from None
    if (width, height) != (frame.width, frame.height):
        raise FrameRefused(f"its JPEG is {width}x{height}, the message says "
                           f"{frame.width}x{frame.height}")
    if width * height > max_pixels:
        raise FrameRefused(f"{width}x{height} is more than {max_pixels} pixels")
    return frame


def decode_image(frame: CameraFrame) -> np.ndarray:
    """The frame's BGR image; FrameRefused if its JPEG does not decode."""
    image = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_COLOR)
    if image is None or image.shape[:2] != (frame.height, frame.width):
        raise FrameRefused("its JPEG does not decode")
    return image


class BrowserFrames:
    """A live :class:`~slamlens.services.registration.sources.FrameSource` fed from the bus:
    the newest frame a browser sent (``offer`` runs on a Zenoh thread and only stores)."""

    live = True

    def __init__(self, camera: str, *, max_pixels: int, drops: DropCounter,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.camera = camera
        self.name = f"browser camera {camera}"
        self.max_pixels = max_pixels
        self.drops = drops
        self._clock = clock
        self._slot: Latest[CameraFrame] = Latest()
        self.last_offer = clock()  #: when the newest frame arrived
        self.size: tuple[int, int] | None = None  #: (width, height) of its frames
        self.resized = False  #: a frame of another size came: the camera must start anew

    @property
    def skipped(self) -> int:
        """Frames replaced by a newer one before they were read."""
        return self._slot.dropped

    def offer(self, frame: CameraFrame) -> None:
        self._slot.put(frame)
        self.last_offer = self._clock()

    def read(self) -> Frame | None:
        frame = self._slot.take(timeout=0.1)
        if frame is None:
            return None
        try:
            image = decode_image(frame)
        except FrameRefused as exc:
            self.drops.drop("browser frame", f"camera {self.camera}: {exc}")
            return None
        size = (frame.width, frame.height)
        if self.size is not None and size != self.size:
            self.resized = True  # its calibration was for the other size
            return None
        return frame.stamp, image, frame.data

    def close(self) -> None:
        self._slot.close()


@dataclass
class _Camera:
    source: BrowserFrames
    pipeline: CameraPipeline


#: makes a browser camera's pipeline: (camera, its source, frame width, height)
PipelineFactory = Callable[[str, BrowserFrames, int, int], CameraPipeline]


class BrowserCameras:
    """Every browser camera this service serves (module docstring)."""

    def __init__(self, bus: Bus, keys: Keys, *, base: str, make: PipelineFactory,
                 add: Callable[[CameraPipeline], None],
                 remove: Callable[[CameraPipeline], None], idle_s: float = 3.0,
                 max_cameras: int = 8, max_pixels: int = 8_294_400,
                 max_bytes: int = 8 << 20) -> None:
        self.keys = keys
        self.base = base
        self._make, self._add, self._remove = make, add, remove
        self.idle_s = idle_s
        self.max_cameras = max_cameras
        self.max_pixels = max_pixels
        self.max_bytes = max_bytes
        self.drops = DropCounter(log)  #: refused frames and cameras
        self.joined = 0  #: cameras that joined so far
        self.left = 0  #: cameras released so far
        self._lock = threading.Lock()
        self._cameras: dict[str, _Camera] = {}
        self._joining: dict[str, CameraFrame] = {}  #: first frames of cameras not set up
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="browser-cameras", daemon=True)
        bus.subscribe(keys.any_capture(), self._on_frame)

    def serves(self, camera: str) -> bool:
        """Whether ``camera`` is one of this service's: ``base`` or ``base-…``."""
        return camera == self.base or camera.startswith(self.base + "-")

    @property
    def cameras(self) -> list[str]:
        with self._lock:
            return sorted(self._cameras)

    # -- Zenoh thread: check the header, store, return ------------------------------
    def _on_frame(self, key: str, payload: bytes) -> None:
        camera = self.keys.camera_of(key)
        if camera is None or not self.serves(camera):
            return  # another service's browser camera
        try:
            if len(payload) > self.max_bytes:
                raise FrameRefused(f"{len(payload)} bytes is more than {self.max_bytes}")
            frame = check_header(payload, max_pixels=self.max_pixels)
        except FrameRefused as exc:
            self.drops.drop("browser frame", f"camera {camera}: {exc}")
            return
        with self._lock:
            known = self._cameras.get(camera)
            if known is None:
                if camera not in self._joining and (len(self._cameras) + len(self._joining)
                                                    >= self.max_cameras):
                    self.drops.drop("browser camera", f"camera {camera} refused: this service "
                                    f"already serves {self.max_cameras} browser cameras")
                    return
                self._joining[camera] = frame
        if known is not None:
            known.source.offer(frame)
        else:
            self._wake.set()

    # -- the manager thread: cameras join and leave ---------------------------------
    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(10.0)
        with self._lock:
            cameras, self._cameras = list(self._cameras.values()), {}
        for cam in cameras:
            self._remove(cam.pipeline)
            cam.pipeline.release()

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(min(0.25, self.idle_s / 4))
            self._wake.clear()
            with self._lock:
                joining, self._joining = self._joining, {}
            for camera, frame in joining.items():
                try:
                    self._join(camera, frame)
                except Exception:  # a camera that cannot be set up must not stop the others
                    log.exception("camera %s: setting up the browser camera failed", camera)
            now = time.monotonic()
            with self._lock:
                leaving = [(name, cam) for name, cam in self._cameras.items()
                           if cam.source.resized or now - cam.source.last_offer > self.idle_s]
                for name, _ in leaving:
                    del self._cameras[name]
            for name, cam in leaving:
                self._leave(name, cam, now)

    def _join(self, camera: str, frame: CameraFrame) -> None:
        source = BrowserFrames(camera, max_pixels=self.max_pixels, drops=self.drops)
        source.size = (frame.width, frame.height)
        pipeline = self._make(camera, source, frame.width, frame.height)
        self._add(pipeline)
        pipeline.start()
        with self._lock:
            self._cameras[camera] = _Camera(source, pipeline)
        source.offer(frame)
        self.joined += 1
        log.info("camera %s: a browser joined (%dx%d frames); registering it", camera,
                 frame.width, frame.height)

    def _leave(self, camera: str, cam: _Camera, now: float) -> None:
        self._remove(cam.pipeline)
        cam.pipeline.release()
        self.left += 1
        if cam.source.resized:
            log.info("camera %s: its frames changed size; starting it anew", camera)
            return
        log.info("camera %s: left (no frame for %.1f s); its pipeline is released", camera,
                 now - cam.source.last_offer)
