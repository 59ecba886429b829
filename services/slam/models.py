"""The estimator's models (docs/estimator.md, "The models") as small pure functions of
small arrays: the motion model, the range-bearing observation, the landmark a new
observation places, and their Jacobians. The kernels of :mod:`slamlens.services.slam.ekf`
use the same closed forms in place, on the covariance; the tests hold the kernels to these
and these to numerical derivatives, and tests and benchmarks make observations with them.
"""

from __future__ import annotations

import math

import numpy as np

_TWO_PI = 2.0 * math.pi


def wrap(angle: float) -> float:
    """An angle wrapped to [−π, π): the modulo formula on one float, without
    :func:`slamlens.common.geometry.wrap_angle`'s numpy dispatch (the kernels' hot path)."""
    return (angle + math.pi) % _TWO_PI - math.pi


def motion(pose: np.ndarray, *, v: float, w: float, dt: float) -> np.ndarray:
    """First-order velocity model: the pose after driving (v m/s, w rad/s) for dt s."""
    x, y, theta = (float(p) for p in pose)
    return np.array([x + v * dt * math.cos(theta), y + v * dt * math.sin(theta),
                     wrap(theta + w * dt)])


def motion_jacobians(pose: np.ndarray, *, v: float, w: float,
                     dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(Fx 3×3, Fu 3×2) of :func:`motion` with respect to the pose and to (v, w)."""
    c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
    Fx = np.array([[1.0, 0.0, -v * dt * s], [0.0, 1.0, v * dt * c], [0.0, 0.0, 1.0]])
    Fu = np.array([[dt * c, 0.0], [dt * s, 0.0], [0.0, dt]])
    return Fx, Fu


def observe(pose: np.ndarray, landmark_xy: np.ndarray) -> np.ndarray:
    """h = (range m, bearing rad) of a landmark seen from ``pose``; bearing wrapped."""
    dx, dy = float(landmark_xy[0] - pose[0]), float(landmark_xy[1] - pose[1])
    return np.array([math.hypot(dx, dy), wrap(math.atan2(dy, dx) - float(pose[2]))])


def observation_jacobians(pose: np.ndarray,
                          landmark_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Hv 2×3, Hm 2×2) of :func:`observe` with respect to the pose and the landmark."""
    dx, dy = float(landmark_xy[0] - pose[0]), float(landmark_xy[1] - pose[1])
    q = dx * dx + dy * dy
    r = math.sqrt(q)
    Hv = np.array([[-dx / r, -dy / r, 0.0], [dy / q, -dx / q, -1.0]])
    Hm = np.array([[dx / r, dy / r], [-dy / q, dx / q]])
    return Hv, Hm


def inverse_observation(pose: np.ndarray, *, range_m: float, bearing: float) -> np.ndarray:
    """Landmark position (m, map frame) from a range-bearing observation taken at ``pose``."""
    alpha = float(pose[2]) + bearing
    return np.array([float(pose[0]) + range_m * math.cos(alpha),
                     float(pose[1]) + range_m * math.sin(alpha)])


def inverse_observation_jacobians(pose: np.ndarray, *, range_m: float,
                                  bearing: float) -> tuple[np.ndarray, np.ndarray]:
    """(Gv 2×3, Gz 2×2) of :func:`inverse_observation` w.r.t. the pose and (range, bearing)."""
    alpha = float(pose[2]) + bearing
    c, s = math.cos(alpha), math.sin(alpha)
    Gv = np.array([[1.0, 0.0, -range_m * s], [0.0, 1.0, range_m * c]])
    Gz = np.array([[c, -range_m * s], [s, range_m * c]])
    return Gv, Gz
