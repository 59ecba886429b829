"""Settings of the SLAM side: ``sim``, ``replay``, ``serial``, ``estimator``, ``summary``
and ``tune``.

One frozen dataclass per command; every field is a TOML key of ``--config FILE`` and a
flag over it (:func:`slamlens.common.config.setting`; docs/cli.md lists them all). No numpy here:
``slamlens estimator --help`` must not load it before the one-BLAS-thread default is set.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from slamlens.common.config import setting
from slamlens.common.errors import ConfigError

#: planted fault kinds (services/slam/faults.py says what each does)
NONE, MAP_UPDATE, CROSS_COVARIANCE = "none", "map-update", "cross-covariance"
FAULT_KINDS = (NONE, MAP_UPDATE, CROSS_COVARIANCE)
#: where the estimator's Jacobians are evaluated (services/slam/linearisation.py)
STANDARD, FEJ, OC, INVARIANT = "standard", "fej", "oc", "invariant"
LINEARISATIONS = (STANDARD, FEJ, OC, INVARIANT)


def check_fault(kind: str, feature_ids: tuple[int, ...], magnitude: float | None) -> None:
    """A planted fault's configuration, checked (ConfigError naming what is wrong);
    ``magnitude`` None = the kind's default."""
    if kind == NONE:
        return
    if kind not in FAULT_KINDS:
        raise ConfigError(f"unknown fault kind {kind!r}; one of {FAULT_KINDS[1:]}")
    if not feature_ids:
        raise ConfigError(f"fault {kind!r} needs at least one faulty feature id")
    if magnitude is None:
        return
    if kind == MAP_UPDATE and not magnitude >= 0.0:
        raise ConfigError(f"map-update magnitude must be ≥ 0 m², got {magnitude}")
    if kind == CROSS_COVARIANCE and not 0.0 <= magnitude <= 1.0:
        raise ConfigError(f"cross-covariance magnitude is a fraction in [0, 1], got {magnitude}")


def _robot() -> str:
    return setting("robot1", doc="robot name, a key segment")


def _progress() -> str:
    return setting("auto", doc="progress bar on stderr (data time, × real time, time left): "
                               "auto = only on a terminal", choices=("auto", "on", "off"))


# ------------------------------------------------------------------------------ drivers


@dataclass(frozen=True)
class SimSettings:
    """``slamlens sim``: the simulated robot (docs/simulator.md)."""

    robot: str = setting("robot1", doc="robot name, a key segment; several, comma-separated, "
                                       "drive the same loop in one arena, each from the next "
                                       "corner", metavar="R[,R…]")
    marker_ids: tuple[int, ...] = setting(
        (), doc="the fiducial marker id each robot carries, in --robot order (in its Truth, "
                "for a synthetic camera); empty = 0, 1, 2 …", metavar="ID,ID")
    scenario: str = setting("paper", doc="world: a packaged world name (paper, grid, large) or the "
                                         "path of a world TOML file", metavar="WORLD")
    seed: int = setting(0, doc="random seed: same seed, same run")
    rate: float = setting(1.0, doc="× real time; 0 = as fast as possible", min=0.0)
    loops: int = setting(0, doc="laps of the waypoint loop; 0 = the world's default", min=0)
    anonymous: bool = setting(False, doc="publish landmark id −1 (the estimator associates)")
    wait_for_estimator: bool = setting(
        True, doc="wait until the robot's estimator is alive before the first message",
        flag="--no-wait")
    wait_timeout_s: float = setting(60.0, doc="give up waiting for the estimator after this",
                                    unit="s", min=0.0)
    hold_s: float = setting(
        0.0, doc="stand at the start pose (truth repeated at 10 Hz) before moving, so that a "
                 "camera can register the map frame there (paper §3.1)", unit="s", min=0.0,
        flag="--hold", metavar="SECONDS")
    progress: str = _progress()

    def __post_init__(self) -> None:
        robots = self.robots()
        if len(set(robots)) != len(robots):
            raise ConfigError(f"setting 'robot': {self.robot!r} names a robot twice")
        if self.marker_ids and len(self.marker_ids) != len(robots):
            raise ConfigError(f"setting 'marker_ids': {len(self.marker_ids)} ids for "
                              f"{len(robots)} robots ({self.robot})")
        if any(i < 0 for i in self.marker_ids):
            raise ConfigError("setting 'marker_ids': ids must be ≥ 0")

    def robots(self) -> list[str]:
        """The robot names, in order (one unless --robot lists several)."""
        return [r.strip() for r in self.robot.split(",") if r.strip()] or [self.robot]

    def marker_id_of(self, index: int) -> int:
        """The marker id of the ``index``-th robot."""
        return int(self.marker_ids[index]) if self.marker_ids else index


@dataclass(frozen=True)
class ReplaySettings:
    """``slamlens replay``: a recorded dataset as a robot driver (docs/drivers.md)."""

    path: str = setting("", doc="dataset folder (e.g. ../shared/data/mrclam6, or a rosbag2 "
                                "folder), or GTSAM's victoria_park.txt", positional=True,
                        required=True, metavar="PATH")
    robot: str = _robot()
    format: str = setting("mrclam", doc="dataset format: mrclam | rosbag2 (a bag of a ROS 2 "
                                        "robot's topics, docs/ros2.md) | victoria-park (GTSAM's "
                                        "text file, docs/drivers.md)",
                          choices=("mrclam", "rosbag2", "victoria-park"))
    step_s: float = setting(0.2, doc="victoria-park: seconds per pose step (the file has no "
                                     "times; deploy/victoria_park.toml's σv, σω are for 0.2)",
                            unit="s", min=1e-3, metavar="SECONDS")
    from_ros: str = setting("inputs", doc="rosbag2: play the bag's /R/odom and "
                                          "/R/landmarks/observations as the robot's inputs, or "
                                          "its /R/slam/estimate (or /R/slam/pose) as its states",
                            choices=("inputs", "estimate"))
    robot_index: int = setting(1, doc="which robot of the dataset: MRCLAM Robot{k}_*.dat",
                               min=1)
    robots: str = setting(
        "", doc="publish several robots of the dataset at once: all, or their numbers "
                "K,K; each is named robot{K} (--robot and --robot-index are then unused); "
                "empty = one robot", metavar="all|K,K")
    rate: float = setting(1.0, doc="× real time; 0 = as fast as possible", min=0.0)
    start_s: float = setting(0.0, doc="dataset seconds to skip from the start", unit="s",
                             flag="--start", metavar="SECONDS")
    duration_s: float = setting(0.0, doc="dataset seconds to play; 0 = all", unit="s",
                                flag="--duration", metavar="SECONDS")
    wait_for_estimator: bool = setting(
        True, doc="wait until the robot's estimator is alive before the first message",
        flag="--no-wait")
    wait_timeout_s: float = setting(60.0, doc="give up waiting for the estimator after this",
                                    unit="s", min=0.0)
    progress: str = _progress()

    def __post_init__(self) -> None:
        if self.robots and self.robots != "all":
            try:
                numbers = [int(k) for k in self.robots.split(",") if k.strip()]
            except ValueError:
                numbers = []
            if not numbers or any(k < 1 for k in numbers):
                raise ConfigError(f"setting 'robots': {self.robots!r} is neither 'all' nor "
                                  "robot numbers K,K (from 1)")


@dataclass(frozen=True)
class TuneSettings:
    """``slamlens tune``: noise settings fitted to runs with ground truth, as an estimator
    settings TOML (docs/estimator.md, "Tuning on real data")."""

    path: str = setting("", doc="dataset folder (e.g. ../shared/data/mrclam6)",
                        positional=True, required=True, metavar="RUN")
    truth: str = setting("", doc="folder with the ground truth (MRCLAM Robot{k}_Groundtruth.dat"
                                 " and Landmark_Groundtruth.dat); empty = the run's folder",
                         metavar="DIR")
    format: str = setting("mrclam", doc="dataset format", choices=("mrclam",))
    robot_index: tuple[int, ...] = setting(
        (1,), doc="robots of the dataset to fit together (one profile for all of them)",
        metavar="K,K")
    motion_model: str = setting(
        "spec", doc="odometry noise to fit: spec = the standard σv, σω; distance = the opt-in "
                    "terms growing with distance and turn instead (not the standard model)",
        choices=("spec", "distance"))
    gate_chi2: float = setting(13.82, doc="innovation gate written into the profile (χ²₂ "
                                          "99.9 %); 0 = none", min=0.0)
    linearisation: str = setting(
        "all", doc="the estimator's linearisation to fit for: standard, fej, oc, invariant, or "
                   "all = "
                   "fit each and choose by the robots left out (by the fit itself with one "
                   "robot or --no-cross-validate)", choices=(*LINEARISATIONS, "all"))
    update_iterations: int = setting(
        1, doc="fit for the iterated EKF: the estimator's --update-iterations, used in every "
               "pass and written into the profile; 1 = the EKF (fej: no effect)",
        min=1, max=100)
    cross_validate: bool = setting(
        True, doc="leave each robot out in turn: fit on the others, score it (NEES, landmark "
                  "RMSE after a rigid fit), report, and choose the linearisation by that; "
                  "needs two robots or more (docs/estimator.md)", flag="--no-cross-validate")
    scale: str = setting(
        "motion", doc="what the NEES scale multiplies: motion = the odometry σ only (the "
                      "sensor σ stay as measured against the truth); all = every σ; choose "
                      "= fit both and keep the one whose robots left out do better, as for "
                      "the linearisation (docs/estimator.md)",
        choices=("motion", "all", "choose"))
    jobs: int = setting(2, doc="processes scoring the robots of a pass at once (1 = this "
                               "process only)", min=1)
    folds: str = setting("", doc="also write each leave-one-robot-out profile here, as "
                                 "without-robotK.toml (to run a robot left out through the "
                                 "real processes); empty = none", metavar="DIR")
    output: str = setting("", doc="settings TOML to write; empty = print it", short="-o",
                          metavar="FILE.toml")
    progress: str = _progress()




@dataclass(frozen=True)
class SerialSettings:
    """``slamlens serial``: a real robot on a serial line (wire protocol: docs/drivers.md)."""

    robot: str = _robot()
    port: str = setting("", doc="serial device path or pyserial URL (e.g. /dev/ttyUSB0, "
                                "loop://)", required=True, metavar="DEV")
    baudrate: int = setting(115200, doc="line speed", unit="baud", min=1)


# ---------------------------------------------------------------------------- estimator

_MOTION = "estimator: opt-in noise terms (not the standard model; 0 = off)"
_GATES = "estimator: innovation gate and guard"
_PLAUSIBLE = "estimator: plausibility gates (0 = no bound)"


@dataclass(frozen=True)
class EstimatorSettings:
    """``slamlens estimator``: EKF-SLAM with the standard model (docs/estimator.md).

    Noise defaults equal the simulator's "paper" world, so a correct run is consistent.
    """

    robot: str = _robot()
    sigma_v: float = setting(0.05, doc="odometry speed noise σv", unit="m/s", min=0.0)
    sigma_w: float = setting(0.05, doc="odometry turn-rate noise σω", unit="rad/s", min=0.0)
    sigma_range: float = setting(0.05, doc="range noise σr (> 0)", unit="m", min=0.0)
    sigma_bearing: float = setting(0.02, doc="bearing noise σφ (> 0)", unit="rad", min=0.0)
    gate_chi2: float = setting(
        9.21, doc="id −1: accept the nearest landmark when d² is below this (χ²₂ 99 %)",
        min=0.0)
    new_landmark_chi2: float = setting(
        27.63, doc="id −1: start a new landmark when the nearest d² is above this (χ²₂ "
                   "1 − 1e-6: over thousands of observations a 99.9 % threshold makes "
                   "duplicates)", min=0.0)
    anonymous_id_base: int = setting(
        1_000_000, doc="first id given to landmarks found by association (then counting up)",
        min=0)
    initial_pose: tuple[float, ...] = setting(
        (0.0, 0.0, 0.0), doc="x_v(0) = (x m, y m, θ rad) in the map frame",
        metavar="X,Y,THETA")
    initial_pose_sigma: tuple[float, ...] = setting(
        (0.0, 0.0, 0.0), doc="standard deviations of x_v(0) (m, m, rad); 0 = the map frame is "
                             "the start pose", metavar="SX,SY,STHETA")
    fault: str = setting(NONE, doc="plant a documented fault (docs/estimator.md)",
                         choices=FAULT_KINDS)
    faulty_features: tuple[int, ...] = setting((), doc="landmark ids the fault acts on",
                                               metavar="ID,ID")
    fault_magnitude: float | None = setting(
        None, doc="size of the fault; none = the kind's default (map-update 2e-3 m², "
                  "cross-covariance 1.0 = propagation fully omitted)", min=0.0)
    fault_onset: float = setting(0.0, doc="stamp from which the fault acts (0 = from the "
                                          "start)", unit="s")
    publish_innovations: bool = setting(
        True, doc="put each update's innovations and S into the state (the monitor's NIS)")
    linearisation: str = setting(
        STANDARD, doc="where the Jacobians are evaluated: standard = at the latest estimates "
                      "(estimator.md); fej = First-Estimates Jacobians (the robot's propagated "
                      "estimate, each landmark's first estimate), so global translation and "
                      "rotation stay unobservable and the filter does not grow overconfident "
                      "in the map's heading; oc = Observability-Constrained Jacobians (each "
                      "H at the latest estimates, made blind to FEJ's unobservable "
                      "directions: the same guarantee with Jacobians nearer the truth); "
                      "invariant = the invariant EKF (the error of the group SE(2) of robot "
                      "and map: H at the latest estimates, each update's step taken by the "
                      "group's exponential and P carried to the new estimate; the same "
                      "guarantee without first estimates) (docs/estimator.md)",
        choices=LINEARISATIONS)
    update_iterations: int = setting(
        1, doc="the iterated EKF: at most this many linearisations of each update, each at "
               "the estimate the last one gave (a step that would raise the update's cost "
               "halved back), until one lands within 1e-9 of where it was taken; 1 = the "
               "EKF. For wide priors (long blind stretches, loop closures); fej: no effect, "
               "its H does not move (docs/estimator.md)",
        min=1, max=100)
    # -- opt-in motion noise (not the standard model; all 0 = the standard model exactly) --
    sigma_distance: float = setting(
        0.0, doc="opt-in, not the standard model: along-track noise growing with the distance "
                 "driven, "
                 "σ after 1 m (variance σ²·|v·dt| per step, whatever the odometry rate)",
        unit="m/√m", min=0.0, group=_MOTION)
    sigma_turn: float = setting(
        0.0, doc="opt-in: heading noise growing with the angle turned, σ after 1 rad "
                 "(variance σ²·|ω·dt| per step)", unit="rad/√rad", min=0.0, group=_MOTION)
    sigma_heading_per_distance: float = setting(
        0.0, doc="opt-in: heading noise growing with the distance driven, σ after 1 m "
                 "(variance σ²·|v·dt| per step)", unit="rad/√m", min=0.0, group=_MOTION)
    sigma_range_per_m: float = setting(
        0.0, doc="opt-in, not the standard model: range noise growing with the range measured: "
                 "variance σr² + (k·r)²", unit="m/m", min=0.0, group=_MOTION)
    sigma_range_off_axis: float = setting(
        0.0, doc="opt-in: range noise growing with the range and the bearing off the sensor's "
                 "axis: variance + (k·r·φ²)² (a camera that ranges by a marker's apparent size; "
                 "docs/estimator.md)", unit="1/rad²", min=0.0, group=_MOTION)
    # -- innovation gate and the filter's guard ------------------------------------------
    innovation_gate_chi2: float = setting(
        0.0, doc="known ids: an observation whose NIS νᵀS⁻¹ν is above this is not applied "
                 "(counted, published in the state's gated_* fields), e.g. 13.82 = χ²₂ 99.9 %; "
                 "0 = no gate (the default: on a mistuned filter a gate refuses the very "
                 "observations that would correct it, docs/estimator.md)", min=0.0,
        group=_GATES)
    guard_rtol: float = setting(
        1e-9, doc="the filter's guard: a step that would make the state non-finite or take a "
                  "variance below −guard_rtol × its value is refused (off for planted "
                  "faults, which break PSD on purpose)", min=0.0, group=_GATES)
    # -- plausibility gates: an input outside is refused whole; 0 = no bound --
    max_dt_s: float = setting(10.0, doc="odometry dt above this is refused", unit="s",
                              min=0.0, group=_PLAUSIBLE)
    max_speed: float = setting(10.0, doc="odometry |v| above this is refused", unit="m/s",
                               min=0.0, group=_PLAUSIBLE)
    max_turn_rate: float = setting(10.0, doc="odometry |ω| above this is refused",
                                   unit="rad/s", min=0.0, group=_PLAUSIBLE)
    max_range: float = setting(100.0, doc="a batch with a range above this is refused",
                               unit="m", min=0.0, group=_PLAUSIBLE)
    max_abs_bearing: float = setting(
        2 * math.pi, doc="a batch with a |bearing| above this is refused (one turn: an "
                         "unwrapped angle is still an angle, 1e6 rad is not)", unit="rad",
        min=0.0, group=_PLAUSIBLE)
    max_stamp_jump_s: float = setting(
        60.0, doc="an input stamped further than this (either way) from the newest input "
                  "applied is refused …", unit="s", min=0.0, group=_PLAUSIBLE)
    stamp_resync: int = setting(
        20, doc="… until this many in a row, each within max_stamp_jump_s of the one "
                "before, say the clock really jumped: then it is followed; 0 = never",
        min=0, group=_PLAUSIBLE)
    max_batch: int = setting(500, doc="a batch with more observations than this is refused",
                             min=0, group=_PLAUSIBLE)
    max_landmarks: int = setting(
        2000, doc="a batch whose new ids would grow the map beyond this is refused (an "
                  "anonymous observation that would start one is not applied)", min=0,
        group=_PLAUSIBLE)
    # -- delivery (docs/delivery.md; the service, not the filter) --------------------------------
    checkpoint: str = setting(
        "", doc="crash recovery: save the map in DIR (atomically, at least once a second and "
                "at exit) and resume it from there on a restart; empty = none", metavar="DIR")
    checkpoint_interval_s: float = setting(1.0, doc="time between checkpoints", unit="s",
                                           min=0.01)
    input_gap_wait_s: float = setting(
        15.0, doc="how long a numbered input waits behind a gap that Zenoh neither fills "
                  "(recovery from the publisher's cache) nor reports missed, before the "
                  "missing numbers are counted lost: the last resort for a publisher without "
                  "a cache; longer than Zenoh's recovery query (10 s)", unit="s", min=0.0)
    input_sources: int = setting(
        1, doc="publishing sessions the inputs come from (e.g. 2: odometry from one process, "
               "observations from another): nothing is applied before that many were "
               "heard, then their inputs are merged by stamp (docs/protocol.md)", min=1)
    input_reorder_s: float = setting(
        0.5, doc="with several input sessions: how long the merge by stamp waits for a "
                 "session that has gone quiet (docs/protocol.md)", unit="s", min=0.0)
    input_history_s: float = setting(
        60.0, doc="when resuming from a checkpoint, the drivers' cached inputs asked for",
        unit="s", min=0.0)
    state_cache: int = setting(
        10_000, doc="states kept for subscribers that recover what they missed (at most "
                    "state_cache_mb of them)", unit="states", min=1)
    state_cache_mb: float = setting(256.0, doc="memory the state cache may hold", unit="MB",
                                    min=1.0)

    def __post_init__(self) -> None:
        if not (self.sigma_range > 0 and self.sigma_bearing > 0):
            raise ConfigError("settings 'sigma_range' and 'sigma_bearing' must be > 0 "
                              "(R must be positive definite)")
        for name in ("sigma_v", "sigma_w"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"setting {name!r} must be ≥ 0")
        if not 0 < self.gate_chi2 <= self.new_landmark_chi2:
            raise ConfigError(f"settings need 0 < 'gate_chi2' ≤ 'new_landmark_chi2', got "
                              f"{self.gate_chi2} and {self.new_landmark_chi2}")
        for name in ("initial_pose", "initial_pose_sigma"):
            value = getattr(self, name)
            if len(value) != 3 or not all(math.isfinite(float(v)) for v in value):
                raise ConfigError(f"setting {name!r}: expected 3 finite numbers, got {value!r}")
        if any(s < 0 for s in self.initial_pose_sigma):
            raise ConfigError("setting 'initial_pose_sigma': standard deviations must be ≥ 0")
        if self.linearisation == INVARIANT and self.update_iterations > 1:
            raise ConfigError("settings 'linearisation' invariant and 'update_iterations' > 1: "
                              "the iterated update is not defined for the invariant EKF")
        try:
            check_fault(self.fault, self.faulty_features, self.fault_magnitude)
        except ConfigError as exc:
            raise ConfigError(f"settings 'fault'/'faulty_features'/'fault_magnitude': {exc}") \
                from None


@dataclass(frozen=True)
class SummarySettings:
    """``slamlens summary``: remote viewers' summaries of the newest state (docs/remote_viewers.md).

    It answers the queryable ``robot/R/summary`` (docs/protocol.md)."""

    robot: str = _robot()
    hold_s: float = setting(
        2.0, doc="a query with after=SEQ waits up to this long for a newer state, then gets "
                 "the newest anyway (the long poll; a client's timeout must be longer)",
        unit="s", min=0.0, max=60.0)
    cache: int = setting(16, doc="summaries kept (per state and query): viewers that ask the "
                                 "same share one computation", min=1)
    max_pending: int = setting(256, doc="queries held at once; more are answered 'busy'",
                               min=1)
    max_group_pairs: int = setting(
        20_000, doc="a clusters answer of more group pairs than this is refused (ask with a "
                    "glyph budget: the groups then become map tiles)", min=1)
    max_pairs: int = setting(
        50_000, doc="a pairs answer of more pairs than this is refused (ask with a glyph "
                    "budget: then its largest); an answer must cross a slow link in a few "
                    "seconds", min=1)
