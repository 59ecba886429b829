"""Replay of the Victoria Park dataset in GTSAM's text format as a robot driver (pure: a
file in, messages out).

Victoria Park (J. Guivant, E. Nebot, ACFR): a car driven through a park, trees seen by a
laser as point landmarks. GTSAM's ``examples/Data/victoria_park.txt`` holds it as a graph,
one line per edge, whitespace-separated:

* ``ODOMETRY i j dx dy dθ c11 c12 c13 c22 c23 c33`` — pose j relative to pose i (m, m, rad,
  in pose i's frame) and its covariance's upper triangle;
* ``LANDMARK i l x y c11 c12 c22`` — landmark l seen from pose i at (x, y) m in pose i's
  frame, and a covariance of that sighting.

The file has no times and no ground truth; data association is given (landmark ids).
Poses and landmarks share one counter (pose ids skip the landmarks' numbers): the odometry
is read as a chain, each line's j the next line's i.

Conventions (also in ``docs/drivers.md``):

* **Noise, as GTSAM reads the file** (``gtsam/slam/dataset.cpp``): the odometry's six
  values are a covariance, (c11, c22, c33) the variances of (dx, dy, dθ); a sighting's
  c11 = c22 is "the uncertainty at a range of 10 m" — range σ = √c11, bearing σ = √(c11/10)
  rad (GTSAM's own comment: the file's x-y covariance "is not very good"). :meth:`noise`
  gives these; a sighting with c11 ≠ c22 is refused (GTSAM ignores it; there is none).
* **Time.** Pose k is at ``k × step_s`` s (``step_s`` nominal, default 0.2 s: the laser's
  period). Sightings from pose k form one ``Observations`` at that stamp, after the
  odometry that reached it.
* **Odometry as the estimator's unicycle steps.** A step (dx, dy, dθ) is an arc: dy is its
  chord's offset (dy ≈ 0.88 · dx · tan(dθ/2) over the file, correlation 0.9997), which the
  first-order model (drive along θ, then turn) cannot express. Each step is therefore played
  as two ``Odometry``: a turn on the spot by α = atan(dy / dx) over the first tenth of the
  step, then a drive of ±√(dx² + dy²) (the sign of dx: the car reverses in 59 steps) along
  the new heading while turning by dθ − α over the rest. The model's pose after the two
  equals GTSAM's pose composition exactly (a step shorter than 1 µm, where α means nothing,
  is played straight: α = 0). The played speeds stay the car's (≤ 8.2 m/s) and the turn
  rates small (≤ 2.9 rad/s).
* Malformed lines (unknown tag, wrong column count, not numbers, NaN) are skipped and
  counted, with one log line per load. An ODOMETRY line that does not continue the chain
  (a step lost to a malformed line) ends the run there, with its own log line: no pose after
  it could be placed.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamlens.common.arrays import frozen_array
from slamlens.common.errors import SourceError
from slamlens.common.messages import Observations, Odometry

log = logging.getLogger("slamlens.victoria_park")

STEP_S = 0.2  #: nominal seconds per pose step (the file has no times)
TURN_SHARE = 0.1  #: share of a step played as the turn on the spot (module docstring)
_STILL_M = 1e-6  #: a step shorter than this has no chord angle
_COLUMNS = {"ODOMETRY": 11, "LANDMARK": 7}  #: values after the tag


@dataclass
class VictoriaParkStats:
    """What a load kept and what it skipped."""

    odometry: int = 0  #: odometry steps kept (the chain's edges)
    sightings: int = 0  #: landmark sightings kept
    bad_lines: int = 0  #: malformed lines skipped (off-chain ones included)
    first_bad: str = ""  #: the first of them, for the log line
    off_chain: int = 0  #: ODOMETRY lines after the chain broke (the run ends there)
    chain_ends_at: int | None = None  #: the pose where it broke, if it did


@dataclass(frozen=True)
class VictoriaParkNoise:
    """The file's noise as GTSAM reads it (module docstring)."""

    var_dx: float  #: m² per step, along
    var_dy: float  #: m² per step, across (the unicycle model has no such term)
    var_dtheta: float  #: rad² per step
    sigma_range: float  #: m
    sigma_bearing: float  #: rad

    def estimator_sigmas(self, step_s: float = STEP_S) -> dict[str, float]:
        """The estimator's σv, σω, σr, σφ that give a played step (two Odometry of
        t₁ = TURN_SHARE · step_s and t₂ = step_s − t₁, module docstring) the file's
        along-track and heading variances: σv² (t₁² + t₂²) = var_dx, σω² (t₁² + t₂²) =
        var_dθ. (The file's var_dy has no counterpart: the unicycle's lateral error comes
        from its heading error.)"""
        t1 = TURN_SHARE * step_s
        squares = t1 * t1 + (step_s - t1) ** 2
        return {"sigma_v": math.sqrt(self.var_dx / squares),
                "sigma_w": math.sqrt(self.var_dtheta / squares),
                "sigma_range": self.sigma_range, "sigma_bearing": self.sigma_bearing}


@dataclass(frozen=True, eq=False)
class VictoriaParkRun:
    """One loaded file: the pose chain, the sightings, the noise."""

    robot: str
    poses: np.ndarray  #: int64[m + 1], the chain's pose ids in order
    steps: np.ndarray  #: float64[m, 3], (dx, dy, dθ) from poses[k] to poses[k + 1]
    sightings: np.ndarray  #: float64[s, 4], (chain index k, landmark id, x, y), sorted by k
    noise: VictoriaParkNoise
    stats: VictoriaParkStats
    step_s: float = STEP_S

    @property
    def t0(self) -> float:
        return 0.0

    @property
    def duration_s(self) -> float:
        return float(self.steps.shape[0]) * self.step_s

    @property
    def landmark_ids(self) -> np.ndarray:
        return np.unique(self.sightings[:, 1].astype(np.int64))

    def events(self, start: float | None = None, end: float | None = None, *,
               truth: bool = False) -> Iterator[Odometry | Observations]:
        """Time-ordered messages for the poses in [start, end] s (module docstring); the
        file has no truth, so ``truth`` changes nothing."""
        first = 0 if start is None else max(0, math.ceil(start / self.step_s - 1e-9))
        last = self.steps.shape[0] if end is None else \
            min(self.steps.shape[0], math.floor(end / self.step_s + 1e-9))
        k_of = self.sightings[:, 0].astype(np.int64)
        bounds = np.searchsorted(k_of, np.arange(first, last + 2))
        t1 = TURN_SHARE * self.step_s
        t2 = self.step_s - t1
        for k in range(first, last + 1):
            rows = self.sightings[bounds[k - first]:bounds[k - first + 1]]
            if rows.shape[0]:
                yield Observations(robot=self.robot, stamp=k * self.step_s,
                                   ids=rows[:, 1].astype(np.int64),
                                   ranges=np.hypot(rows[:, 2], rows[:, 3]),
                                   bearings=np.arctan2(rows[:, 3], rows[:, 2]))
            if k == last:
                break
            dx, dy, dtheta = (float(v) for v in self.steps[k])
            length = math.hypot(dx, dy)
            alpha = math.atan(dy / dx) if length >= _STILL_M and dx else 0.0
            yield Odometry(robot=self.robot, stamp=k * self.step_s + t1, dt=t1, v=0.0,
                           w=alpha / t1)
            yield Odometry(robot=self.robot, stamp=(k + 1) * self.step_s, dt=t2,
                           v=math.copysign(length, dx) / t2, w=(dtheta - alpha) / t2)


def _parse(path: Path, stats: VictoriaParkStats) -> tuple[list[list[float]], list[list[float]]]:
    """The file's ODOMETRY and LANDMARK rows (values after the tag); bad lines counted."""
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise SourceError(f"Victoria Park file {path}: cannot read ({exc.strerror})") from None
    rows: dict[str, list[list[float]]] = {tag: [] for tag in _COLUMNS}
    for number, line in enumerate(text.splitlines(), start=1):
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        try:
            values = [float(p) for p in parts[1:]]
        except ValueError:
            values = []
        if len(values) != _COLUMNS.get(parts[0], -1) or not all(map(math.isfinite, values)):
            if not stats.bad_lines:
                stats.first_bad = f"{path.name}:{number}: {line.strip()[:60]!r}"
            stats.bad_lines += 1
            continue
        rows[parts[0]].append(values)
    return rows["ODOMETRY"], rows["LANDMARK"]


def _chain(odometry: list[list[float]], stats: VictoriaParkStats) -> np.ndarray:
    """The odometry rows that continue the chain from its first pose. A row that does not
    (a step lost to a malformed line, or a file out of order) ends the run there: no pose
    after it can be placed. The rows after it are counted."""
    kept: list[list[float]] = []
    for row in odometry:
        if kept and row[0] != kept[-1][1]:
            stats.chain_ends_at = int(kept[-1][1])
            stats.off_chain = len(odometry) - len(kept)
            stats.bad_lines += stats.off_chain
            break
        kept.append(row)
    return np.array(kept, dtype=float).reshape(-1, 11)


def _noise(odometry: np.ndarray, sightings: np.ndarray) -> VictoriaParkNoise:
    if not sightings.shape[0]:
        raise SourceError("Victoria Park: no LANDMARK line on the odometry's chain")
    c11, c22 = sightings[:, 4], sightings[:, 6]
    if np.any(np.abs(c11 - c22) >= 1e-4) or np.any(c11 <= 0):
        raise SourceError("Victoria Park: a sighting's covariance is not isotropic "
                          "(c11 ≠ c22); GTSAM's reading needs c11 = c22 > 0")
    cov = np.median(odometry[:, 5:], axis=0)  # one value in the file
    range_var = float(np.median(c11))
    return VictoriaParkNoise(var_dx=float(cov[0]), var_dy=float(cov[3]),
                             var_dtheta=float(cov[5]), sigma_range=math.sqrt(range_var),
                             sigma_bearing=math.sqrt(range_var / 10.0))


def load_victoria_park(path: str | Path, *, robot: str = "robot1",
                       step_s: float = STEP_S) -> VictoriaParkRun:
    """Load GTSAM's ``victoria_park.txt`` (module docstring)."""
    path = Path(path)
    if path.is_dir():
        path = path / "victoria_park_gtsam.txt"
    stats = VictoriaParkStats()
    odometry_rows, landmark_rows = _parse(path, stats)
    odometry = _chain(odometry_rows, stats)
    if not odometry.shape[0]:
        raise SourceError(f"Victoria Park file {path}: no ODOMETRY line")
    poses = np.r_[odometry[:, 0], odometry[-1, 1]].astype(np.int64)
    index = {int(p): k for k, p in enumerate(poses)}
    landmarks = np.array(landmark_rows, dtype=float).reshape(-1, 7)
    on_chain = np.array([int(p) in index for p in landmarks[:, 0]], dtype=bool)
    if not on_chain.all():
        stats.bad_lines += int(np.count_nonzero(~on_chain))
        stats.first_bad = stats.first_bad or (
            f"LANDMARK from pose {int(landmarks[~on_chain][0, 0])}, not on the odometry's chain")
    landmarks = landmarks[on_chain]
    k = np.array([index[int(p)] for p in landmarks[:, 0]], dtype=float)
    sightings = np.column_stack([k, landmarks[:, 1:4]])
    sightings = sightings[np.argsort(k, kind="stable")]
    stats.odometry, stats.sightings = int(odometry.shape[0]), int(sightings.shape[0])
    if stats.bad_lines - stats.off_chain:
        log.warning("Victoria Park %s: %d malformed line(s) skipped, first %s", path.name,
                    stats.bad_lines - stats.off_chain, stats.first_bad)
    if stats.off_chain:
        log.warning("Victoria Park %s: the odometry chain breaks after pose %d: the run ends "
                    "there, %d later ODOMETRY line(s) unused", path.name,
                    stats.chain_ends_at, stats.off_chain)
    return VictoriaParkRun(robot=robot, poses=frozen_array(poses, "<i8"),
                           steps=frozen_array(odometry[:, 2:5], "<f8"),
                           sightings=frozen_array(sightings, "<f8"),
                           noise=_noise(odometry, landmarks), stats=stats, step_s=step_s)
