"""``slamlens register --camera C [--robot R]``: re-register a camera, and say the result.

It asks the camera's registration service (a :class:`~slamlens.common.messages.CameraControl`
``reregister`` on ``slamlens/camera/C/control``), waits for the registration made from the
frames after the request, and prints it. The robot must stand still at its map origin,
marker in view, while the camera averages its frames (paper §3.1).

Clear failures: no registration service for that camera (no liveliness token, or nobody
subscribed to its control key), or no new registration within ``--timeout`` (with the
camera's last status, e.g. "marker not found").
"""

from __future__ import annotations

import argparse
import threading
import time

import numpy as np

from slamlens.common.bus import Bus
from slamlens.common.cli import command_bus, keys_from, setup_logging, stop_event
from slamlens.common.config import settings_from_args
from slamlens.common.errors import BusError, MessageError, ServiceError
from slamlens.common.keys import Keys, check_name
from slamlens.common.messages import CameraControl, Registration
from slamlens.services.commands.settings import RegisterSettings

REREGISTERING = "reregistering"  #: the status a camera says while it averages anew


class _Watch:
    """Registrations of the camera as they come (Zenoh thread: decode, store, notify)."""

    def __init__(self, robot: str) -> None:
        self.robot = robot
        self.cond = threading.Condition()
        self.latest: Registration | None = None
        self.saw_reregistering = False
        self.new: Registration | None = None
        self.before: Registration | None = None  #: the registration when the request went out

    def arm(self) -> None:
        with self.cond:
            self.before = self.latest
            self.saw_reregistering = False

    def __call__(self, key: str, payload: bytes) -> None:
        try:
            reg = Registration.from_bytes(payload)
        except MessageError:
            return
        if self.robot and reg.robot != self.robot:
            return
        with self.cond:
            self.latest = reg
            if reg.status == REREGISTERING:
                self.saw_reregistering = True
            elif reg.status != "waiting for marker" and self.new is None and (
                    self.saw_reregistering or self._differs(reg)):
                self.new = reg
            self.cond.notify_all()

    def _differs(self, reg: Registration) -> bool:
        before = self.before
        return before is None or reg.stamp != before.stamp or not np.array_equal(
            reg.T_camera_from_map, before.T_camera_from_map)


def reregister(bus: Bus, keys: Keys, *, camera: str, robot: str = "", timeout_s: float,
               stop: threading.Event | None = None) -> Registration | None:
    """Ask ``camera`` to re-register and return the new registration (see module doc);
    None if ``stop`` was set while waiting."""
    check_name("camera", camera)
    if robot:
        check_name("robot", robot)
    if not bus.alive(keys.camera_alive(camera), timeout=min(timeout_s, 2.0)):
        raise BusError(f"no registration service for camera {camera!r} is alive (start "
                       f"`slamlens registration --camera {camera}`; `slamlens status` lists "
                       "what runs)")
    control = keys.camera_control(camera)
    if not bus.wait_for_subscriber(control, timeout=min(timeout_s, 5.0)):
        raise BusError(f"camera {camera!r} is alive but nothing listens on {control}")
    watch = _Watch(robot)
    key = keys.registration(camera, robot) if robot else keys.registrations(camera)
    bus.subscribe(key, watch)
    for sample in bus.get(key, timeout=2.0):  # the registration now, to tell the new one
        watch(sample.key, sample.payload)
    watch.arm()
    bus.publisher(control).put(CameraControl(command="reregister",
                                             robot=robot or None).to_bytes())
    deadline = time.monotonic() + timeout_s
    with watch.cond:
        while watch.new is None and not (stop and stop.is_set()):
            left = deadline - time.monotonic()
            if left <= 0:
                break
            watch.cond.wait(timeout=min(0.25, left))
        if watch.new is not None:
            return watch.new
        if stop is not None and stop.is_set():
            return None
        last = watch.latest
    said = f"; its last status: {last.status!r}" if last is not None else \
        "; it has published no registration yet"
    raise ServiceError(
        f"camera {camera!r} did not re-register{f' robot {robot!r}' if robot else ''} "
        f"within {timeout_s:g} s{said} (the robot must stand still at its map origin with its "
        "marker in view)")


def describe(reg: Registration) -> str:
    """The registration in a few lines: who, how good, where the map sits in the camera."""
    T = np.asarray(reg.T_camera_from_map)
    rows = "\n".join("  [" + ", ".join(f"{v:8.4f}" for v in row) + "]" for row in T)
    return (f"camera {reg.camera} registered robot {reg.robot}: {reg.status}, reprojection "
            f"error {reg.reprojection_error_px:.3f} px, frame stamp {reg.stamp:.3f} s, "
            f"{reg.width}x{reg.height}\nT_camera_from_map =\n{rows}")


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, "register")
    s = settings_from_args(RegisterSettings, args)
    keys = keys_from(args)
    stop = stop_event()
    bus = command_bus(args)
    try:
        reg = reregister(bus, keys, camera=s.camera, robot=s.robot, timeout_s=s.timeout_s,
                         stop=stop)
        if reg is not None:
            print(describe(reg), flush=True)
    finally:
        bus.close()
    return 0
