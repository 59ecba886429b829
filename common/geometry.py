"""Small geometry helpers shared by every service: angles, rigid transforms, P_d."""

from __future__ import annotations

import math

import numpy as np

from slamlens.common.errors import ConfigError


def wrap_angle(angle: float | np.ndarray) -> float | np.ndarray:
    """Wrap radians to [-π, π) (docs/estimator.md); angles already in range come back unchanged.

    The modulo formula alone adds a rounding error (~1e-16) to in-range angles, which
    would make a dataset's bearings differ from the file they were read from.
    """
    if isinstance(angle, np.ndarray):
        inside = (angle >= -math.pi) & (angle < math.pi)
        return np.where(inside, angle, (angle + math.pi) % (2.0 * math.pi) - math.pi)
    if -math.pi <= angle < math.pi:
        return angle
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def rot_z(theta: float) -> np.ndarray:
    """3x3 rotation about z by ``theta`` radians."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from a rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (transpose the rotation, no general inverse)."""
    R = T[:3, :3]
    return make_T(R.T, -R.T @ T[:3, 3])


def T_from_pose2(pose: np.ndarray, *, z: float = 0.0) -> np.ndarray:
    """T_map_from_robot for a planar pose (x, y, θ) at height ``z``."""
    return make_T(rot_z(float(pose[2])), np.array([pose[0], pose[1], z]))


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to an (N, 3) array of points."""
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    return pts @ T[:3, :3].T + T[:3, 3]


def compose2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Planar pose composition a ⊕ b (b expressed in a's frame), θ wrapped."""
    c, s = math.cos(float(a[2])), math.sin(float(a[2]))
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1],
                     float(wrap_angle(float(a[2]) + float(b[2])))])


def inverse2(a: np.ndarray) -> np.ndarray:
    """The planar pose ⊖a, so that ⊖a ⊕ a = 0."""
    c, s = math.cos(float(a[2])), math.sin(float(a[2]))
    return np.array([-c * a[0] - s * a[1], s * a[0] - c * a[1], float(wrap_angle(-float(a[2])))])


def transform2(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply the planar pose ``T`` (x, y, θ) as a rigid transform to (N, 2) points."""
    c, s = math.cos(float(T[2])), math.sin(float(T[2]))
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    return np.column_stack([T[0] + c * pts[:, 0] - s * pts[:, 1],
                            T[1] + s * pts[:, 0] + c * pts[:, 1]])


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees (for registration error reports)."""
    c = (np.trace(R) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def relative_covariance(P: np.ndarray, i: int, j: int) -> np.ndarray:
    """P_d = P_ii + P_jj − P_ij − P_ijᵀ for landmarks at state indices i, j (docs/monitor.md).

    ``i`` and ``j`` are landmark positions in the state (0-based), so landmark k occupies
    rows 3 + 2k and 3 + 2k + 1.
    """
    a, b = 3 + 2 * i, 3 + 2 * j
    Pii = P[a:a + 2, a:a + 2]
    Pjj = P[b:b + 2, b:b + 2]
    Pij = P[a:a + 2, b:b + 2]
    return Pii + Pjj - Pij - Pij.T


def all_relative_covariances(P: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """P_d for every pair i < j of the first ``n`` landmarks, vectorised.

    Returns ``(I, J, Pd)`` with ``Pd`` of shape (n(n−1)/2, 2, 2). Only the entries needed
    are gathered (four element gathers per pair), never a reshaped copy of P_mm.
    """
    first, second = np.triu_indices(n, k=1)
    lm = 3 + 2 * np.arange(n)
    # each landmark's own 2x2 block (a, b; b, d), then the cross block of each pair
    a_ = P[lm, lm]
    b_ = P[lm + 1, lm]
    d_ = P[lm + 1, lm + 1]
    r, c = lm[first], lm[second]
    Pd = np.empty((first.size, 2, 2))
    Pd[:, 0, 0] = a_[first] + a_[second] - 2.0 * P[r, c]
    Pd[:, 1, 1] = d_[first] + d_[second] - 2.0 * P[r + 1, c + 1]
    off = b_[first] + b_[second] - P[r, c + 1] - P[r + 1, c]
    Pd[:, 0, 1] = off
    Pd[:, 1, 0] = off
    return first, second, Pd


def eig2x2_max(Pd: np.ndarray) -> np.ndarray:
    """Largest eigenvalue of each symmetric 2x2 matrix in ``Pd`` (…, 2, 2), closed form."""
    a, b, d = Pd[..., 0, 0], 0.5 * (Pd[..., 0, 1] + Pd[..., 1, 0]), Pd[..., 1, 1]
    half_tr = 0.5 * (a + d)
    return half_tr + np.sqrt(np.maximum(0.25 * (a - d) ** 2 + b * b, 0.0))


def pd_size_m(Pd: np.ndarray) -> np.ndarray:
    """Size of a relative covariance: the 1-σ major semi-axis, √λ_max, in metres.

    One scalar per pair used wherever slamlens ranks or summarises P_d (demo summary,
    min/max picks): it is in metres, and it grows whenever P_d grows along its major axis.
    """
    return np.sqrt(np.maximum(eig2x2_max(Pd), 0.0))


def eig_sym2(M: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form eigen-decomposition of symmetric 2x2 matrices (..., 2, 2).

    Returns ``(lam_major, lam_minor, angle)``: eigenvalues with lam_major ≥ lam_minor and the
    angle (rad, in (−π/2, π/2]) of the major eigenvector (cos, sin). The off-diagonal is
    the mean of both entries, so a slightly asymmetric input is read as its symmetric part.
    """
    a = M[..., 0, 0]
    c = M[..., 1, 1]
    b = 0.5 * (M[..., 0, 1] + M[..., 1, 0])
    mean = 0.5 * (a + c)
    half_diff = 0.5 * (a - c)
    radius = np.hypot(half_diff, b)  # hypot: no overflow/underflow in the square
    angle = 0.5 * np.arctan2(b, half_diff)  # = ½·atan2(2b, a − c)
    return mean + radius, mean - radius, angle


def semi_axes(lam_major: np.ndarray, lam_minor: np.ndarray, *, glyph: str, sigma_k: float,
              scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Glyph semi-axes (m) from eigenvalues (m²): k-sigma ("sigma") or the paper's "linear".

    Negative eigenvalues (rounding on a singular P_d, or a broken estimator) give a zero axis.
    """
    lo = np.maximum(lam_minor, 0.0)
    hi = np.maximum(lam_major, 0.0)
    if glyph == "sigma":
        return scale * sigma_k * np.sqrt(hi), scale * sigma_k * np.sqrt(lo)
    if glyph == "linear":
        return scale * hi, scale * lo  # the paper: axis length = eigenvalue, read as metres
    raise ConfigError(f"unknown glyph mode {glyph!r}")
