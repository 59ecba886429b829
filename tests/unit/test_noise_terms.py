"""The opt-in noise terms and the innovation gate: what each adds,
that the defaults stay docs/estimator.md, and that the gate refuses a known landmark's outlier."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.settings import EstimatorSettings

OPT_IN = ("sigma_distance", "sigma_turn", "sigma_heading_per_distance", "sigma_range_per_m",
          "sigma_range_off_axis", "innovation_gate_chi2")


def test_the_defaults_are_the_spec_model_with_no_gate() -> None:
    s = EstimatorSettings()
    assert all(getattr(s, name) == 0.0 for name in OPT_IN)


def test_distance_and_turn_noise_of_one_step_in_closed_form() -> None:
    kd, kt, khd = 0.2, 0.3, 0.05
    est = Estimator(EstimatorSettings(sigma_v=0.0, sigma_w=0.0, sigma_distance=kd,
                                      sigma_turn=kt, sigma_heading_per_distance=khd,
                                      initial_pose=(0.0, 0.0, 0.7)))
    v, w, dt = 0.4, -0.6, 0.5
    est.predict(v=v, w=w, dt=dt, stamp=0.5)
    d, a = abs(v * dt), abs(w * dt)
    u = np.array([math.cos(0.7), math.sin(0.7), 0.0])
    expected = kd ** 2 * d * np.outer(u, u)
    expected[2, 2] = kt ** 2 * a + khd ** 2 * d
    np.testing.assert_allclose(est.pose_covariance, expected, rtol=1e-12, atol=1e-18)


def test_distance_noise_does_not_depend_on_the_odometry_rate_and_spec_noise_does() -> None:
    def along_variance(settings: EstimatorSettings, steps: int) -> float:
        est = Estimator(settings)
        for k in range(steps):
            est.predict(v=0.5, w=0.0, dt=2.0 / steps, stamp=2.0 * (k + 1) / steps)
        return float(est.pose_covariance[0, 0])

    opt_in = EstimatorSettings(sigma_v=0.0, sigma_w=0.0, sigma_distance=0.1)
    assert along_variance(opt_in, 1) == pytest.approx(0.1 ** 2 * 1.0, rel=1e-12)
    assert along_variance(opt_in, 200) == pytest.approx(0.1 ** 2 * 1.0, rel=1e-9)
    spec = EstimatorSettings(sigma_v=0.1, sigma_w=0.0)
    assert along_variance(spec, 200) == pytest.approx(along_variance(spec, 1) / 200, rel=1e-9)


def test_opt_in_range_noise_enters_s_and_the_new_landmark() -> None:
    sr, k, k_off = 0.05, 0.02, 0.4
    est = Estimator(EstimatorSettings(sigma_range=sr, sigma_range_per_m=k,
                                      sigma_range_off_axis=k_off))
    r, phi = 3.0, 0.5
    est.observe(ids=[7], ranges=[r], bearings=[phi], stamp=0.0)
    var_r = sr ** 2 + (k * r) ** 2 + (k_off * r * phi ** 2) ** 2
    c, s = math.cos(phi), math.sin(phi)
    rb = 0.02 ** 2 * r * r
    expected = var_r * np.outer([c, s], [c, s]) + rb * np.outer([-s, c], [-s, c])
    np.testing.assert_allclose(est.covariance[3:5, 3:5], expected, rtol=1e-12)
    P = est.covariance
    rep = est.observe(ids=[7], ranges=[r + 0.01], bearings=[phi], stamp=0.0)
    # S = H P Hᵀ + R with the same R: the robot is still at the origin with P_vv = 0
    dx, dy = r * c, r * s
    Hm = np.array([[dx / r, dy / r], [-dy / r ** 2, dx / r ** 2]])
    S = Hm @ P[3:5, 3:5] @ Hm.T + np.diag([sr ** 2 + (k * (r + 0.01)) ** 2
                                           + (k_off * (r + 0.01) * phi ** 2) ** 2, 0.02 ** 2])
    np.testing.assert_allclose(rep.innovation_covariances[0], S, rtol=1e-10, atol=1e-15)


def test_the_innovation_gate_refuses_a_known_landmarks_outlier_and_its_off_switch() -> None:
    def run(gate: float) -> tuple[Estimator, object]:
        est = Estimator(EstimatorSettings(innovation_gate_chi2=gate))
        est.observe(ids=[1, 2], ranges=[1.0, 2.0], bearings=[0.2, -0.3], stamp=0.0)
        est.predict(v=0.1, w=0.0, dt=0.1, stamp=0.1)
        rep = est.observe(ids=[1, 2], ranges=[0.99, 3.0], bearings=[0.21, -0.3], stamp=0.1)
        return est, rep

    gated, rep = run(13.82)
    assert list(rep.gated_ids) == [2] and rep.gated == 1 and rep.rejected == 1
    assert rep.gated_nis[0] > 13.82 and list(rep.gated_observations[0]) == [3.0, -0.3]
    assert list(rep.innovation_ids) == [1] and gated.gated == 1
    kept, rep_off = run(0.0)
    assert rep_off.gated == 0 and list(rep_off.innovation_ids) == [1, 2]
    # the gated outlier was not applied: the map moved less
    assert abs(gated.landmarks[1, 0] - 2.0 * math.cos(-0.3)) < \
        abs(kept.landmarks[1, 0] - 2.0 * math.cos(-0.3))


def test_the_gate_value_is_the_nis_of_the_innovation() -> None:
    est = Estimator(EstimatorSettings(innovation_gate_chi2=1e9))
    est.observe(ids=[1], ranges=[2.0], bearings=[0.1], stamp=0.0)
    est.predict(v=0.2, w=0.1, dt=0.2, stamp=0.2)
    rep = est.observe(ids=[1], ranges=[1.9], bearings=[0.05], stamp=0.2)
    nu, S = rep.innovations[0], rep.innovation_covariances[0]
    nis = float(nu @ np.linalg.solve(S, nu))
    tight = Estimator(EstimatorSettings(innovation_gate_chi2=nis * 0.999))
    tight.observe(ids=[1], ranges=[2.0], bearings=[0.1], stamp=0.0)
    tight.predict(v=0.2, w=0.1, dt=0.2, stamp=0.2)
    gated = tight.observe(ids=[1], ranges=[1.9], bearings=[0.05], stamp=0.2)
    assert gated.gated == 1 and gated.gated_nis[0] == pytest.approx(nis, rel=1e-9)
