"""The registration logic, pure: marker detections in → registration and tracked pose out.

Paper §3.1: when SLAM starts, the robot stands at the map origin; the marker's pose in the
camera then fixes where the map frame is (T_camera_from_map = T_camera_from_marker ·
T_marker_from_map). A :class:`Registrar` averages the first ``register_frames`` marker poses
(it stops early if the marker moves: the robot has started), then keeps measuring the robot
pose from the marker in every later frame (the "tracked" pose, beyond the paper).

A new map (a new epoch of the estimator, docs/delivery.md: restarted without a checkpoint) has its
origin where the robot stood when that map started (its ``origin_stamp``), usually while the
robot moves. The registrar keeps the marker's recent poses, so :meth:`Registrar.register_at`
registers the new map frame from the frame nearest that instant.

A moving (head-mounted) camera is handled by an *anchor* frame: each frame comes with
T_anchor_from_camera (the camera's pose in the world, from the board or a tracker). The
registration is stored as T_anchor_from_map, and the camera's current
T_camera_from_map = inv(T_anchor_from_camera) · T_anchor_from_map. A fixed overhead camera is
its own anchor (T_anchor_from_camera = identity).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from slamlens.common.geometry import invert_T, make_T, rotation_angle_deg
from slamlens.services.registration.calibration import CameraCalibration
from slamlens.services.registration.markers import Detection, mean_detection
from slamlens.services.registration.pose import (
    PoseError,
    T_marker_from_map,
    marker_object_points,
    marker_pose,
    reprojection_rms,
    robot_pose_from_marker,
)

STATUS_REGISTERED = "registered"
STATUS_TRACKING = "tracking"  #: moving camera, registration updated this frame
STATUS_NOT_FOUND = "marker not found"
STATUS_POSE_LOST = "camera pose lost"  #: moving camera without a pose this frame
STATUS_REREGISTERING = "reregistering"
STATUS_WAITING = "waiting for marker"  #: no registration yet


@dataclass(frozen=True)
class RegistrarSettings:
    """How the robot's marker is read and averaged."""

    marker_id: int
    marker_size_m: float
    marker_offset_xyz: tuple[float, float, float]
    register_frames: int = 5
    still_tolerance_m: float = 0.01
    still_tolerance_deg: float = 1.0
    max_reprojection_error_px: float = 2.0
    moving_camera: bool = False  #: head-mounted: status says whether the camera pose is known


@dataclass(frozen=True, eq=False)
class FrameResult:
    """What one frame produced."""

    stamp: float
    status: str
    marker_seen: bool  #: the robot's marker was found with a usable pose
    registered_now: bool  #: a (re-)registration was completed with this frame
    T_camera_from_map: np.ndarray | None  #: current registration in this camera, if known
    tracked_pose: np.ndarray | None  #: camera-measured robot pose (x, y, θ), map frame
    T_camera_from_marker: np.ndarray | None


def average_transforms(Ts: Sequence[np.ndarray]) -> np.ndarray:
    """Chordal mean of rigid transforms: mean translation, rotation = SO(3) projection of
    the mean rotation matrix (the L2 rotation mean; exact for small spreads)."""
    R_sum = np.sum([T[:3, :3] for T in Ts], axis=0)
    U, _, Vt = np.linalg.svd(R_sum)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])  # keep det = +1
    return make_T(U @ D @ Vt, np.mean([T[:3, 3] for T in Ts], axis=0))


@dataclass(frozen=True, eq=False)
class _Sample:
    stamp: float
    T_anchor_from_map: np.ndarray
    T_anchor_from_camera: np.ndarray
    detection: Detection


#: marker poses the registrar remembers for registering a new map at its origin instant
HISTORY = 600


@dataclass(frozen=True)
class Change:
    """How far one registration moved the map frame from the previous one."""

    moved_m: float  #: translation of the map origin, m
    moved_deg: float  #: rotation of the map frame, degrees


def frame_change(T_old: np.ndarray, T_new: np.ndarray) -> Change:
    """The change of the map frame between two T_anchor_from_map."""
    D = invert_T(T_old) @ T_new
    return Change(moved_m=float(np.linalg.norm(D[:3, 3])),
                  moved_deg=rotation_angle_deg(D[:3, :3]))


class Registrar:
    """Registration state of one camera for one robot (not thread-safe: one caller)."""

    def __init__(self, settings: RegistrarSettings, calib: CameraCalibration) -> None:
        self.settings = settings
        self.calib = calib
        self._T_marker_from_map = T_marker_from_map(settings.marker_offset_xyz)
        #: (stamp, T_anchor_from_robot) of recent frames where the marker was seen
        self._history: deque[tuple[float, np.ndarray]] = deque(maxlen=HISTORY)
        self._samples: list[_Sample] = []
        self.T_anchor_from_map: np.ndarray | None = None
        self.stamp: float | None = None  #: stamp of the first frame of the registration
        self.reprojection_error_px = math.nan
        self.collecting = True
        self.registrations = 0
        self.rejected_poses = 0  #: marker poses over the reprojection limit or degenerate

    @property
    def registered(self) -> bool:
        return self.T_anchor_from_map is not None

    def reset(self) -> None:
        """Re-register from the next frames (the previous registration is kept until then)."""
        self._samples = []
        self.collecting = True

    def register_at(self, stamp: float, *, tolerance_s: float) -> Change | None:
        """Register the map frame as the robot's pose at ``stamp`` (a new map's origin
        instant), from the remembered frame nearest it; None (and nothing changed) if no
        frame is within ``tolerance_s`` of it."""
        if not self._history:
            return None
        t, A = min(self._history, key=lambda item: abs(item[0] - stamp))
        if abs(t - stamp) > tolerance_s:
            return None
        old = self.T_anchor_from_map
        self.T_anchor_from_map = A.copy()
        self.stamp = t
        self._samples = []
        self.collecting = False
        self.registrations += 1
        return None if old is None else frame_change(old, A)

    @property
    def history_span(self) -> tuple[float, float] | None:
        """Stamps of the oldest and newest remembered marker poses."""
        if not self._history:
            return None
        return self._history[0][0], self._history[-1][0]

    # -- internals ----------------------------------------------------------------
    def _marker(self, detections: Sequence[Detection]) -> tuple[np.ndarray, Detection] | None:
        mine = [d for d in detections if d.marker_id == self.settings.marker_id]
        if len(mine) != 1:  # absent, or two markers with the robot's id: ambiguous
            return None
        try:
            T_cm, rms = marker_pose(mine[0], size_m=self.settings.marker_size_m,
                                           calib=self.calib)
        except PoseError:
            self.rejected_poses += 1
            return None
        if rms > self.settings.max_reprojection_error_px:
            self.rejected_poses += 1
            return None
        return T_cm, mine[0]

    def _moved(self, T_a: np.ndarray, T_b: np.ndarray) -> bool:
        s = self.settings
        return (float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3])) > s.still_tolerance_m
                or rotation_angle_deg(T_a[:3, :3].T @ T_b[:3, :3]) > s.still_tolerance_deg)

    def _finalise(self) -> None:
        samples, self._samples = self._samples, []
        T = self._average(samples)
        obj = marker_object_points(self.settings.marker_size_m)
        T_map_from_marker = invert_T(self._T_marker_from_map)
        squares = [reprojection_rms(obj, s.detection.corners_px, calib=self.calib,
                                    T_camera_from_object=invert_T(s.T_anchor_from_camera)
                                    @ T @ T_map_from_marker) ** 2 for s in samples]
        self.T_anchor_from_map = T
        self.stamp = samples[0].stamp
        self.reprojection_error_px = float(math.sqrt(np.mean(squares)))
        self.collecting = False
        self.registrations += 1

    def _average(self, samples: Sequence[_Sample]) -> np.ndarray:
        """T_anchor_from_map from the samples.

        A still camera (same anchor pose in every sample): one pose from the corner-wise
        mean of the detections, since the tilt of a small face-on marker is nonlinear in
        the corners and averaging corners beats averaging poses. A moving camera: the
        chordal mean of the per-frame T_anchor_from_map.
        """
        T0 = samples[0].T_anchor_from_camera
        if len(samples) > 1 and all(np.array_equal(s.T_anchor_from_camera, T0)
                                    for s in samples):
            try:
                det = mean_detection([s.detection for s in samples])
                T_cm, _ = marker_pose(det, size_m=self.settings.marker_size_m,
                                             calib=self.calib)
                return T0 @ T_cm @ self._T_marker_from_map
            except PoseError:
                pass
        return average_transforms([s.T_anchor_from_map for s in samples])

    # -- the one entry point ----------------------------------------------------------
    def observe(self, stamp: float, detections: Sequence[Detection], *,
                T_anchor_from_camera: np.ndarray | None) -> FrameResult:
        """Digest one frame's detections; ``T_anchor_from_camera`` None = pose unknown."""
        found = self._marker(detections)
        registered_now = False
        if found is not None and T_anchor_from_camera is not None:
            self._history.append((stamp, T_anchor_from_camera @ found[0]
                                  @ self._T_marker_from_map))
        if self.collecting and found is not None and T_anchor_from_camera is not None:
            T_cm, det = found
            A = T_anchor_from_camera @ T_cm @ self._T_marker_from_map
            if self._samples and self._moved(A, self._samples[0].T_anchor_from_map):
                self._finalise()  # the robot started moving: register from the still frames
                registered_now = True
            else:
                self._samples.append(_Sample(stamp, A, T_anchor_from_camera, det))
                if len(self._samples) >= self.settings.register_frames:
                    self._finalise()
                    registered_now = True

        T_camera_from_map = None
        if self.T_anchor_from_map is not None and T_anchor_from_camera is not None:
            T_camera_from_map = invert_T(T_anchor_from_camera) @ self.T_anchor_from_map
        tracked = None
        if found is not None and T_camera_from_map is not None and not self.collecting:
            tracked = robot_pose_from_marker(found[0], T_camera_from_map,
                                             self.settings.marker_offset_xyz)
        return FrameResult(stamp=stamp, status=self._status(found is not None,
                                                            T_anchor_from_camera),
                           marker_seen=found is not None, registered_now=registered_now,
                           T_camera_from_map=T_camera_from_map, tracked_pose=tracked,
                           T_camera_from_marker=None if found is None else found[0])

    def finish(self) -> FrameResult | None:
        """Register from the samples collected so far (the source ended before
        ``register_frames`` were seen); None if there are none."""
        if not self.collecting or not self._samples:
            return None
        T_anchor = self._samples[-1].T_anchor_from_camera
        self._finalise()
        assert self.T_anchor_from_map is not None and self.stamp is not None
        return FrameResult(stamp=self.stamp, status=self._status(False, T_anchor),
                           marker_seen=False, registered_now=True,
                           T_camera_from_map=invert_T(T_anchor) @ self.T_anchor_from_map,
                           tracked_pose=None, T_camera_from_marker=None)

    def _status(self, seen: bool, T_anchor_from_camera: np.ndarray | None) -> str:
        if not self.registered:
            return STATUS_WAITING
        if self.collecting:
            return STATUS_REREGISTERING
        if T_anchor_from_camera is None:
            return STATUS_POSE_LOST
        if self.settings.moving_camera:
            return STATUS_TRACKING
        return STATUS_REGISTERED if seen else STATUS_NOT_FOUND
