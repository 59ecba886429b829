"""Raw payloads to the values the viewer draws, or a reason to drop them: pure functions.

A bad payload is logged (the first few of each kind, then one line in a while:
:class:`~slamlens.common.drops.DropCounter`), counted and dropped, never an exception out
of here; so is a registration no camera model can be made of (or larger than
``max_frame_pixels``), and a frame whose JPEG header (read without decoding) claims another
size than its message or more pixels than allowed (a decode bomb). States are decoded
without the symmetry check: the viewer shows what the estimator sent (judging it is the
monitor's job).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

import cv2
import numpy as np

from slamlens.common.drops import DropCounter
from slamlens.common.errors import MessageError
from slamlens.common.messages import CameraFrame, Health, Registration, SlamState
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.inputs import Raw
from slamlens.services.visualiser.jpeg import JpegError, jpeg_size
from slamlens.services.visualiser.summary_view import decode_summary_state

T = TypeVar("T")


def decode(source: str, raw: Raw, decoder: Callable[[bytes], T], drops: DropCounter) -> T | None:
    """``decoder(raw.payload)``, or None (counted and logged) when it is malformed."""
    try:
        return decoder(raw.payload)
    except Exception as exc:  # any decoder failure is a bad message, never a crash
        drops.drop(source, str(exc))
        return None


def decode_state(raw: Raw, robot: str, *, summary: bool, drops: DropCounter
                 ) -> SlamState | None:
    """``robot``'s state (``summary``: its summary, docs/remote_viewers.md), or None."""
    # symmetry is the monitor's business: the viewer shows what the estimator sent
    state = decode("state", raw, decode_summary_state if summary
                   else lambda b: SlamState.from_bytes(b, check_symmetry=False), drops)
    if state is not None and state.robot != robot:
        drops.drop("state", f"SlamState.robot: expected {robot!r}, got {state.robot!r}")
        return None
    return state


def decode_health(raw: Raw, robot: str, drops: DropCounter) -> Health | None:
    """``robot``'s verdict, or None."""
    health = decode("health", raw, Health.from_bytes, drops)
    if health is not None and health.robot != robot:
        drops.drop("health", f"Health.robot: expected {robot!r}, got {health.robot!r}")
        return None
    return health


def drawable_registration(payload: bytes, *, max_frame_pixels: int) -> Registration:
    """A registration the viewer can draw through: well-formed, a camera model
    (positive focal lengths, K[2,2] = 1, a known number of distortion coefficients) and
    at most ``max_frame_pixels`` (the picture is drawn at its size even before a frame
    comes); else an error naming what is wrong (counted, never a failed render)."""
    reg = Registration.from_bytes(payload)
    if reg.width * reg.height > max_frame_pixels:
        raise MessageError("Registration", "width×height",
                           f"at most {max_frame_pixels} pixels (max_frame_pixels)",
                           f"{reg.width}×{reg.height}")
    CameraModel.from_registration(reg)  # CalibrationError: no camera has such a model
    return reg


def decode_frame(camera: str, raw: Raw, *, drops: DropCounter, max_frame_pixels: int,
                 registered: Sequence[Registration]) -> tuple[np.ndarray, CameraFrame] | None:
    """The camera's frame and its BGR picture, or None: malformed, refused by its JPEG
    header's size (:func:`frame_refused`, before decoding: a bomb never allocates), or not
    the JPEG its message says."""
    source = f"frame {camera}"
    frame = decode(source, raw, CameraFrame.from_bytes, drops)
    if frame is None:
        return None
    refused = frame_refused(frame, max_frame_pixels=max_frame_pixels, registered=registered)
    if refused:
        drops.drop(source, refused)
        return None
    try:
        image = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_COLOR)
    except cv2.error:  # e.g. empty data
        image = None
    if image is None or image.shape[:2] != (frame.height, frame.width):
        got = "undecodable JPEG" if image is None else f"{image.shape[1]}×" \
            f"{image.shape[0]} pixels"
        drops.drop(source, f"CameraFrame.data: expected a {frame.width}×{frame.height} "
                           f"JPEG, got {got}")
        return None
    return image, frame


def frame_refused(frame: CameraFrame, *, max_frame_pixels: int,
                  registered: Sequence[Registration]) -> str:
    """Why the frame must not be decoded (its JPEG header's size), or "": the header's
    size must be the message's, at most ``max_frame_pixels`` and at most 4 × the largest
    size the camera was ``registered`` with (for any robot)."""
    try:
        width, height = jpeg_size(frame.data)
    except JpegError as exc:
        return f"CameraFrame.data: {exc}"
    if (width, height) != (frame.width, frame.height):
        return (f"CameraFrame.data: the JPEG header says {width}×{height} pixels, the "
                f"message {frame.width}×{frame.height} (not decoded)")
    limit, why = max_frame_pixels, "max_frame_pixels"
    if registered:
        reg = max(registered, key=lambda r: r.width * r.height)
        if 4 * reg.width * reg.height < limit:
            limit, why = (4 * reg.width * reg.height,
                          f"4 × the registered {reg.width}×{reg.height}")
    if width * height > limit:
        return (f"CameraFrame.data: a {width}×{height} JPEG has more pixels than {limit} "
                f"({why}; not decoded)")
    return ""
