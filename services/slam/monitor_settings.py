"""Settings of the behaviour monitor (SPEC §5): tolerances, windows, significance, blame.

Every tolerance is *relative* to the scale of the covariance entries it guards, plus a tiny
absolute floor, because rounding in an EKF update is relative to the entries it touches: a
correct filter's covariance moves in the wrong direction by at most a few ε·|P| per step
(ε = 2.2e-16), so 1e-9 leaves a margin of about 10⁶ over rounding, while the faults a
developer plants or makes are 10⁻⁶…10⁻¹ of that scale. See docs/monitor.md for the reasons.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class MonitorSettings:
    """Documented defaults for :class:`services.slam.monitor.Monitor`."""

    robot: str = "robot1"
    """Robot whose states are checked (names the bus keys; the core ignores it)."""

    # -- covariance theorems (deterministic checks) ------------------------------------
    rtol_growth: float = field(default=1e-9, metadata={"min": 0.0})
    """P_d / P_ii growth tolerance, relative to tr(P_ii) + tr(P_jj) of the older state
    (the entries P_d is computed from: cancellation-aware, P_d itself can be tiny)."""
    atol_growth: float = field(default=1e-12, metadata={"min": 0.0})
    """Absolute floor of the growth tolerance, m²."""
    rtol_symmetry: float = field(default=1e-9, metadata={"min": 0.0})
    """|P_ab − P_ba| allowed, relative to sqrt(P_aa·P_bb)."""
    rtol_psd: float = field(default=1e-9, metadata={"min": 0.0})
    """Smallest eigenvalue of P allowed down to −rtol_psd·max(diag P) − atol_growth."""
    rtol_correlation: float = field(default=1e-9, metadata={"min": 0.0})
    """|P_ab| ≤ sqrt(P_aa·P_bb)·(1 + rtol_correlation) + atol_growth."""
    check_prediction: bool = True
    """After a predict state: P_mm unchanged, P_vm = Fx·P_vm(previous), Pvv − Fx·Pvv·Fxᵀ ≽ 0
    (valid for any odometry model whose displacement turns with the heading)."""
    rtol_prediction: float = field(default=1e-9, metadata={"min": 0.0})
    """Prediction residual tolerance, relative to sqrt(P_aa·P_bb) of the entry checked."""

    # -- statistical tests -------------------------------------------------------------
    significance: float = field(default=1e-6, metadata={"min": 1e-15})
    """Two-sided α of each windowed test (one test per completed window, not per state)."""
    nis_window: int = field(default=50, metadata={"min": 1})
    """Innovations per NIS window (innovations of a consistent EKF are white: the band of the
    window mean is χ²(2·N)/N)."""
    nees_window: int = field(default=50, metadata={"min": 1})
    """States per NEES window (NEES along one run is strongly autocorrelated: the band used
    is the dependence-robust one of a single χ²(dof) sample)."""
    truth_tolerance_s: float = field(default=0.02, metadata={"min": 0.0})
    """A truth / tracked pose matches a state if their stamps differ by at most this, s."""
    truth_pose_sigma: tuple[float, ...] = (0.0, 0.0, 0.0)
    """Std devs (m, m, rad) of the truth pose itself (a camera-tracked pose); added to Pvv."""
    nees_condition_max: float = field(default=1e10, metadata={"min": 1.0})
    """NEES skipped when the covariance's condition number exceeds this (e.g. the first
    steps from a zero initial covariance: rank-deficient, error dominated by linearisation)."""

    # -- pinpointing -------------------------------------------------------------------
    evidence_half_life: float = field(default=100.0, metadata={"min": 1.0})
    """Blame evidence halves every this many states checked."""
    suspect_score: float = field(default=0.75, metadata={"min": 0.0})
    """A feature is a suspect while its evidence is at least this (1 = one full blame: it
    stays a suspect for 0.4 half-lives; a split blame of 1/2 alone is not enough) ..."""
    suspect_ratio: float = field(default=0.1, metadata={"min": 0.0})
    """... and at least this fraction of the strongest suspect's evidence."""
    clear_after: int = field(default=200, metadata={"min": 1})
    """A violation stands (and keeps the verdict) until this many further states were checked
    without it; a fault also stands while any suspect is named (docs/monitor.md)."""
    max_violations_per_kind: int = field(default=20, metadata={"min": 1})
    """Health lists at most this many violations per kind (the largest); counts are in the
    statistics (``pairs_growing`` …) and the blame uses all of them."""
