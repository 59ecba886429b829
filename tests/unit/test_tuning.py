"""``slamlens tune`` and its figures: the robust fit recovers known noise, the truth and NEES
helpers against hand computations, and a tune of the real MRCLAM excerpt writes a profile
the estimator loads (tests/fixtures/mrclam_small, 60 s of dataset 6, robot 1)."""

from __future__ import annotations

import math
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from slamlens.common.config import load_settings
from slamlens.services.harness.procs import REPO, spawn
from slamlens.services.slam import scoring, tuning
from slamlens.services.slam.mrclam import load_mrclam
from slamlens.services.slam.settings import EstimatorSettings

SMALL = REPO / "tests" / "fixtures" / "mrclam_small"


def test_the_trimmed_fit_recovers_a_known_sigma_through_gross_outliers() -> None:
    rng = np.random.default_rng(1)
    e = rng.normal(0.0, 0.08, 20000)
    e[:600] = rng.uniform(0.5, 3.0, 600) * rng.choice([-1, 1], 600)  # 3 % gross outliers
    a = tuning.fit_variance(e, np.ones((e.size, 1)))
    assert math.sqrt(a[0]) == pytest.approx(0.08, rel=0.03)
    plain = float(np.sqrt(np.mean(e ** 2)))
    assert plain > 3 * 0.08  # what an untrimmed estimate would say


def test_the_fit_separates_two_variance_terms() -> None:
    rng = np.random.default_rng(2)
    turn, dist = rng.uniform(0.0, 2.0, 30000), rng.uniform(0.0, 3.0, 30000)
    var = 0.1 ** 2 * turn + 0.03 ** 2 * dist
    e = rng.normal(0.0, 1.0, turn.size) * np.sqrt(var)
    a = tuning.fit_variance(e, np.column_stack([turn, dist]))
    assert math.sqrt(a[0]) == pytest.approx(0.1, rel=0.05)
    assert math.sqrt(a[1]) == pytest.approx(0.03, rel=0.1)


def test_samples_no_term_can_explain_are_left_out() -> None:
    e = np.r_[np.full(10, 0.01), np.random.default_rng(3).normal(0, 0.2, 5000)]
    X = np.r_[np.zeros(10), np.ones(5000)].reshape(-1, 1)  # standing still: no noise term
    assert math.sqrt(tuning.fit_variance(e, X)[0]) == pytest.approx(0.2, rel=0.05)


def test_truth_track_interpolates_the_angle_the_short_way_round() -> None:
    track = scoring.TruthTrack(np.array([0.0, 1.0]), np.array([[0.0, 0.0, 3.1],
                                                              [1.0, 2.0, -3.1]]),
                              np.zeros(0, np.int64), np.zeros((0, 2)))
    p = track.pose_at(0.5)
    assert p is not None
    assert p[:2] == pytest.approx([0.5, 1.0])
    assert abs(p[2]) == pytest.approx(math.pi, abs=1e-9)
    assert track.pose_at(-0.1) is None and track.pose_at(1.1) is None


def test_truth_track_covers_a_stamp_with_no_gap_before_it() -> None:
    stamps = np.r_[np.arange(0.0, 10.0, 0.1), np.arange(12.0, 20.0, 0.1)]  # a 2 s gap
    track = scoring.TruthTrack(stamps, np.zeros((stamps.size, 3)), np.zeros(0, np.int64),
                               np.zeros((0, 2)))
    assert track.covers(5.0) and track.covers(10.3) and not track.covers(11.0)
    assert track.covers(9.0, before_s=3.0) and not track.covers(13.0, before_s=3.0)
    assert track.covers(15.5, before_s=3.0) and not track.covers(2.0, before_s=3.0)
    assert not track.covers(20.6) and not track.covers(-0.6)


def test_pose_nees_rigid_fit_and_band() -> None:
    P = np.diag([0.25, 0.25, 0.01])
    assert scoring.pose_nees(np.array([1.0, 0.0, 0.1]), P) == pytest.approx(4.0 + 1.0)
    assert math.isnan(scoring.pose_nees(np.ones(3), np.diag([1.0, 1.0, 0.0])))
    truth = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 1.0], [3.0, 3.0]])
    a = math.radians(25.0)
    R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    estimated = (truth - 1.0) @ R.T + [4.0, -2.0]
    rmse, rotation = scoring.rigid_fit(estimated, truth)
    assert rmse == pytest.approx(0.0, abs=1e-12) and rotation == pytest.approx(-25.0)
    scaled = 1.02 * estimated  # a map 2 % too large: no rigid fit, an exact similarity one
    assert scoring.rigid_fit(scaled, truth)[0] > 0.01
    rmse, scale = scoring.similarity_fit(scaled, truth)
    assert rmse == pytest.approx(0.0, abs=1e-12) and scale == pytest.approx(1 / 1.02)
    lo, hi = scoring.nees_band()
    assert (lo, hi) == pytest.approx((0.2158, 9.348), abs=1e-3)


def test_window_figures_of_an_evaluation() -> None:
    nees = np.r_[np.full(100, 2.0), np.full(100, 20.0), np.full(50, 3.0), [math.nan]]
    ev = scoring.Evaluation(robot="r", stamps=np.arange(nees.size, dtype=float), nees=nees,
                           errors=np.zeros((nees.size, 3)), landmark_ids=np.zeros(0, np.int64),
                           landmark_errors=np.zeros((0, 2)), landmark_rmse=math.nan,
                           landmark_rmse_rigid=math.nan, map_rotation_deg=math.nan)
    assert list(ev.windows(100)) == [2.0, 20.0]
    assert ev.window_fraction(100) == 0.5
    assert ev.nees_mean == pytest.approx((200 + 2000 + 150) / 250)


def test_a_fit_of_the_real_excerpt_agrees_with_a_plain_robust_estimate() -> None:
    run = load_mrclam(SMALL, 1)
    v = tuning.fit_noise([run]).values
    # independent of the fit: the bearing residuals computed here, their scaled MAD
    ids = [int(i) for i in run.landmark_ids]
    residuals = []
    for t, subject, _r, b in run.measurements:
        pose = run.pose_at(float(t))
        if pose is None:
            continue
        dx, dy = run.landmarks_world[ids.index(int(subject))] - pose[:2]
        residuals.append((b - (math.atan2(dy, dx) - pose[2]) + math.pi) % (2 * math.pi)
                         - math.pi)
    r = np.array(residuals)
    mad = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    rms = float(np.sqrt(np.mean(r ** 2)))  # zero mean: a bias is an error the filter sees
    # trimming only ever removes residuals (then corrects the variance by 1/0.973)
    assert mad <= v["sigma_bearing"] <= rms / math.sqrt(0.973) * 1.0001
    assert 0.0 < v["sigma_range"] < 0.15
    assert v["sigma_v"] > 0 and v["sigma_w"] > 0 and v["sigma_distance"] == 0.0  # docs/estimator.md
    opt_in = tuning.fit_noise([run], motion_model="distance").values
    assert opt_in["sigma_v"] == opt_in["sigma_w"] == 0.0
    assert opt_in["sigma_distance"] > 0 and opt_in["sigma_turn"] > 0


def test_tune_cli_writes_a_profile_the_estimator_loads(tmp_path: Path) -> None:
    out = tmp_path / "profile.toml"
    proc = spawn("tune", str(SMALL), "--robot-index", "1", "-o", str(out))
    stdout, stderr = proc.communicate(timeout=240)
    assert proc.returncode in (0, 1), stderr  # 1 = the check failed (60 s is little data)
    assert "tune done:" in stdout and "\r" not in stderr  # no progress bar off a terminal
    text = out.read_text()
    assert "fitted by: slamlens tune" in text and "NEES scale c =" in text
    settings = load_settings(EstimatorSettings, out, {"robot": "robot3"})
    values = tomllib.loads(text)
    assert settings.sigma_v == values["sigma_v"] > 0 and settings.sigma_distance == 0.0
    assert settings.sigma_range_off_axis == values["sigma_range_off_axis"] > 0
    assert settings.innovation_gate_chi2 == 13.82 and settings.robot == "robot3"


def test_the_shipped_profile_is_one_for_the_dataset_and_loads() -> None:
    path = REPO / "deploy" / "mrclam.toml"
    values = tomllib.loads(path.read_text())
    assert "robot" not in values  # not tuned per robot: --robot R picks the robot
    text = path.read_text()
    # fitted on every robot of the dataset, judged on each left out, every linearisation
    # tried, the invariant EKF chosen by that
    assert "--robot-index 1,2,3,4,5" in text and "leave-one-robot-out" in text
    assert "--linearisation all" in text and "chosen: invariant" in text
    s = load_settings(EstimatorSettings, path, {"robot": "robot1"})
    assert s.linearisation == "invariant"
    assert s.sigma_v > 0 and s.sigma_range_off_axis > 0 and s.innovation_gate_chi2 > 0


# ------------------------------------------------------------------ leave one robot out


def two_robots(tmp_path: Path, *, corrupt_robot2: bool = False) -> Path:
    """The excerpt twice, as robots 1 and 2 (robot 2's ranges ×1.5 if ``corrupt_robot2``)."""
    folder = tmp_path / ("corrupt" if corrupt_robot2 else "clean")
    folder.mkdir()
    for f in SMALL.glob("*.dat"):
        (folder / f.name).write_bytes(f.read_bytes())
        if f.name.startswith("Robot1_"):
            text = f.read_text()
            if corrupt_robot2 and f.name == "Robot1_Measurement.dat":
                lines = []
                for line in text.splitlines():
                    parts = line.split()
                    if line.startswith("#") or len(parts) != 4:
                        lines.append(line)
                        continue
                    parts[2] = f"{float(parts[2]) * 1.5:.3f}"
                    lines.append("\t".join(parts))
                text = "\n".join(lines) + "\n"
            (folder / f.name.replace("Robot1_", "Robot2_")).write_text(text)
    return folder


def test_a_fold_never_sees_the_robot_it_scores(tmp_path: Path) -> None:
    """Corrupting robot 2 changes the profile fitted with robot 2 in it, and not the one
    scored on robot 2: that one is fitted on robot 1 alone, exactly as tune() on it."""
    from slamlens.services.slam import crossval

    folders = [two_robots(tmp_path, corrupt_robot2=c) for c in (False, True)]
    clean, corrupt = ([load_mrclam(folder, k) for k in (1, 2)] for folder in folders)
    cand = crossval.Candidate("fej")
    a = crossval.cross_validate(clean, cand)
    b = crossval.cross_validate(corrupt, cand)
    assert [f.held_out for f in a.folds] == ["robot1", "robot2"]
    assert a.folds[1].result.values == b.folds[1].result.values  # robot 2 left out
    assert a.folds[0].result.values != b.folds[0].result.values  # robot 2 fitted on
    alone = tuning.tune([clean[0]], base=EstimatorSettings(linearisation="fej"))
    assert alone.values == a.folds[1].result.values
    expected = scoring.evaluate(clean[1], tuning.settings_with(
        EstimatorSettings(linearisation="fej"), alone.values))
    assert np.array_equal(a.folds[1].test.nees, expected.nees, equal_nan=True)
    assert b.folds[1].test.landmark_rmse_rigid > a.folds[1].test.landmark_rmse_rigid


def _evaluation(nees: float, rigid: float) -> scoring.Evaluation:
    return scoring.Evaluation(
        robot="r", stamps=np.arange(3.0), nees=np.full(3, nees), errors=np.zeros((3, 3)),
        landmark_ids=np.zeros(0, np.int64), landmark_errors=np.zeros((0, 2)),
        landmark_rmse=math.nan, landmark_rmse_rigid=rigid, map_rotation_deg=0.0)


def test_the_choice_goes_by_the_robots_left_out() -> None:
    from slamlens.services.slam import crossval

    def cv(name: str, *figures: tuple[float, float]) -> crossval.CrossValidation:
        return crossval.CrossValidation(crossval.Candidate(name), [
            crossval.Fold(f"robot{k}", None, _evaluation(*f))  # type: ignore[arg-type]
            for k, f in enumerate(figures)])

    timid = cv("standard", (0.5, 0.05), (0.9, 0.05), (2.5, 0.05))  # 1 meets
    honest = cv("fej", (2.0, 0.05), (5.0, 0.05), (7.0, 0.05))  # 2 meet
    assert crossval.choose([timid, honest]) is honest
    assert [crossval.meets(e) for e in honest.held_out] == [True, True, False]
    tied = cv("fej", (1.5, 0.05), (3.0, 0.2), (4.0, 0.05))  # 2 meet, nearer 3
    assert crossval.choose([honest, tied]) is tied
    assert crossval.meets(_evaluation(3.0, 0.1)) and not crossval.meets(_evaluation(3.0, 0.11))


def test_tune_cli_leaves_each_robot_out_and_writes_the_choice(tmp_path: Path) -> None:
    out = tmp_path / "profile.toml"
    proc = spawn("tune", str(two_robots(tmp_path)), "--robot-index", "1,2", "--jobs", "1",
                 "--linearisation", "fej", "-o", str(out))
    stdout, stderr = proc.communicate(timeout=600)
    assert proc.returncode in (0, 1), stderr
    assert "leave-one-robot-out" in stderr and "chosen: fej" in stderr
    text = out.read_text()
    assert "robot2 left out" not in text  # the table names the robot left out …
    assert "fej, spec motion model" in text and "robot1" in text
    settings = load_settings(EstimatorSettings, out, {"robot": "robot2"})
    assert settings.linearisation == "fej" and tomllib.loads(text)["linearisation"] == "fej"
    assert "# m/s: error of the commanded speed" in text  # what each term means


def test_the_scale_search_is_a_secant_in_log_log() -> None:
    # NEES = 40·c^s: from two passes the secant lands on 3 whatever the slope s
    for s in (-2.0, -1.3, -0.7):
        history = [(math.log(c), math.log(40.0 * c ** s)) for c in (1.0, 2.0)]
        c = tuning._next_scale(history)
        assert 40.0 * c ** s == pytest.approx(3.0, rel=1e-9)
    # one pass: the every-σ rule c·sqrt(NEES/3)
    assert tuning._next_scale([(0.0, math.log(12.0))]) == pytest.approx(2.0)


def test_the_scale_multiplies_the_motion_sigma_only() -> None:
    """The sensor σ stay as measured against the truth; the NEES scale is the odometry's."""
    run = load_mrclam(SMALL, 1)
    fit = tuning.fit_noise([run]).values
    result = tuning.tune([run], max_passes=2)
    assert result.scaled == "motion" and result.scale != 1.0
    for key in ("sigma_range", "sigma_bearing", "sigma_range_per_m", "sigma_range_off_axis"):
        assert result.values[key] == fit[key]
    for key in ("sigma_v", "sigma_w"):
        assert result.values[key] == pytest.approx(fit[key] * result.scale, rel=1e-12)


def test_tune_fits_for_the_iterated_update_when_asked(tmp_path: Path) -> None:
    """``--update-iterations K`` reaches every pass, the robot left out and the profile: the
    figures are the iterated estimator's (scored here independently of tune), not the EKF's."""
    from slamlens.services.slam import crossval

    folder = two_robots(tmp_path)
    runs = [load_mrclam(folder, k) for k in (1, 2)]
    iterated = crossval.cross_validate(runs, crossval.Candidate("oc", update_iterations=10))
    assert iterated.candidate.label == ("oc, iterated (K = 10), spec motion model, motion σ "
                                        "scaled")
    for fold, held in zip(iterated.folds, runs, strict=True):
        assert fold.held_out == held.robot
        # the held-out figures: the fold's profile run by an Estimator with K = 10
        profile = tuning.settings_with(EstimatorSettings(linearisation="oc",
                                                         update_iterations=10),
                                       fold.result.values)
        alone = scoring.evaluate(held, profile)
        assert np.array_equal(fold.test.nees, alone.nees, equal_nan=True)
        ekf = scoring.evaluate(held, replace(profile, update_iterations=1))
        assert not np.array_equal(alone.nees, ekf.nees, equal_nan=True)
        assert fold.result.update_iterations == 10
        text = tuning.profile_toml(fold.result)
        assert tomllib.loads(text)["update_iterations"] == 10
        loaded = load_settings(EstimatorSettings, _write(tmp_path / "p.toml", text),
                               {"robot": "robot1"})
        assert loaded.update_iterations == 10 and loaded.linearisation == "oc"
    plain = tuning.profile_toml(tuning.tune(runs[:1], base=EstimatorSettings(), max_passes=1))
    assert "update_iterations" not in tomllib.loads(plain)  # the EKF: nothing written


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_scale_choose_cross_validates_both_rules(tmp_path: Path) -> None:
    """``--scale choose`` makes a candidate of each rule; a candidate's rule reaches every
    fold's fit: with ``all`` the sensor σ are the fold's measured ones × its scale."""
    from slamlens.services.slam import crossval
    from slamlens.services.slam.cli import _scales
    from slamlens.services.slam.settings import TuneSettings

    assert _scales(TuneSettings(scale="choose")) == ["motion", "all"]
    assert _scales(TuneSettings(scale="all")) == ["all"]
    folder = two_robots(tmp_path)
    runs = [load_mrclam(folder, k) for k in (1, 2)]
    every = crossval.cross_validate(runs, crossval.Candidate("fej", scale="all"))
    assert every.candidate.label == "fej, spec motion model, all σ scaled"
    for fold, held in zip(every.folds, runs, strict=True):
        train = [r for r in runs if r is not held]
        measured = tuning.fit_noise(train).values
        assert fold.result.scaled == "all" and fold.result.scale != 1.0
        for key in ("sigma_range", "sigma_bearing", "sigma_v", "sigma_w"):
            assert fold.result.values[key] == pytest.approx(
                measured[key] * fold.result.scale, rel=1e-12)
