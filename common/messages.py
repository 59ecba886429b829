"""The messages slamlens sends: what each carries, field by field (docs/protocol.md).

Each message is a frozen dataclass over :class:`~slamlens.common.codec.Message` (validation
on construction, msgpack encoding and decoding); each field is declared with its kind, unit
and shape (:mod:`slamlens.common.fields`), and a message checks what spans fields (counts
that must agree, a square covariance) in ``_check``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Self

import numpy as np

from slamlens.common.arrays import check_finite, check_int, check_str, check_symmetric, frozen_array
from slamlens.common.codec import SCHEMA, Message, count_check
from slamlens.common.errors import MessageError
from slamlens.common.fields import (
    COUNT,
    PIXELS,
    UINT64,
    array_field,
    finite_by_construction,
    scalar_field,
)
from slamlens.common.msgpack_walk import peek_fields, unpack_in_place

__all__ = [
    "MESSAGE_TYPES", "SCHEMA", "STEPS", "SUMMARY_WHATS", "VIOLATION_KINDS", "CameraControl",
    "CameraFrame", "CameraPose", "Health", "Message", "Observations", "Odometry",
    "Registration", "ServiceStatus", "SlamState", "StateSummary", "Truth", "Violation",
    "finite_by_construction", "peek_fields", "unpack_in_place",
]

STEPS = ("init", "predict", "update")
VIOLATION_KINDS = ("pair", "feature", "symmetry", "psd", "correlation", "nees", "nis",
                   "prediction", "unobservable")


@dataclass(frozen=True, eq=False)
class Odometry(Message):
    """Odometry of one time step: forward speed and turn rate held over ``dt``."""

    TYPE: ClassVar[str] = "Odometry"
    robot: str = scalar_field("str", "robot name")
    stamp: float = scalar_field("float", "time of the end of the step, s")
    dt: float = scalar_field("float", "duration of the step, s (≥ 0)")
    v: float = scalar_field("float", "forward speed, m/s")
    w: float = scalar_field("float", "turn rate, rad/s")
    input_seq: int | None = scalar_field(
        "int", "optional: the driver's input counter, +1 per odometry or observations "
        "message on either key (docs/delivery.md ordering; docs/protocol.md)", optional=True,
        range=UINT64)

    def _check(self) -> None:
        if self.dt < 0:
            raise MessageError(self.TYPE, "dt", "≥ 0", repr(self.dt))


@dataclass(frozen=True, eq=False)
class Observations(Message):
    """One batch of range-bearing observations taken at ``stamp``."""

    TYPE: ClassVar[str] = "Observations"
    robot: str = scalar_field("str", "robot name")
    stamp: float = scalar_field("float", "sensor time, s")
    ids: np.ndarray = array_field("<i8", (None,),
                           "landmark ids int64[k]; −1 = unknown (the estimator associates)")
    ranges: np.ndarray = array_field("<f8", (None,), "ranges, m, float64[k] (≥ 0)")
    bearings: np.ndarray = array_field("<f8", (None,), "bearings, rad, float64[k], robot frame")
    input_seq: int | None = scalar_field(
        "int", "optional: the driver's input counter (see Odometry.input_seq)",
        optional=True, range=UINT64)

    def _check(self) -> None:
        k = self.ids.shape[0]
        count_check(self.TYPE, "ranges", self.ranges, k, "one per id")
        count_check(self.TYPE, "bearings", self.bearings, k, "one per id")
        if np.any(self.ranges < 0):
            raise MessageError(self.TYPE, "ranges", "non-negative ranges", "a negative range")
        if np.any(self.ids < -1):
            raise MessageError(self.TYPE, "ids", "ids ≥ −1", str(int(self.ids.min())))


@dataclass(frozen=True, eq=False)
class Truth(Message):
    """Ground truth: the robot's true pose and the true landmarks, in the map frame."""

    TYPE: ClassVar[str] = "Truth"
    robot: str = scalar_field("str", "robot name")
    stamp: float = scalar_field("float", "time, s")
    pose: np.ndarray = array_field("<f8", (3,), "true pose (x m, y m, θ rad) in the map frame")
    landmark_ids: np.ndarray = array_field("<i8", (None,), "landmark ids int64[n]")
    landmarks: np.ndarray = array_field("<f8", (None, 2),
                                        "true landmark positions [n,2], m, map frame")
    marker_id: int | None = scalar_field(
        "int", "optional: the id of the fiducial marker the robot carries (the simulator "
        "says it, so a synthetic camera can draw each robot's own marker)", optional=True,
        range=(0, 2 ** 31 - 1))

    def _check(self) -> None:
        count_check(self.TYPE, "landmarks", self.landmarks, self.landmark_ids.shape[0],
                     "one per landmark id")


@dataclass(frozen=True, eq=False)
class SlamState(Message):
    """The estimator's full state after one event (docs/protocol.md)."""

    TYPE: ClassVar[str] = "SlamState"
    robot: str = scalar_field("str", "robot name")
    seq: int = scalar_field("int", "state sequence number, +1 per event applied", range=COUNT)
    stamp: float = scalar_field("float", "time of the event applied, s")
    step: str = scalar_field("str", "what produced this state: init / predict / update",
                        choices=STEPS)
    pose: np.ndarray = array_field("<f8", (3,), "estimated robot pose (x m, y m, θ rad), map frame")
    landmark_ids: np.ndarray = array_field("<i8", (None,), "landmark ids int64[n], state order")
    landmarks: np.ndarray = array_field("<f8", (None, 2), "estimated landmarks [n,2], m, map frame")
    covariance: np.ndarray = array_field("<f8", (None, None),
                                  "state covariance [(3+2n),(3+2n)] (flat on the wire)")
    observed_ids: np.ndarray = array_field("<i8", (None,), "ids observed in this event",
                                           optional=True)
    new_ids: np.ndarray = array_field("<i8", (None,), "ids initialised in this event",
                                      optional=True)
    innovation_ids: np.ndarray = array_field("<i8", (None,), "ids of the innovations below",
                                      optional=True)
    innovations: np.ndarray = array_field("<f8", (None, 2), "innovations ν [k,2] (m, rad)",
                                          optional=True)
    innovation_covariances: np.ndarray = array_field(
        "<f8", (None, 2, 2), "innovation covariances S", optional=True)
    epoch: int = scalar_field("int", "uint64 fixed for the life of one map (kept across a restart "
                         "from a checkpoint, new when a map starts from scratch); 0 = unknown "
                         "(a third-party estimator that does not say)", range=UINT64,
                         default=0)
    input_stamp: float | None = scalar_field(
        "float", "stamp of the newest input folded in, s (what drivers pace on); "
        "defaults to ``stamp``", optional=True)
    origin_stamp: float | None = scalar_field(
        "float", "optional: when the robot stood at this epoch's map origin (the start of "
        "the first input folded in), s; None until an input is applied", optional=True)
    gated_ids: np.ndarray | None = array_field(
        "<i8", (None,), "optional: landmarks of the observations of this update refused by the "
        "innovation gate (NIS above it)", optional=True)
    gated_observations: np.ndarray | None = array_field(
        "<f8", (None, 2), "optional: those observations as measured [g,2] (range m, bearing rad)",
        optional=True)
    gated_nis: np.ndarray | None = array_field("<f8", (None,), "optional: their NIS νᵀS⁻¹ν",
                                        optional=True)
    diagnostics: dict[str, float] | None = field(
        default=None, metadata={"kind": "stats", "optional": True,
                                "doc": "optional: the estimator's running counts (gated, "
                                       "refused_updates, refused.<reason>); docs/protocol.md"})

    def __post_init__(self) -> None:
        self._fill_defaults()
        super().__post_init__()

    def _fill_defaults(self) -> None:
        for name in ("observed_ids", "new_ids"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, frozen_array(np.zeros(0), "<i8"))
        if self.input_stamp is None:
            object.__setattr__(self, "input_stamp", self.stamp)

    @property
    def n(self) -> int:
        """Number of landmarks."""
        return int(self.landmark_ids.shape[0])

    def _check(self) -> None:
        n = self.n
        count_check(self.TYPE, "landmarks", self.landmarks, n, "one per landmark id")
        N = 3 + 2 * n
        if self.covariance.shape != (N, N):
            raise MessageError(self.TYPE, "covariance", f"[{N}, {N}] for n = {n}",
                               str(list(self.covariance.shape)))
        if len(set(self.landmark_ids.tolist())) != n:
            raise MessageError(self.TYPE, "landmark_ids", "distinct ids", "duplicates")
        if self.innovations is not None or self.innovation_covariances is not None:
            k = 0 if self.innovation_ids is None else self.innovation_ids.shape[0]
            count_check(self.TYPE, "innovations", self.innovations, k, "one per innovation id")
            count_check(self.TYPE, "innovation_covariances", self.innovation_covariances, k,
                         "one per innovation id")
        if self.gated_observations is not None or self.gated_nis is not None:
            g = 0 if self.gated_ids is None else self.gated_ids.shape[0]
            count_check(self.TYPE, "gated_observations", self.gated_observations, g,
                         "one per gated id")
            count_check(self.TYPE, "gated_nis", self.gated_nis, g, "one per gated id")
        if self.diagnostics is not None:
            if not isinstance(self.diagnostics, Mapping):
                raise MessageError(self.TYPE, "diagnostics", "a map",
                                   type(self.diagnostics).__name__)
            for key, value in self.diagnostics.items():
                check_finite(self.TYPE, f"diagnostics.{key}", value)

    _FLAT = ("covariance",)
    #: the fields whose wire shape _wire_shape decides (the decoder's fast path asks it
    #: for these only)
    _WIRE_SHAPED: ClassVar[tuple[str, ...]] = ("covariance",)

    @classmethod
    def _wire_shape(cls, name: str, raw: Mapping[str, Any],
                    shape: tuple[int | None, ...]) -> tuple[int | None, ...]:
        if name == "covariance":
            cov = raw.get("covariance")
            wire = cov.get("shape") if isinstance(cov, Mapping) else None
            if isinstance(wire, list) and len(wire) == 1:
                return (None,)
        return shape

    @classmethod
    def _from_wire(cls, kwargs: dict[str, Any], **options: Any) -> Self:
        kwargs["covariance"] = cls._square(kwargs["covariance"])
        state = cls(**kwargs)
        cls._check_symmetry(state, options)
        return state

    @classmethod
    def _fast_finish(cls, message: Any, options: Mapping[str, Any]) -> None:
        object.__setattr__(message, "covariance", cls._square(message.covariance))
        message._fill_defaults()  # as __post_init__
        cls._check_symmetry(message, options)

    @classmethod
    def _square(cls, cov: np.ndarray) -> np.ndarray:
        """The wire's flat covariance as its N×N matrix (a 2-D one as it is)."""
        if cov.ndim != 1:
            return cov
        N = math.isqrt(cov.shape[0])
        if N * N != cov.shape[0]:
            raise MessageError(cls.TYPE, "covariance", "(3+2n)² entries",
                               f"{cov.shape[0]} (not a square)")
        return cov.reshape(N, N)

    @classmethod
    def _check_symmetry(cls, state: Any, options: Mapping[str, Any]) -> None:
        """A decoded state's symmetry test, unless the decoder was asked not to."""
        if options.get("check_symmetry", True):
            check_symmetric(cls.TYPE, "covariance", state.covariance,
                            rtol=options.get("symmetry_rtol", 1e-6))


SUMMARY_WHATS = ("blocks", "clusters", "pairs")


@dataclass(frozen=True, eq=False)
class StateSummary(Message):
    """What a remote viewer draws of one ``SlamState``, not the whole matrix (key
    ``robot/R/summary``, a queryable; docs/protocol.md, docs/remote_viewers.md).

    Always the map's blocks (pose and its 3×3 covariance, each feature's mean and 2×2
    marginal covariance); with ``what = "clusters"`` the min / mean / max of the relative
    covariances P_d = P_ii + P_jj − P_ij − P_ji between every two groups of features; with
    ``what = "pairs"`` the P_d of every pair of one cluster, or of one feature. Reals are
    float32 on the wire but for ``pose`` and the stamps; indices are into the state's
    landmarks (``landmark_ids`` order)."""

    TYPE: ClassVar[str] = "StateSummary"
    robot: str = scalar_field("str", "robot name")
    seq: int = scalar_field("int", "seq of the state summarised", range=COUNT)
    stamp: float = scalar_field("float", "its stamp, s")
    step: str = scalar_field("str", "its step: init / predict / update", choices=STEPS)
    pose: np.ndarray = array_field("<f8", (3,), "estimated robot pose (x m, y m, θ rad), map frame")
    pose_covariance: np.ndarray = array_field("<f4", (3, 3),
                                              "its covariance P_vv (m², m·rad, rad²)")
    landmark_ids: np.ndarray = array_field("<i8", (None,), "landmark ids int64[n], state order")
    landmarks: np.ndarray = array_field("<f4", (None, 2),
                                        "feature means float32[n,2], m, map frame")
    landmark_covariances: np.ndarray = array_field("<f4", (None, 2, 2),
                                            "marginal covariances P_ii float32[n,2,2], m²")
    epoch: int = scalar_field("int", "its map epoch (uint64; 0 = unknown)", range=UINT64,
                         default=0)
    input_stamp: float | None = scalar_field("float", "its input_stamp, s", optional=True)
    what: str = scalar_field("str", "what it holds beyond the blocks: blocks / clusters / pairs",
                        choices=SUMMARY_WHATS, default="blocks")
    state_bytes: int = scalar_field("int", "size of the full state's payload summarised, bytes",
                               default=0, range=UINT64)
    cluster_threshold_m: float | None = scalar_field(
        "float", "clusters: the single-linkage cut used, m", optional=True)
    cluster_count: int | None = scalar_field(
        "int", "clusters: the cluster count asked for (0 = cut at the threshold)",
        optional=True, range=(0, 2 ** 31 - 1))
    tile_m: float | None = scalar_field(
        "float", "clusters: the groups are square map tiles of this side, m (the budget "
        "rule); absent: they are the clusters", optional=True)
    groups: np.ndarray | None = array_field(
        "<i8", (None,), "clusters, pairs: group per landmark int64[n]: stable cluster id "
        "(or tile id with tile_m)", optional=True)
    group_pairs: np.ndarray | None = array_field(
        "<i8", (None, 2), "clusters: (A, B) group ids, A < B, int64[c,2]", optional=True)
    pair_count: np.ndarray | None = array_field(
        "<i8", (None,), "clusters: feature pairs between A and B, int64[c]", optional=True)
    min_pair: np.ndarray | None = array_field(
        "<i8", (None, 2), "clusters: landmark indices (i < j) of the smallest P_d (by √λmax), "
        "int64[c,2]", optional=True)
    max_pair: np.ndarray | None = array_field("<i8", (None, 2), "clusters: those of the largest",
                                       optional=True)
    min_Pd: np.ndarray | None = array_field("<f4", (None, 2, 2), "clusters: the smallest P_d, m²",
                                     optional=True)
    mean_Pd: np.ndarray | None = array_field("<f4", (None, 2, 2), "clusters: the element-wise mean "
                                      "P_d over the pairs between A and B, m²", optional=True)
    max_Pd: np.ndarray | None = array_field("<f4", (None, 2, 2), "clusters: the largest P_d, m²",
                                     optional=True)
    selected_cluster: int | None = scalar_field("int", "pairs: the cluster whose pairs these are",
                                           optional=True)
    selected_feature: int | None = scalar_field("int", "pairs: the feature id whose pairs these "
                                           "are", optional=True)
    pairs: np.ndarray | None = array_field("<i8", (None, 2), "pairs: landmark indices (i < j), "
                                    "int64[m,2]", optional=True)
    pairs_Pd: np.ndarray | None = array_field("<f4", (None, 2, 2), "pairs: their P_d, m²",
                                       optional=True)
    pairs_total: int | None = scalar_field("int", "pairs: how many there were before the cap "
                                      "(the largest are kept)", optional=True, range=UINT64)
    compute_s: float | None = scalar_field("float", "robot side: time to make it, s",
                                      optional=True)

    @property
    def n(self) -> int:
        return int(self.landmark_ids.shape[0])

    def _check(self) -> None:
        n = self.n
        for name in ("landmarks", "landmark_covariances", "groups"):
            count_check(self.TYPE, name, getattr(self, name), n, "one per landmark id")
        c = None if self.group_pairs is None else self.group_pairs.shape[0]
        for name in ("pair_count", "min_pair", "max_pair", "min_Pd", "mean_Pd", "max_Pd"):
            value = getattr(self, name)
            if (value is None) != (c is None):
                raise MessageError(self.TYPE, name, "present with group_pairs",
                                   "missing" if value is None else "without group_pairs")
            count_check(self.TYPE, name, value, c or 0, "one per group pair")
        m = None if self.pairs is None else self.pairs.shape[0]
        if (self.pairs_Pd is None) != (m is None):
            raise MessageError(self.TYPE, "pairs_Pd", "present with pairs", "alone")
        count_check(self.TYPE, "pairs_Pd", self.pairs_Pd, m or 0, "one per pair")
        for name in ("min_pair", "max_pair", "pairs"):
            value = getattr(self, name)
            if value is not None and value.size and (value.min() < 0 or value.max() >= n):
                raise MessageError(self.TYPE, name, f"landmark indices in [0, {n})",
                                   f"[{int(value.min())}, {int(value.max())}]")
        if self.what == "clusters" and (self.groups is None or self.group_pairs is None):
            raise MessageError(self.TYPE, "groups", "groups and group_pairs (what = "
                               "clusters)", "missing")
        if self.what == "pairs" and self.pairs is None:
            raise MessageError(self.TYPE, "pairs", "present (what = pairs)", "missing")


@dataclass(frozen=True)
class Violation:
    """One broken expectation found by the monitor (an entry of ``Health.violations``)."""

    kind: str  #: one of VIOLATION_KINDS
    ids: tuple[int, ...]  #: feature ids involved (a pair, one feature, or none)
    step: int  #: seq of the state where it was seen
    value: float  #: growth (covariance kinds) or the test statistic (nees, nis)
    bound: float | None = None  #: tolerance or χ² bound it was held against
    phase: str = ""  #: "predict" / "update" when the step type matters
    detail: str = ""  #: one human sentence
    first_step: int | None = None  #: standing violations: seq where it was first seen
    count: int | None = None  #: standing violations: states that showed it

    _STAT_KINDS: ClassVar[tuple[str, ...]] = ("nees", "nis")

    def to_dict(self) -> dict[str, Any]:
        key = "statistic" if self.kind in self._STAT_KINDS else "growth"
        out: dict[str, Any] = {"kind": self.kind, "ids": list(self.ids), "step": self.step,
                               key: self.value}
        if self.bound is not None:
            out["bound"] = self.bound
        if self.phase:
            out["phase"] = self.phase
        if self.detail:
            out["detail"] = self.detail
        if self.first_step is not None:
            out["first_step"] = self.first_step
        if self.count is not None:
            out["count"] = self.count
        return out

    @classmethod
    def from_dict(cls, raw: Any) -> Violation:
        m = "Health.violation"
        if not isinstance(raw, Mapping):
            raise MessageError(m, "<entry>", "a map", type(raw).__name__)
        kind = check_str(m, "kind", raw.get("kind"), choices=VIOLATION_KINDS)
        ids_raw = raw.get("ids", [])
        if not isinstance(ids_raw, list):
            raise MessageError(m, "ids", "a list of ints", type(ids_raw).__name__)
        ids = tuple(check_int(m, "ids", i) for i in ids_raw)
        key = "statistic" if kind in cls._STAT_KINDS else "growth"
        value = check_finite(m, key, raw.get(key, raw.get("growth", raw.get("statistic"))))
        bound = raw.get("bound")
        first, count = raw.get("first_step"), raw.get("count")
        return cls(kind=kind, ids=ids, step=_count(m, "step", raw.get("step")), value=value,
                   bound=None if bound is None else check_finite(m, "bound", bound),
                   phase=str(raw.get("phase", "")), detail=str(raw.get("detail", "")),
                   first_step=None if first is None else _count(m, "first_step", first),
                   count=None if count is None else _count(m, "count", count))


def _count(message: str, name: str, value: Any) -> int:
    """A sequence number or count: an integer, never negative."""
    out = check_int(message, name, value)
    if not COUNT[0] <= out <= COUNT[1]:
        raise MessageError(message, name, f"an integer in [{COUNT[0]}, {COUNT[1]}]",
                           str(out))
    return out


@dataclass(frozen=True, eq=False)
class Health(Message):
    """The monitor's verdict on one state (docs/monitor.md)."""

    TYPE: ClassVar[str] = "Health"
    robot: str = scalar_field("str", "robot name")
    seq: int = scalar_field("int", "seq of the state checked", range=COUNT)
    stamp: float = scalar_field("float", "stamp of the state checked, s")
    ok: bool = scalar_field("bool", "no violation in this state")
    suspects: np.ndarray = array_field("<i8", (None,), "feature ids blamed, int64[]")
    violations: tuple[Violation, ...] = field(
        default=(), metadata={"kind": "records", "record": Violation,
                                    "doc": "violations found in this state"})
    statistics: dict[str, float] = field(
        default_factory=dict, metadata={"kind": "stats",
                                        "doc": "named statistics: nees_pose, nis, bounds…"})
    verdict: str = field(default="ok", metadata={
        "kind": "str", "choices": ("ok", "fault", "tuning"),
        "doc": "the robot's verdict now (not only this state): ok / fault (a covariance "
               "theorem broken: an estimator fault) / tuning (only NEES/NIS outside their "
               "bands: inconsistent tuning or model mismatch); docs/monitor.md"})
    verdict_since: int | None = scalar_field("int", "seq where the current verdict began",
                                        optional=True, range=COUNT)
    standing: tuple[Violation, ...] = field(
        default=(), metadata={"kind": "records", "record": Violation,
                              "doc": "the violations that keep the verdict up (each once, "
                                     "with first_step and count)"})


@dataclass(frozen=True, eq=False)
class CameraFrame(Message):
    """One encoded camera image."""

    TYPE: ClassVar[str] = "CameraFrame"
    camera: str = scalar_field("str", "camera name")
    seq: int = scalar_field("int", "frame number", range=COUNT)
    stamp: float = scalar_field("float", "capture time, s")
    encoding: str = scalar_field("str", "image codec", choices=("jpeg",))
    width: int = scalar_field("int", "pixels", range=PIXELS)
    height: int = scalar_field("int", "pixels", range=PIXELS)
    data: bytes = scalar_field("bytes", "the encoded image")


@dataclass(frozen=True, eq=False)
class Registration(Message):
    """Where the map frame sits in a camera, with that camera's intrinsics."""

    TYPE: ClassVar[str] = "Registration"
    camera: str = scalar_field("str", "camera name")
    robot: str = scalar_field("str", "robot name")
    stamp: float = scalar_field("float", "time of the frame it was computed from, s")
    K: np.ndarray = array_field("<f8", (3, 3), "camera matrix, pixels")
    dist: np.ndarray = array_field("<f8", (None,), "OpenCV distortion coefficients")
    width: int = scalar_field("int", "image width, pixels", range=PIXELS)
    height: int = scalar_field("int", "image height, pixels", range=PIXELS)
    T_camera_from_map: np.ndarray = array_field("<f8", (4, 4), "map frame → camera frame, m")
    reprojection_error_px: float = scalar_field("float", "RMS reprojection error of the marker, px")
    status: str = field(default="registered", metadata={
        "kind": "str", "doc": "registered / tracking / marker not found …"})
    epoch: int | None = scalar_field(
        "int", "optional: the epoch of the map this registration is for (docs/delivery.md: a new "
        "map has a new frame); absent: whichever map the camera saw the robot start",
        optional=True, range=UINT64)
    reason: str | None = scalar_field(
        "str", "optional: why this registration was made: 'start', 'new map', or "
        "'requested by …' (who asked, as the request said)", optional=True)
    moved_m: float | None = scalar_field(
        "float", "optional: how far this registration moved the map origin from the "
        "previous one, m", optional=True)
    moved_deg: float | None = scalar_field(
        "float", "optional: how far it turned the map frame, degrees", optional=True)


@dataclass(frozen=True, eq=False)
class CameraPose(Message):
    """Pose of a moving camera in the world (tracker or fiducial board)."""

    TYPE: ClassVar[str] = "CameraPose"
    camera: str = scalar_field("str", "camera name")
    stamp: float = scalar_field("float", "time, s")
    T_world_from_camera: np.ndarray = array_field("<f8", (4, 4), "camera frame → world frame, m")


@dataclass(frozen=True, eq=False)
class CameraControl(Message):
    """A request to the registration service of the camera named in its key (docs/protocol.md)."""

    TYPE: ClassVar[str] = "CameraControl"
    COMMANDS: ClassVar[tuple[str, ...]] = ("reregister",)
    command: str = scalar_field("str", "what to do: reregister (from the next frames)",
                           choices=COMMANDS)
    robot: str | None = scalar_field("str", "only the service registering this robot obeys; "
                                "absent: any", optional=True)
    requester: str | None = scalar_field(
        "str", "optional: who asks (a person or program, as it says; shown with the "
        "registration it causes)", optional=True)


@dataclass(frozen=True, eq=False)
class ServiceStatus(Message):
    """What one running service says about itself, answered to a ``get`` on its status key
    (``slamlens status``; docs/protocol.md)."""

    TYPE: ClassVar[str] = "ServiceStatus"
    service: str = scalar_field("str", "the slamlens command it runs: router, estimator, sim …")
    name: str = scalar_field("str", "its identity: the certificate name with --secure, else the "
                               "name of its role (robot-R, camera-C, monitor-R, viewer-…, "
                               "router-…)")
    host: str = scalar_field("str", "host name of its machine")
    pid: int = scalar_field("int", "process id on that host", range=(0, 2 ** 63 - 1))
    version: str = scalar_field("str", "slamlens version")
    started: float = scalar_field("float", "when it started, s since the Unix epoch")
    uptime_s: float = scalar_field("float", "seconds since it started")
    state: str = scalar_field("str", "what it is doing, in a few words: running, waiting for "
                                "an estimator, registered, fault …")
    robot: str | None = scalar_field("str", "the robot(s) it serves, comma-separated",
                                optional=True)
    camera: str | None = scalar_field("str", "the camera(s) it serves, comma-separated",
                                 optional=True)
    epoch: int | None = scalar_field("int", "the map epoch it is on (docs/delivery.md)",
                                     optional=True, range=UINT64)
    counts: dict[str, float] = field(
        default_factory=dict, metadata={"kind": "stats",
                                        "doc": "running totals: states, frames, inputs …; "
                                               "the first is its main output"})
    rates: dict[str, float] = field(
        default_factory=dict, metadata={"kind": "stats",
                                        "doc": "per second over the last few seconds, one per "
                                               "count"})
    dropped: int = scalar_field("int", "messages it discarded: malformed, foreign or refused",
                           default=0, range=UINT64)
    lost: int = scalar_field("int", "samples it knows it missed and could not recover",
                        default=0, range=UINT64)


MESSAGE_TYPES: tuple[type[Message], ...] = (
    Odometry, Observations, Truth, SlamState, Health, CameraFrame, Registration, CameraPose,
    CameraControl, ServiceStatus, StateSummary,
)
