"""The bus's messages in, what to log to Rerun out (pure; docs/rerun.md).

:class:`RerunTranslator` keeps what one robot's picture needs between messages — the path,
the newest health's flags and verdict, the true landmarks already shown, the timeline
kind — and turns each message into :class:`Batch` es: the timeline values and the
:class:`~slamlens.services.rerun.draw.Log` s to log at them.

* a ``state`` (or, ``--source summary``, a robot's ``summary``) → the P_d ellipsoids and
  pair lines of the mode, the features, the suspects, the robot, the P_d sizes, and the
  path at most once per second of robot time (always on a new map); at most ``scene_hz``
  states per robot second;
* a ``health`` → NEES, NIS and their bands, the verdict when it changes, the violations;
* a ``truth`` → the true pose, the true path (once per robot second), the true landmarks
  when they change;
* a camera's ``registration`` → its pose and pinhole, its ``frame`` → the JPEG.

Timelines (:mod:`.entities`): ``stamp`` is the robot's clock — the stamps of its states,
health and truth. A camera frame goes at its own stamp when that is on the same kind of
clock (both from 0, or both Unix time), else at the robot's newest stamp; a registration
goes at the robot's newest stamp (it holds from when it is known; its own stamp is that of
the frame it was computed from, often on the camera's clock). Camera messages that come
before any robot data wait (a registration) or are skipped (frames, counted ``early``).

A malformed payload raises :class:`~slamlens.common.errors.MessageError` (the caller drops
and counts it).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import rerun as rr

from slamlens.common.messages import (
    CameraFrame,
    Health,
    Registration,
    SlamState,
    StateSummary,
    Truth,
)
from slamlens.common.scene3d import PairGlyphs, flagged_pairs, pair_glyphs, summary_glyphs
from slamlens.services.rerun.draw import (
    TRUTH,
    Log,
    camera_logs,
    features_logs,
    glyph_logs,
    health_logs,
    image_log,
    path_log,
    pd_logs,
    robot_log,
    robot_path_log,
    static_logs,
    truth_logs,
)
from slamlens.services.rerun.entities import (
    TIMELINE_SEQ,
    TIMELINE_STAMP,
    UNIX_STAMP_S,
    truth_path,
)
from slamlens.services.rerun.settings import RerunSettings

PATH_PERIOD_S = 1.0  #: a path is logged at most once per this much robot time
KINDS = ("state", "summary", "health", "truth", "frame", "registration")

Times = tuple[tuple[str, str, float | int], ...]


@dataclass(frozen=True)
class Batch:
    """Logs that share their timeline values (none: static)."""

    times: Times
    logs: list[Log]


def log_batches(rec: rr.RecordingStream, batches: list[Batch]) -> int:
    """Log ``batches`` to ``rec``, each at its timeline values; how many log calls."""
    logged = 0
    for batch in batches:
        rec.reset_time()
        for timeline, kind, value in batch.times:
            rec.set_time(timeline, **{kind: value})
        for item in batch.logs:
            rec.log(item.path, *item.parts, static=item.static)
            logged += 1
    return logged


@dataclass
class _Path:
    """A path of points, thinned beyond a length, logged at most once per period."""

    limit: int
    points: list[tuple[float, float]] = field(default_factory=list)
    last_logged: float | None = None

    def add(self, x: float, y: float) -> None:
        if not self.points or self.points[-1] != (x, y):
            self.points.append((x, y))
            if len(self.points) > 2 * self.limit:
                self.points = self.points[::2]  # the old path thinned, its shape kept

    def due(self, stamp: float, *, force: bool = False) -> bool:
        if (force or self.last_logged is None or stamp < self.last_logged
                or stamp - self.last_logged >= PATH_PERIOD_S):
            self.last_logged = stamp
            return True
        return False

    def reset(self) -> None:
        self.points, self.last_logged = [], None


class RerunTranslator:
    """Messages of one robot (and its cameras) in, :class:`Batch` es out."""

    def __init__(self, settings: RerunSettings) -> None:
        self.settings = settings
        self.robot = settings.robot
        self.scene = settings.scene_settings()
        self._stamp_kind: str | None = None
        self.seq = 0  #: the newest state's seq (the seq of what is not a state)
        self._stamp = 0.0  #: the newest stamp on the robot's clock
        self._epoch: int | None = None
        self._path = _Path(self.scene.path_points)
        self._truth_path = _Path(self.scene.path_points)
        self._last_drawn: float | None = None
        self._verdict: str | None = None
        self._flagged: frozenset[tuple[int, int]] = frozenset()
        self._suspects: tuple[int, ...] = ()
        self._truth_map: tuple[bytes, bytes] | None = None
        self._registrations: dict[str, bytes] = {}
        self._pending: dict[str, list[Log]] = {}  #: registrations waiting for the clock
        self.drawn = 0  #: states (or summaries) drawn
        self.skipped = 0  #: states not drawn because of ``scene_hz``
        self.glyphs = 0  #: ellipsoids in the last picture
        self.maps = 0  #: maps started (epochs seen, restarts)
        self.early = 0  #: camera frames before any robot data (not shown)
        self.images = 0  #: camera frames logged
        self.cameras = 0  #: registrations logged

    def start(self) -> list[Batch]:
        return [Batch((), static_logs(self.robot))]

    def feed(self, kind: str, payload: bytes) -> list[Batch]:
        """The batches of one message of ``kind`` (one of :data:`KINDS`)."""
        return {"state": self._state, "summary": self._summary, "health": self._health,
                "truth": self._truth, "frame": self._frame,
                "registration": self._registration}[kind](payload)

    def times(self, stamp: float, seq: int) -> Times:
        """The timeline values of robot data stamped ``stamp`` at state ``seq`` (the first
        one decides how the ``stamp`` timeline reads: a duration, or a date)."""
        if self._stamp_kind is None:
            self._stamp_kind = "timestamp" if stamp >= UNIX_STAMP_S else "duration"
        return ((TIMELINE_STAMP, self._stamp_kind, float(stamp)),
                (TIMELINE_SEQ, "sequence", int(seq)))

    def _robot_clock(self, stamp: float) -> Times:
        """Times of a message on the robot's clock (state, summary, health, truth)."""
        self._stamp = stamp
        return self.times(stamp, self.seq)

    def _camera_times(self, stamp: float | None) -> Times | None:
        """Times of a camera's message: its own stamp if it is on the robot's kind of clock,
        else (a camera on wall time beside a simulated robot) the robot's newest stamp;
        None before any robot data (nothing to show it with yet)."""
        if self._stamp_kind is None:
            return None
        unix = self._stamp_kind == "timestamp"
        own = stamp is not None and (stamp >= UNIX_STAMP_S) == unix
        return self.times(stamp if own and stamp is not None else self._stamp, self.seq)

    # -- the picture -------------------------------------------------------------------
    def _state(self, payload: bytes) -> list[Batch]:
        state = SlamState.from_bytes(payload, check_symmetry=False)
        return self._picture(state.seq, state.epoch, state.stamp, state.pose,
                             state.landmark_ids, state.landmarks,
                             lambda: pair_glyphs(state, self.scene, self._flagged))

    def _summary(self, payload: bytes) -> list[Batch]:
        summary = StateSummary.from_bytes(payload)
        return self._picture(summary.seq, summary.epoch, summary.stamp, summary.pose,
                             summary.landmark_ids, summary.landmarks,
                             lambda: summary_glyphs(summary, self.scene, self._flagged))

    def _picture(self, seq: int, epoch: int, stamp: float, pose: np.ndarray, ids: np.ndarray,
                 xy: np.ndarray, glyphs_of: Callable[[], PairGlyphs]) -> list[Batch]:
        new_map = self._epoch != epoch or seq < self.seq
        if new_map:
            self._epoch = epoch
            self._path.reset()
            self._last_drawn = None
            self.maps += 1
        self.seq = seq
        times = self._robot_clock(stamp)
        self._path.add(float(pose[0]), float(pose[1]))
        pending = self._pending_camera()
        hz = self.settings.scene_hz
        if (hz > 0 and self._last_drawn is not None and self._last_drawn <= stamp
                < self._last_drawn + 1.0 / hz):
            self.skipped += 1
            return pending
        self._last_drawn = stamp
        glyphs = glyphs_of()
        logs = [*glyph_logs(self.robot, glyphs),
                *features_logs(self.robot, ids, xy, self._suspects),
                robot_log(self.robot, pose), *pd_logs(self.robot, glyphs.sizes_m)]
        if self._path.due(stamp, force=new_map):
            logs.append(robot_path_log(self.robot, self._path.points))
        self.drawn += 1
        self.glyphs = len(glyphs.centres)
        return [*pending, Batch(times, logs)]

    # -- the rest ----------------------------------------------------------------------
    def _health(self, payload: bytes) -> list[Batch]:
        health = Health.from_bytes(payload)
        self._flagged = flagged_pairs(health)
        self._suspects = tuple(int(s) for s in health.suspects.tolist())
        logs = health_logs(self.robot, health, self._verdict)
        self._verdict = health.verdict
        times = self._robot_clock(health.stamp)
        times = times[:1] + ((TIMELINE_SEQ, "sequence", int(health.seq)),)
        return [*self._pending_camera(), Batch(times, logs)]

    def _truth(self, payload: bytes) -> list[Batch]:
        truth = Truth.from_bytes(payload)
        self._truth_path.add(float(truth.pose[0]), float(truth.pose[1]))
        map_key = (truth.landmark_ids.tobytes(), truth.landmarks.tobytes())
        new_landmarks = map_key != self._truth_map
        self._truth_map = map_key
        logs = truth_logs(self.robot, truth.pose,
                          ids=truth.landmark_ids if new_landmarks else None,
                          xy=truth.landmarks if new_landmarks else None)
        if self._truth_path.due(truth.stamp):
            logs.append(path_log(truth_path(self.robot, "path"), self._truth_path.points, TRUTH))
        times = self._robot_clock(truth.stamp)
        return [*self._pending_camera(), Batch(times, logs)]

    def _frame(self, payload: bytes) -> list[Batch]:
        frame = CameraFrame.from_bytes(payload)
        times = self._camera_times(frame.stamp)
        if times is None:
            self.early += 1
            return []
        log = image_log(frame)
        self.images += 1
        return [Batch(times, [log])]

    def _registration(self, payload: bytes) -> list[Batch]:
        """A camera's pose and pinhole, on the robot's clock from when the sink has it (a
        registration's stamp is the frame it was computed from, often on another clock)."""
        reg = Registration.from_bytes(payload)
        if self._registrations.get(reg.camera) == payload:
            return []  # the same registration again (asked for at start, then published)
        self._registrations[reg.camera] = payload
        self._pending[reg.camera] = camera_logs(reg)
        return self._pending_camera()

    def _pending_camera(self) -> list[Batch]:
        """The registrations not logged yet, once the robot's clock is known."""
        times = self._camera_times(None)
        if times is None or not self._pending:
            return []
        logs = [log for logs in self._pending.values() for log in logs]
        self.cameras += len(self._pending)
        self._pending.clear()
        return [Batch(times, logs)]

    def finish(self) -> list[Batch]:
        """The paths as they are at the end (the last ones logged may be up to a second
        of robot time old)."""
        if self._stamp_kind is None:
            return []
        logs = [robot_path_log(self.robot, self._path.points)]
        if self._truth_path.points:
            logs.append(path_log(truth_path(self.robot, "path"), self._truth_path.points, TRUTH))
        return [Batch(self.times(self._stamp, self.seq), logs)]
