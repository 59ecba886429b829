"""Settings of ``slamlens monitor`` (docs/monitor.md).

One frozen dataclass whose fields are declared once with
:func:`slamlens.common.config.setting` (TOML key, flag, help and docs/cli.md row in one). No
numpy here: ``slamlens monitor --help`` must not load it before the one-BLAS-thread default
is set.
"""

from __future__ import annotations

from dataclasses import dataclass

from slamlens.common.config import setting

_THEOREMS = "monitor: covariance theorems (deterministic checks)"
_STATISTICS = "monitor: statistical tests"
_BLAME = "monitor: pinpointing"


@dataclass(frozen=True)
class MonitorSettings:
    """``slamlens monitor``: the behaviour monitor (docs/monitor.md).

    Every tolerance is *relative* to the scale of the covariance entries it guards, plus a
    tiny absolute floor, because rounding in an EKF update is relative to the entries it
    touches: a correct filter's covariance moves in the wrong direction by at most a few
    ε·|P| per step (ε = 2.2e-16), so 1e-9 leaves a margin of about 10⁶ over rounding, while
    the faults a developer plants or makes are 10⁻⁶…10⁻¹ of that scale.
    """

    robot: str = setting("robot1", doc="robot whose states are checked (names the bus keys; "
                                       "the core ignores it)")

    # -- covariance theorems (deterministic checks) ------------------------------------
    rtol_growth: float = setting(
        1e-9, doc="P_d / P_ii growth tolerance, relative to tr(P_ii) + tr(P_jj) of the older "
                  "state (the entries P_d is computed from: cancellation-aware, P_d itself can "
                  "be tiny)", min=0.0, flag="--rtol", group=_THEOREMS)
    atol_growth: float = setting(1e-12, doc="absolute floor of every tolerance", unit="m²",
                                 min=0.0, group=_THEOREMS)
    rtol_symmetry: float = setting(1e-9, doc="|P_ab − P_ba| allowed, relative to "
                                             "sqrt(P_aa·P_bb)", min=0.0, group=_THEOREMS)
    rtol_psd: float = setting(1e-9, doc="smallest eigenvalue of P allowed down to "
                                        "−rtol_psd·max(diag P) − atol_growth", min=0.0,
                              group=_THEOREMS)
    rtol_correlation: float = setting(1e-9, doc="|P_ab| ≤ sqrt(P_aa·P_bb)·(1 + "
                                                "rtol_correlation) + atol_growth", min=0.0,
                                      group=_THEOREMS)
    check_prediction: bool = setting(
        True, doc="check each predict step: P_mm unchanged, P_vm = Fx·P_vm(previous), "
                  "Pvv − Fx·Pvv·Fxᵀ ≽ 0 (valid for any odometry model whose displacement "
                  "turns with the heading)", group=_THEOREMS)
    rtol_prediction: float = setting(1e-9, doc="prediction residual tolerance, relative to "
                                               "sqrt(P_aa·P_bb) of the entry checked",
                                     min=0.0, group=_THEOREMS)
    check_unobservable: str = setting(
        "auto", doc="the information in the unobservable directions (global x, y, rotation) "
                    "must never grow: auto = a violation for an estimator that says it keeps "
                    "them unobservable (FEJ), the growth in the statistics for any other (a "
                    "standard EKF grows it by construction); always = a violation for any; "
                    "off = not computed (docs/monitor.md)", choices=("auto", "always", "off"),
        group=_THEOREMS)
    rtol_unobservable: float = setting(
        1e-6, doc="growth of that information allowed, relative (in the direction it grew "
                  "most): rounding stays below 2e-12 on MRCLAM, a standard EKF's updates add "
                  "1e-3 to 5", min=0.0, group=_THEOREMS)

    # -- statistical tests -------------------------------------------------------------
    significance: float = setting(1e-6, doc="two-sided α of each windowed test (one test per "
                                            "completed window, not per state)", min=1e-15,
                                  group=_STATISTICS)
    nis_window: int = setting(50, doc="innovations per NIS window", min=1, group=_STATISTICS)
    nis_dependence: str = setting(
        "measured", doc="how the NIS band counts a window's innovations: measured = as "
                        "N / τ independent ones, τ from the autocorrelation of the run's NIS "
                        "before the window (white innovations: τ ≈ 1, the textbook band); "
                        "white = as N independent ones always, χ²(2·N)/N (docs/monitor.md)",
        choices=("measured", "white"), group=_STATISTICS)
    nis_measure_after: int = setting(
        4, doc="NIS windows completed before their dependence is measured (the white band "
               "until then)", min=1, group=_STATISTICS)
    nees_window: int = setting(50, doc="states per NEES window (NEES along one run is "
                                       "strongly autocorrelated: the band used is the "
                                       "dependence-robust one of a single χ²(dof) sample)",
                               min=1, group=_STATISTICS)
    truth_tolerance_s: float = setting(0.02, doc="a truth / tracked pose matches a state if "
                                                 "their stamps differ by at most this",
                                       unit="s", min=0.0, group=_STATISTICS)
    truth_pose_sigma: tuple[float, ...] = setting(
        (0.0, 0.0, 0.0), doc="std devs (m, m, rad) of the truth pose itself (a camera-tracked "
                             "pose); added to Pvv", metavar="SX,SY,STHETA", group=_STATISTICS)
    nees_condition_max: float = setting(
        1e10, doc="NEES skipped when the covariance's condition number exceeds this (e.g. the "
                  "first steps from a zero initial covariance: rank-deficient, error dominated "
                  "by linearisation)", min=1.0, group=_STATISTICS)

    # -- pinpointing -------------------------------------------------------------------
    evidence_half_life: float = setting(100.0, doc="blame evidence halves every this many "
                                                   "states checked", min=1.0, group=_BLAME)
    suspect_score: float = setting(
        0.75, doc="a feature is a suspect while its evidence is at least this (1 = one full "
                  "blame: it stays a suspect for 0.4 half-lives; a split blame of 1/2 alone is "
                  "not enough) …", min=0.0, group=_BLAME)
    suspect_ratio: float = setting(0.1, doc="… and at least this fraction of the strongest "
                                            "suspect's evidence", min=0.0, group=_BLAME)
    sample_above_mb: float = setting(
        512.0, doc="when the states waiting to be checked hold more than this, the monitor "
                   "checks the newest and skips those before it (counted as 'sampled_out'; "
                   "the Loewner order is transitive, so the checks stay valid across the "
                   "gap): a large map at the estimator's full rate; small maps never reach "
                   "it (docs/monitor.md)", unit="MB", min=1.0, group=_BLAME)
    newest_above_mb: float = setting(
        8.0, doc="a state at least this large (n ≳ 500) waits in Zenoh's buffer, uncopied, "
                 "and only the newest one waits: one still waiting when a newer one comes "
                 "is skipped (counted as 'sampled_out'; the checks stay valid across the "
                 "gap), so the monitor copies only the states it checks and never pins "
                 "more than one of the estimator's shared-memory buffers (docs/monitor.md)",
        unit="MB", min=0.1, group=_BLAME)
    large_share: float = setting(
        0.25, doc="after checking a large state (newest_above_mb) the checking thread "
                  "rests so that it uses at most this share of a core, leaving the rest to "
                  "the estimator and the viewer on the same host; the states that come "
                  "meanwhile are sampled as above (1 = no rest; docs/monitor.md)",
        min=0.001, max=1.0, group=_BLAME)
    clear_after: int = setting(
        200, doc="a violation stands (and keeps the verdict) until this many further states "
                 "were checked without it; a fault also stands while any suspect is named, a "
                 "NIS violation until a NIS window passed after it (docs/monitor.md)",
        unit="states", min=1, group=_BLAME)
    max_violations_per_kind: int = setting(
        20, doc="Health lists at most this many violations per kind (the largest); counts are "
                "in the statistics (pairs_growing …) and the blame uses all of them", min=1,
        group=_BLAME)
