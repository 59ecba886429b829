"""Victoria Park in GTSAM's text format (services/slam/victoria_park.py, docs/drivers.md):
the file as read, GTSAM's reading of its noise, and the played odometry against GTSAM's
pose composition written out here (x' = x + R(θ)(dx, dy), θ' = θ + dθ)."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from slamlens.common.config import load_settings
from slamlens.common.errors import SourceError
from slamlens.common.messages import Observations, Odometry
from slamlens.services.slam import models
from slamlens.services.slam.settings import EstimatorSettings
from slamlens.services.slam.victoria_park import load_victoria_park
from tests.conftest import REPO, SHARED_DATA

FILE = SHARED_DATA / "victoria_park" / "victoria_park_gtsam.txt"
PROFILE = REPO / "deploy" / "victoria_park.toml"


def compose(pose: np.ndarray, step: np.ndarray) -> np.ndarray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([pose[0] + c * step[0] - s * step[1], pose[1] + s * step[0] + c * step[1],
                     pose[2] + step[2]])


@pytest.fixture(scope="module")
def run():
    return load_victoria_park(FILE)


def test_the_file_is_read_whole(run) -> None:
    # the data's own description: 6969 poses, 3640 observations of 151 landmarks
    assert run.poses.size == 6969 and run.steps.shape == (6968, 3)
    assert run.stats.sightings == 3640 and run.landmark_ids.size == 151
    assert run.stats.bad_lines == 0
    assert run.poses[0] == 0 and run.poses[-1] == 7119  # pose ids skip the landmarks' 151
    assert load_victoria_park(FILE.parent).steps.shape == (6968, 3)  # a folder finds it


def test_the_noise_is_read_as_gtsam_reads_it(run) -> None:
    n = run.noise
    assert (n.var_dx, n.var_dy, n.var_dtheta) == (1e-4, 4e-6, 4e-6)  # a covariance
    assert n.sigma_range == pytest.approx(math.sqrt(0.4))  # "at 10 m"
    assert n.sigma_bearing == pytest.approx(math.sqrt(0.04))
    # the shipped profile is the file's noise for the default step (0.02 s + 0.18 s)
    sigmas = n.estimator_sigmas()
    assert sigmas["sigma_v"] ** 2 * (0.02 ** 2 + 0.18 ** 2) == pytest.approx(1e-4)
    assert sigmas["sigma_w"] ** 2 * (0.02 ** 2 + 0.18 ** 2) == pytest.approx(4e-6)
    profile = load_settings(EstimatorSettings, PROFILE, {})
    for name, value in sigmas.items():
        assert getattr(profile, name) == pytest.approx(value, rel=1e-3), name
    assert profile.linearisation == "oc"


def test_the_played_odometry_is_gtsams_pose_composition(run) -> None:
    """The unicycle's pose after each step's two Odometry is the composed pose, to
    rounding, over the whole drive (4 km, 59 steps in reverse)."""
    model, truth = np.zeros(3), np.zeros(3)
    steps = iter(run.steps)
    worst, played = 0.0, 0
    for m in run.events():
        if not isinstance(m, Odometry):
            continue
        model = models.motion(model, v=m.v, w=m.w, dt=m.dt)
        played += 1
        assert abs(m.v) <= 8.2 and abs(m.w) <= 2.9  # the car's speeds, within the gates
        if played % 2 == 0:
            truth = compose(truth, next(steps))
            worst = max(worst, float(np.hypot(*(model[:2] - truth[:2]))),
                        abs(math.remainder(model[2] - truth[2], math.tau)))
    assert played == 2 * 6968 and worst < 1e-6
    assert np.hypot(*truth[:2]) > 100  # odometry alone ends far from its start


def test_sightings_come_at_their_pose_after_the_step_that_reached_it(run) -> None:
    events = list(run.events(end=10.0))  # poses 0 … 50
    assert events[-1].stamp <= 10.0
    last_odometry = -1.0
    for m in events:
        if isinstance(m, Odometry):
            last_odometry = m.stamp
        else:
            assert isinstance(m, Observations) and m.stamp >= last_odometry
            k = round(m.stamp / run.step_s)
            rows = run.sightings[run.sightings[:, 0] == k]
            assert m.ids.tolist() == rows[:, 1].astype(int).tolist()
            np.testing.assert_allclose(m.ranges, np.hypot(rows[:, 2], rows[:, 3]))
            np.testing.assert_allclose(m.bearings, np.arctan2(rows[:, 3], rows[:, 2]))
    later = list(run.events(start=100.0, end=101.0))
    assert all(100.0 <= m.stamp <= 101.0 for m in later) and later


def test_bad_lines_are_counted_and_bad_files_refused(tmp_path: Path) -> None:
    good = ["ODOMETRY 0 1 0.5 0 0.01 0.0001 0 0 4e-06 0 4e-06",
            "LANDMARK 1 2 3.0 1.0 0.4 0 0.4",
            "ODOMETRY 1 3 0.5 0 0.01 0.0001 0 0 4e-06 0 4e-06"]
    bad = ["ODOMETRY 3 4 0.5 0 nan 0.0001 0 0 4e-06 0 4e-06",  # not finite
           "ODOMETRY 9 10 0.5 0 0 0.0001 0 0 4e-06 0 4e-06",  # off the chain
           "LANDMARK 3 2 1.0",  # columns
           "VERTEX2 7 0 0 0",  # a tag this reader does not take
           "LANDMARK 99 2 3.0 1.0 0.4 0 0.4"]  # a pose not on the chain
    path = tmp_path / "vp.txt"
    path.write_text("\n".join(good + bad) + "\n")
    run = load_victoria_park(path)
    assert run.steps.shape == (2, 3) and run.stats.sightings == 1
    assert run.stats.bad_lines == len(bad)
    # the chain breaks after pose 3 (its next step was the NaN line): the run ends there
    assert (run.stats.chain_ends_at, run.stats.off_chain) == (3, 1)
    path.write_text(good[0] + "\nLANDMARK 1 2 3.0 1.0 0.4 0 0.1\n")  # anisotropic
    with pytest.raises(SourceError, match="not isotropic"):
        load_victoria_park(path)
    path.write_text("LANDMARK 1 2 3.0 1.0 0.4 0 0.4\n")
    with pytest.raises(SourceError, match="no ODOMETRY"):
        load_victoria_park(path)
    with pytest.raises(SourceError, match="cannot read"):
        load_victoria_park(tmp_path / "missing.txt")


def test_a_longer_step_plays_the_same_poses(run) -> None:
    """--step-s changes the stamps and speeds, not where the model ends."""
    slow = replace(run, step_s=1.0)
    a, b = np.zeros(3), np.zeros(3)
    for m, n in zip(run.events(end=60.0), slow.events(end=300.0), strict=True):
        assert type(m) is type(n)
        if isinstance(m, Odometry):
            a = models.motion(a, v=m.v, w=m.w, dt=m.dt)
            b = models.motion(b, v=n.v, w=n.w, dt=n.dt)
    np.testing.assert_allclose(a, b, atol=1e-9)


def test_a_corrupted_file_is_read_or_refused_never_crashes(tmp_path: Path) -> None:
    """Lines of the real file, each corrupted at random (a token dropped, doubled, turned to
    text, NaN or ±inf, a tag misspelt, bytes not UTF-8): every load keeps the good lines and
    counts the others, or refuses the file with a SourceError — never another exception."""
    lines = FILE.read_text().splitlines()[:400]
    rng = np.random.default_rng(7)
    outcomes = {"read": 0, "refused": 0}
    for trial in range(60):
        out = []
        for line in lines:
            tokens = line.split()
            kind = rng.integers(12)
            k = int(rng.integers(len(tokens)))
            if kind == 0:
                tokens.pop(k)
            elif kind == 1:
                tokens.insert(k, tokens[k])
            elif kind == 2:
                tokens[k] = rng.choice(["x", "nan", "inf", "-inf", "1e999", "", "#"])
            elif kind == 3:
                tokens[0] = tokens[0].lower()
            out.append(" ".join(tokens))
        path = tmp_path / f"corrupt{trial}.txt"
        path.write_bytes("\n".join(out).encode() + (b"\xff\xfe\n" if trial % 2 else b""))
        try:
            run = load_victoria_park(path)
        except SourceError:
            outcomes["refused"] += 1
            continue
        outcomes["read"] += 1
        assert run.stats.bad_lines > 0 and run.steps.shape[0] >= 1
        assert np.isfinite(run.steps).all() and np.isfinite(run.sightings).all()
        for m in run.events():  # every message it makes is valid (constructed, checked)
            assert np.isfinite(m.stamp)
    assert outcomes["read"] > 0, outcomes
