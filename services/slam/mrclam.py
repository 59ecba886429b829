"""Replay of the UTIAS MRCLAM dataset as a robot driver (pure: files in, messages out).

Files of one dataset folder (Leung et al., IJRR 2011), whitespace-separated, ``#`` comments:

* ``Robot{k}_Odometry.dat``     t, v m/s, ω rad/s (commanded, ~100 Hz)
* ``Robot{k}_Measurement.dat``  t, barcode, range m, bearing rad
* ``Robot{k}_Groundtruth.dat``  t, x m, y m, θ rad (Vicon, dataset world frame)
* ``Barcodes.dat``              subject, barcode
* ``Landmark_Groundtruth.dat``  subject, x m, y m, σx m, σy m

Conventions (also in ``docs/drivers.md``):

* Odometry sample i, (v_i, ω_i) at t_i, is held until the next sample: it becomes
  ``Odometry(stamp=t_{i+1}, dt=t_{i+1} − t_i, v_i, ω_i)``; the last sample has no end and is
  dropped. Repeated timestamps give dt = 0 steps, kept.
* Measurements with identical timestamps form one ``Observations`` batch, in file order.
  Ids are landmark subject numbers (6–20). Barcodes of subjects without landmark ground
  truth (the robots, subjects 1–5) are skipped, as are barcodes in no subject; both counted.
* The map frame (protocol.md) is the robot's ground-truth pose at the replay's origin time = the
  first odometry sample in the window, linearly interpolated; poses and landmarks are
  transformed into it. ``Truth`` is emitted once at the origin time (pose 0, 0, 0) and then at
  every ground-truth sample after it.
* Stamps are the dataset's own times (s). ``events(start, end)`` takes seconds *after* the
  run's first odometry sample; at equal stamps the order is odometry, truth, observations.
* Malformed lines (wrong column count, not numbers, NaN, negative range) are skipped and
  counted, with one log line per load.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slamlens.common.arrays import frozen_array
from slamlens.common.errors import SourceError
from slamlens.common.geometry import wrap_angle
from slamlens.common.messages import Observations, Odometry, Truth

log = logging.getLogger("slamlens.mrclam")

_ODOMETRY, _TRUTH, _OBSERVATIONS = 0, 1, 2  # order of events sharing a stamp


@dataclass
class MrclamStats:
    """What a load kept and what it skipped."""

    odometry: int = 0  #: odometry samples read
    measurements: int = 0  #: landmark measurements kept
    batches: int = 0  #: observation batches (distinct measurement times)
    groundtruth: int = 0  #: ground-truth samples read
    skipped_robot: int = 0  #: measurements of other robots (subjects without landmark truth)
    skipped_unknown_barcode: int = 0  #: measurements of barcodes in no subject
    unknown_barcodes: tuple[int, ...] = ()  #: those barcodes
    bad_lines: dict[str, int] = field(default_factory=dict)  #: malformed lines per file

    @property
    def total_bad_lines(self) -> int:
        return sum(self.bad_lines.values())


@dataclass
class _BadLines:
    count: int = 0
    first: str = ""

    def add(self, path: Path, number: int, line: str) -> None:
        if not self.count:
            self.first = f"{path.name}:{number}: {line.strip()[:60]!r}"
        self.count += 1


RowCheck = Callable[[list[float]], bool]


def _read_table(path: Path, columns: int, bad: _BadLines, *,
                check: RowCheck | None = None) -> np.ndarray:
    """Numeric rows of ``path`` with exactly ``columns`` finite values; others counted."""
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise SourceError(f"MRCLAM file {path}: cannot read ({exc.strerror})") from None
    rows: list[list[float]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        parts = stripped.split()
        try:
            values = [float(p) for p in parts]
        except ValueError:
            values = []
        if len(values) != columns or not all(math.isfinite(v) for v in values) or (
                check is not None and not check(values)):
            bad.add(path, number, line)
            continue
        rows.append(values)
    return np.array(rows, dtype=float).reshape(-1, columns)


def _sorted_by_time(table: np.ndarray) -> np.ndarray:
    if table.shape[0] and np.any(np.diff(table[:, 0]) < 0):
        table = table[np.argsort(table[:, 0], kind="stable")]
    return table


@dataclass(frozen=True, eq=False)
class MrclamRun:
    """One robot's run of an MRCLAM dataset, parsed. Build it with :func:`load_mrclam`."""

    robot_number: int  #: k of Robot{k}_*.dat
    robot: str  #: robot name put in the messages
    odometry: np.ndarray  #: float64[N, 3]: t s, v m/s, ω rad/s
    measurements: np.ndarray  #: float64[M, 4]: t s, landmark subject, range m, bearing rad
    groundtruth: np.ndarray  #: float64[G, 4]: t s, x m, y m, θ rad (dataset world frame)
    landmark_ids: np.ndarray  #: int64[L] landmark subjects
    landmarks_world: np.ndarray  #: float64[L, 2] in the dataset world frame, m
    landmarks_std: np.ndarray  #: float64[L, 2] ground-truth standard deviations, m
    stats: MrclamStats

    @property
    def t0(self) -> float:
        """Time of the first odometry sample: ``events(start=0)`` begins here."""
        return float(self.odometry[0, 0])

    @property
    def duration_s(self) -> float:
        """From the first to the last odometry sample, s."""
        return float(self.odometry[-1, 0] - self.odometry[0, 0])

    def pose_at(self, t: float) -> np.ndarray | None:
        """Ground-truth pose (world frame) at ``t``, linearly interpolated; None outside it."""
        gt = self.groundtruth
        if gt.shape[0] == 0 or not gt[0, 0] <= t <= gt[-1, 0]:
            return None
        i = int(np.searchsorted(gt[:, 0], t, side="right"))
        if i >= gt.shape[0]:
            return gt[-1, 1:].copy()
        a, b = gt[i - 1], gt[i]
        span = b[0] - a[0]
        f = 0.0 if span <= 0 else (t - a[0]) / span
        dtheta = float(wrap_angle(b[3] - a[3]))  # interpolate the angle the short way round
        return np.array([a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2]),
                         float(wrap_angle(a[3] + f * dtheta))])

    def origin_time(self, start: float | None = None) -> float:
        """The map origin's time for ``events(start, …)``: the first odometry sample whose
        step lies in the window (s, dataset time)."""
        odo = self.odometry
        t_lo = self.t0 + (0.0 if start is None else start)
        first = np.nonzero(odo[:-1, 0] >= t_lo)[0]
        return float(odo[first[0], 0]) if first.size else t_lo

    def truth_in_map_frame(self, start: float | None = None) -> tuple[np.ndarray, np.ndarray,
                                                                      np.ndarray]:
        """Ground truth in the map frame of ``events(start, …)``: (stamps [G], poses [G, 3],
        landmarks [L, 2] in ``landmark_ids`` order); empty if there is none at the origin."""
        origin_t = self.origin_time(start)
        origin = self.pose_at(origin_t)
        if origin is None:
            return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 2))
        gt = self.groundtruth[self.groundtruth[:, 0] > origin_t]
        poses, landmarks = to_map_frame(origin, np.vstack([origin, gt[:, 1:]]),
                                        self.landmarks_world)
        return np.r_[origin_t, gt[:, 0]], np.array(poses), np.array(landmarks)

    def events(self, start: float | None = None, end: float | None = None, *,
               truth: bool = True) -> Iterator[Odometry | Observations | Truth]:
        """Time-ordered messages for the window [t0 + start, t0 + end] (seconds after t0).

        An odometry step is included when its whole interval lies in the window.
        """
        odo = self.odometry
        t_lo = self.t0 + (0.0 if start is None else start)
        t_hi = math.inf if end is None else self.t0 + end
        keep = (odo[:-1, 0] >= t_lo) & (odo[1:, 0] <= t_hi)
        first = np.nonzero(keep)[0]
        origin_t = float(odo[first[0], 0]) if first.size else t_lo
        odo_i = first
        odo_stamps = odo[odo_i + 1, 0]

        meas = self.measurements
        in_window = (meas[:, 0] >= t_lo) & (meas[:, 0] <= t_hi)
        meas = meas[in_window]
        batch_starts = np.nonzero(np.r_[True, np.diff(meas[:, 0]) != 0])[0] if meas.shape[0] \
            else np.zeros(0, dtype=int)
        batch_ends = np.r_[batch_starts[1:], meas.shape[0]].astype(int)

        gt = self.groundtruth
        origin = self.pose_at(origin_t) if truth else None
        if truth and origin is None:
            log.warning("MRCLAM robot %d: no ground truth at the replay origin t=%.3f; "
                        "replaying without truth", self.robot_number, origin_t)
        if origin is not None:
            # a Truth at the origin itself first (pose 0, 0, 0), then every sample after it
            gt_w = gt[(gt[:, 0] > origin_t) & (gt[:, 0] <= t_hi)]
            poses_map, landmarks_map = to_map_frame(
                origin, np.vstack([origin, gt_w[:, 1:]]), self.landmarks_world)
            gt_stamps = np.r_[origin_t, gt_w[:, 0]]
        else:
            poses_map = np.zeros((0, 3))
            landmarks_map = frozen_array(np.zeros((0, 2)), "<f8")
            gt_stamps = np.zeros(0)

        stamps = np.concatenate([odo_stamps, gt_stamps, meas[batch_starts, 0]])
        kinds = np.concatenate([np.full(odo_stamps.size, _ODOMETRY),
                                np.full(gt_stamps.size, _TRUTH),
                                np.full(batch_starts.size, _OBSERVATIONS)])
        index = np.concatenate([np.arange(odo_stamps.size), np.arange(gt_stamps.size),
                                np.arange(batch_starts.size)])
        order = np.lexsort((index, kinds, stamps))  # by stamp, then kind, then file order

        ids_all = frozen_array(meas[:, 1], "<i8")
        ranges_all = frozen_array(meas[:, 2], "<f8")
        bearing = meas[:, 3]
        # wrap only what is out of range: wrapping adds rounding to values already in range
        bearings_all = frozen_array(np.where((bearing < -math.pi) | (bearing >= math.pi),
                                             wrap_angle(bearing), bearing), "<f8")
        for k in order:
            kind, i = kinds[k], int(index[k])
            if kind == _ODOMETRY:
                row = odo_i[i]
                yield Odometry(robot=self.robot, stamp=float(odo_stamps[i]),
                               dt=float(odo[row + 1, 0] - odo[row, 0]),
                               v=float(odo[row, 1]), w=float(odo[row, 2]))
            elif kind == _TRUTH:
                yield Truth(robot=self.robot, stamp=float(gt_stamps[i]), pose=poses_map[i],
                            landmark_ids=self.landmark_ids, landmarks=landmarks_map)
            else:
                a, b = int(batch_starts[i]), int(batch_ends[i])
                yield Observations(robot=self.robot, stamp=float(meas[a, 0]),
                                   ids=ids_all[a:b], ranges=ranges_all[a:b],
                                   bearings=bearings_all[a:b])


def to_map_frame(origin: np.ndarray, poses_world: np.ndarray,
                  landmarks_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Poses [G,3] and landmarks [L,2] in the frame of the world pose ``origin``."""
    x0, y0, th0 = origin
    c, s = math.cos(th0), math.sin(th0)
    R_map_from_world = np.array([[c, s], [-s, c]])
    xy = (poses_world[:, :2] - [x0, y0]) @ R_map_from_world.T
    theta = wrap_angle(poses_world[:, 2] - th0)
    poses = frozen_array(np.column_stack([xy, theta]), "<f8")
    landmarks = frozen_array((landmarks_world - [x0, y0]) @ R_map_from_world.T, "<f8")
    return poses, landmarks


def available_robots(folder: str | Path) -> list[int]:
    """Robot numbers k with a Robot{k}_Odometry.dat in ``folder``."""
    found = []
    for p in Path(folder).glob("Robot*_Odometry.dat"):
        number = p.name[len("Robot"):-len("_Odometry.dat")]
        if number.isdigit():
            found.append(int(number))
    return sorted(found)


def load_mrclam(folder: str | Path, robot: int = 1, *,
                robot_name: str | None = None,
                truth_folder: str | Path | None = None) -> MrclamRun:
    """Parse robot ``robot``'s files of an MRCLAM folder (see the module docstring).

    ``robot_name`` is the name put in the messages (default ``robot{robot}``);
    ``truth_folder`` holds ``Robot{k}_Groundtruth.dat`` and ``Landmark_Groundtruth.dat``
    if they are not in ``folder`` (default: ``folder``).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise SourceError(f"MRCLAM folder {folder} does not exist")
    truth_dir = folder if truth_folder is None else Path(truth_folder)
    if not truth_dir.is_dir():
        raise SourceError(f"MRCLAM ground-truth folder {truth_dir} does not exist")
    prefix = folder / f"Robot{robot}"
    if not Path(f"{prefix}_Odometry.dat").is_file():
        raise SourceError(f"MRCLAM folder {folder}: no Robot{robot}_Odometry.dat; robots "
                          f"present: {available_robots(folder) or 'none'}")
    bad: dict[str, _BadLines] = {}

    def read(filename: str, columns: int, check: RowCheck | None = None, *,
             where: Path = folder) -> np.ndarray:
        bad[filename] = _BadLines()
        return _read_table(where / filename, columns, bad[filename], check=check)

    def is_int(v: float) -> bool:
        return v == int(v)

    barcodes = read("Barcodes.dat", 2, lambda r: is_int(r[0]) and is_int(r[1]))
    landmarks = read("Landmark_Groundtruth.dat", 5, lambda r: is_int(r[0]), where=truth_dir)
    odometry = _sorted_by_time(read(f"Robot{robot}_Odometry.dat", 3))
    groundtruth = _sorted_by_time(read(f"Robot{robot}_Groundtruth.dat", 4, where=truth_dir))
    raw_meas = _sorted_by_time(read(f"Robot{robot}_Measurement.dat", 4,
                                    lambda r: is_int(r[1]) and r[2] >= 0))
    if odometry.shape[0] < 2:
        raise SourceError(f"MRCLAM {prefix}_Odometry.dat: fewer than two odometry samples")

    subject_of = {int(b): int(s) for s, b in barcodes}
    landmark_subjects = {int(s) for s in landmarks[:, 0]}
    barcode = raw_meas[:, 1].astype(int)
    subject = np.array([subject_of.get(b, -1) for b in barcode], dtype=int)
    unknown = subject < 0
    is_landmark = np.isin(subject, list(landmark_subjects))
    measurements = raw_meas[is_landmark].copy()
    measurements[:, 1] = subject[is_landmark]

    stats = MrclamStats(
        odometry=odometry.shape[0], measurements=measurements.shape[0],
        batches=len(np.unique(measurements[:, 0])), groundtruth=groundtruth.shape[0],
        skipped_robot=int(np.sum(~unknown & ~is_landmark)),
        skipped_unknown_barcode=int(np.sum(unknown)),
        unknown_barcodes=tuple(sorted({int(b) for b in barcode[unknown]})),
        bad_lines={k: v.count for k, v in bad.items() if v.count})
    if stats.total_bad_lines:
        first = next(v.first for v in bad.values() if v.count)
        log.warning("MRCLAM %s: skipped %d malformed line(s) (first: %s)", folder,
                    stats.total_bad_lines, first)
    if stats.skipped_unknown_barcode:
        log.info("MRCLAM robot %d: skipped %d measurement(s) of unknown barcode(s) %s",
                 robot, stats.skipped_unknown_barcode, list(stats.unknown_barcodes))

    order = np.argsort(landmarks[:, 0], kind="stable")
    landmarks = landmarks[order]
    return MrclamRun(
        robot_number=robot, robot=robot_name or f"robot{robot}",
        odometry=frozen_array(odometry, "<f8"), measurements=frozen_array(measurements, "<f8"),
        groundtruth=frozen_array(groundtruth, "<f8"),
        landmark_ids=frozen_array(landmarks[:, 0], "<i8"),
        landmarks_world=frozen_array(landmarks[:, 1:3], "<f8"),
        landmarks_std=frozen_array(landmarks[:, 3:5], "<f8"), stats=stats)
