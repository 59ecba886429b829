"""The dense EKF's camera states (services/harness/dense_ekf.py, ``Extra.offset_sd`` and
``Extra.bearing_scale_sd``), held to a simulated camera whose bearing offset and scale are
known: a robot drives a circle among landmarks with the model's own motion noise, and the
camera reads z_φ = (1 + s)·φ + δ + noise. Over 20 seeds the estimated (δ, s) must lie
where their covariance says (a Monte-Carlo NEES of 2 dof) and the pose NEES stay near 3;
without the states the same camera leaves the filter overconfident. This is the check that
the states are right before docs/consistency.md reports what they do on MRCLAM (they run
off there)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from slamlens.common.messages import Observations, Odometry
from slamlens.services.harness.dense_ekf import DenseEkf, Extra
from slamlens.services.slam.settings import EstimatorSettings

OFFSET, SCALE = 0.03, 0.05  #: the simulated camera: 1.7° of yaw, 5 % of bearing scale
SEEDS = 20
STEPS, DT = 1500, 0.05  #: 75 s: a little over two laps of the circle
V, W = 0.5, 0.2  #: commanded speed and turn rate
LANDMARKS = np.array([[2.0 * math.cos(a), 2.5 + 2.0 * math.sin(a)]
                      for a in np.linspace(0.0, 2 * math.pi, 12, endpoint=False)])
FOV, MAX_RANGE = 1.0, 3.5  #: the camera sees ±1 rad out to 3.5 m
SETTINGS = EstimatorSettings(linearisation="oc", sigma_v=0.05, sigma_w=0.05,
                             sigma_range=0.03, sigma_bearing=0.01, innovation_gate_chi2=0.0,
                             robot="robot1")


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def simulate(seed: int, offset: float, scale: float
             ) -> tuple[list[Odometry | Observations], list[np.ndarray]]:
    """The messages of one run with a camera of that bearing offset and scale, and the true
    pose after each."""
    rng = np.random.default_rng(seed)
    pose, messages, truth = np.zeros(3), [], []
    for k in range(1, STEPS + 1):
        v = V + rng.normal(0.0, SETTINGS.sigma_v)  # the model's noise on the true controls
        w = W + rng.normal(0.0, SETTINGS.sigma_w)
        pose = pose + [v * DT * math.cos(pose[2]), v * DT * math.sin(pose[2]), w * DT]
        pose[2] = _wrap(pose[2])
        messages.append(Odometry(robot="robot1", stamp=k * DT, dt=DT, v=V, w=W))
        truth.append(pose.copy())
        if k % 4:
            continue
        d = LANDMARKS - pose[:2]
        ranges = np.hypot(d[:, 0], d[:, 1])
        bearings = np.array([_wrap(math.atan2(y, x) - pose[2]) for x, y in d])
        seen = (ranges < MAX_RANGE) & (np.abs(bearings) < FOV)
        n = int(seen.sum())
        messages.append(Observations(
            robot="robot1", stamp=k * DT, ids=np.nonzero(seen)[0].astype(np.int64) + 1,
            ranges=ranges[seen] + rng.normal(0.0, SETTINGS.sigma_range, n),
            bearings=(1 + scale) * bearings[seen] + offset
            + rng.normal(0.0, SETTINGS.sigma_bearing, n)))
        truth.append(pose.copy())
    return messages, truth


def run(seed: int, extra: Extra, camera: tuple[float, float] = (OFFSET, SCALE)
        ) -> tuple[float, float]:
    """(the camera states' NEES at the end, the mean pose NEES over the run's second half)."""
    messages, truth = simulate(seed, *camera)
    ekf = DenseEkf(SETTINGS, extra)
    nees = []
    for k, (m, pose) in enumerate(zip(messages, truth, strict=True)):
        ekf.apply(m)
        if k >= len(messages) // 2:
            e = ekf.x[:3] - pose
            e[2] = _wrap(float(e[2]))
            nees.append(float(e @ np.linalg.solve(ekf.P[:3, :3], e)))
    if not ekf.camera:
        return math.nan, float(np.mean(nees))
    rows = list(ekf.camera.values())
    e = np.array(ekf.bearing_camera()) - camera
    return float(e @ np.linalg.solve(ekf.P[np.ix_(rows, rows)], e)), float(np.mean(nees))


def test_the_camera_states_find_the_simulated_camera() -> None:
    results = [run(seed, Extra(offset_sd=0.05, bearing_scale_sd=0.1)) for seed in range(SEEDS)]
    camera = np.array([c for c, _ in results])
    pose = np.array([p for _, p in results])
    # the sum of SEEDS independent χ²₂ values is χ²₂·SEEDS: two-sided 99 %
    lo, hi = stats.chi2.ppf([0.005, 0.995], 2 * SEEDS)
    assert lo <= camera.sum() <= hi, camera
    assert 1.5 <= float(np.mean(pose)) <= 6.0, pose


def test_without_the_states_that_camera_makes_the_filter_overconfident() -> None:
    pose = np.array([run(seed, Extra())[1] for seed in range(5)])
    assert float(np.mean(pose)) > 10.0, pose


def test_a_camera_with_neither_error_is_estimated_near_zero() -> None:
    camera = np.array([run(seed, Extra(offset_sd=0.05, bearing_scale_sd=0.1), (0.0, 0.0))[0]
                       for seed in range(SEEDS)])
    lo, hi = stats.chi2.ppf([0.005, 0.995], 2 * SEEDS)
    assert lo <= camera.sum() <= hi, camera


@pytest.mark.parametrize("extra", [Extra(offset_sd=0.05), Extra(bearing_scale_sd=0.1)])
def test_each_state_alone_has_its_own_row(extra: Extra) -> None:
    ekf = DenseEkf(SETTINGS, extra)
    assert len(ekf.camera) == 1 and ekf.base == 4
    (row,) = ekf.camera.values()
    assert ekf.P[row, row] == pytest.approx((extra.offset_sd or extra.bearing_scale_sd) ** 2)
