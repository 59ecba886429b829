"""A dense textbook EKF-SLAM over whole runs, written from docs/estimator.md alone: the
independent oracle the shipped :class:`~slamlens.services.slam.estimator.Estimator` is held
to on real data (tests) and the base of the MRCLAM experiments (benchmarks).

It keeps the full (3 + 2n)² covariance as one numpy array and applies the documented
models with dense Jacobians: the motion model with its process noise M = diag(σv², σω²)
through Fu; range and bearing with R = diag(σr² + (k·r)² + (k_off·r·φ²)², σφ²); a new
landmark's rows through Gv and Gz; the χ² gate on each observation's NIS. The three
linearisations:

* ``standard``: every Jacobian at the latest estimates; observations in message order, an
  unknown id initialised where it comes (and a repeat of it in the batch then updating);
* ``fej``: Fx from the robot's propagated positions, H and Gv at the first estimates and
  the propagated robot position (FEJ's points); new landmarks after the batch's updates;
* ``oc``: FEJ's points, Fx and Gv; H at the latest estimates, each row moved the least
  that makes it blind to the unobservable directions (the closed form h* = h − α u).

It starts from the settings' initial pose and its σ. It does not model what MRCLAM and the
tests never send (two sightings of one new landmark in one batch under FEJ / OC, anonymous
ids, the plausibility bounds) and refuses a planted fault. For the
experiments it can carry states beside robot and map (:class:`Extra`): a Gauss-Markov
range bias per landmark, and the camera's range scale, bearing offset and bearing scale
(constants); none moves N, the global directions (their rows of N are 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from slamlens.common.messages import Observations, Odometry
from slamlens.services.slam.settings import EstimatorSettings

CAPACITY = 256  #: landmarks the arrays hold (Victoria Park has 151)


@dataclass(frozen=True)
class Extra:
    """The states added to robot and map (0 = not carried)."""

    bias_sd: float = 0.0  #: σ_b, m
    bias_tau: float = 10.0  #: τ, s
    white: float = 1.0  #: the white range σ as a share of the profile's
    scale_sd: float = 0.0  #: σ_ε
    motion: float = 1.0  #: the profile's motion σ times this (1/c undoes its NEES scale)
    offset_sd: float = 0.0  #: σ of the camera's bearing offset δ (its yaw on the robot), rad
    bearing_scale_sd: float = 0.0  #: σ of its bearing scale s: z_φ = (1 + s)·φ + δ

    def label(self) -> str:
        parts = []
        if self.bias_sd:
            parts.append(f"bias σ {self.bias_sd} m τ {self.bias_tau:g} s white ×{self.white}")
        if self.scale_sd:
            parts.append(f"scale σ {self.scale_sd}")
        if self.offset_sd:
            parts.append(f"bearing offset σ {self.offset_sd}")
        if self.bearing_scale_sd:
            parts.append(f"bearing scale σ {self.bearing_scale_sd}")
        if self.motion != 1.0:
            parts.append(f"motion σ ×{self.motion}")
        return ", ".join(parts) or "none (the shipped filter)"


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


class DenseEkf:
    """A dense EKF over [x, y, θ, (ε), (mx, my, (b)) …] (module docstring)."""

    def __init__(self, settings: EstimatorSettings, extra: Extra = Extra()) -> None:
        if settings.linearisation not in ("standard", "fej", "oc"):
            raise ValueError(f"linearisation {settings.linearisation!r}")
        if settings.fault != "none":
            raise ValueError(f"a dense EKF plants no faults ({settings.fault!r})")
        self.s, self.extra, self.kind = settings, extra, settings.linearisation
        self.base = 4 if extra.scale_sd else 3
        self.camera: dict[str, int] = {}  #: "offset" / "scale" → its row, when carried
        for name, sd in (("offset", extra.offset_sd), ("scale", extra.bearing_scale_sd)):
            if sd:
                self.camera[name] = self.base
                self.base += 1
        self.block = 3 if extra.bias_sd else 2
        size = self.base + self.block * CAPACITY
        self.x, self.P = np.zeros(size), np.zeros((size, size))
        self.x[:3] = settings.initial_pose
        self.P[:3, :3] = np.diag(np.square(settings.initial_pose_sigma))
        if extra.scale_sd:
            self.P[3, 3] = extra.scale_sd ** 2
        if self.camera:
            rows = list(self.camera.values())
            self.P[rows, rows] = [sd ** 2 for sd in (extra.offset_sd, extra.bearing_scale_sd)
                                  if sd]
        self.n = self.base
        self.index: dict[int, int] = {}  #: landmark id → first row of its block
        self.first: dict[int, np.ndarray] = {}  #: FEJ's first estimates
        self.seen: dict[int, float] = {}  #: when each bias was last brought forward
        self.propagated = self.x[:2].copy()  #: FEJ's p̂(k|k−1)
        self.gated = 0
        self.parts: list[tuple[float, ...]] = []  #: (ν_r², ν_φ², S_rr, S_φφ, R_rr, R_φφ)

    @property
    def scale(self) -> float:
        return 1.0 + float(self.x[3]) if self.extra.scale_sd else 1.0

    def bearing_camera(self) -> tuple[float, float]:
        """The camera's bearing offset δ and scale s as estimated (0 when not carried)."""
        return tuple(float(self.x[self.camera[k]]) if k in self.camera else 0.0
                     for k in ("offset", "scale"))  # type: ignore[return-value]

    def apply(self, message: Odometry | Observations) -> list[tuple[np.ndarray, np.ndarray]]:
        """One input; the (ν, S) of the observations applied."""
        if isinstance(message, Odometry):
            self.predict(message.v, message.w, message.dt)
            return []
        return self.observe(message.ids.tolist(), message.ranges.tolist(),
                            message.bearings.tolist(), message.stamp)

    def predict(self, v: float, w: float, dt: float) -> None:
        x, P, n, th = self.x, self.P, self.n, float(self.x[2])
        nx, ny = x[0] + v * dt * math.cos(th), x[1] + v * dt * math.sin(th)
        ref = x[:2] if self.kind == "standard" else self.propagated
        dx, dy = nx - ref[0], ny - ref[1]
        F = np.array([[1.0, 0.0, -dy], [0.0, 1.0, dx], [0.0, 0.0, 1.0]])
        Fu = np.array([[dt * math.cos(th), 0.0], [dt * math.sin(th), 0.0], [0.0, dt]])
        m = self.extra.motion ** 2
        M = np.diag([self.s.sigma_v ** 2 * m, self.s.sigma_w ** 2 * m])
        x[0], x[1], x[2] = nx, ny, _wrap(th + w * dt)
        P[:3, :n] = F @ P[:3, :n]
        P[:n, :3] = P[:n, :3] @ F.T
        P[:3, :3] += Fu @ M @ Fu.T
        self.propagated = x[:2].copy()

    def observe(self, ids: list[int], ranges: list[float], bearings: list[float],
                stamp: float) -> list[tuple[np.ndarray, np.ndarray]]:
        applied: list[tuple[np.ndarray, np.ndarray]] = []
        new: list[tuple[int, float, float]] = []
        for lid, zr, zb in zip(ids, ranges, bearings, strict=True):
            if lid not in self.index:
                if self.kind == "standard":
                    self.initialise(lid, zr, zb, stamp)
                elif all(lid != k for k, _, _ in new):
                    new.append((lid, zr, zb))
                continue
            done = self.update(lid, zr, zb, stamp)
            if done is not None:
                applied.append(done)
        for lid, zr, zb in new:  # FEJ's and OC's order: after the updates
            self.initialise(lid, zr, zb, stamp)
        return applied

    def range_variance(self, z_range: float, z_bearing: float) -> float:
        s = self.s
        off = z_range * z_bearing * z_bearing
        var = (s.sigma_range ** 2 + (s.sigma_range_per_m * z_range) ** 2
               + (s.sigma_range_off_axis * off) ** 2)
        return var * self.extra.white ** 2 if self.extra.bias_sd else var

    def _bring_bias_forward(self, lid: int, a: int, stamp: float) -> None:
        phi = math.exp(-(stamp - self.seen[lid]) / self.extra.bias_tau)
        self.seen[lid] = stamp
        b, n = a + 2, self.n
        self.x[b] *= phi
        self.P[b, :n] *= phi
        self.P[:n, b] *= phi
        self.P[b, b] += self.extra.bias_sd ** 2 * (1.0 - phi * phi)

    def _rows(self, lid: int, a: int) -> tuple[np.ndarray, np.ndarray]:
        """H's two rows on (x, y, θ, mx, my), as the linearisation evaluates them."""
        x = self.x
        if self.kind == "fej":
            dx, dy = self.first[lid] - self.propagated
        else:
            dx, dy = x[a] - x[0], x[a + 1] - x[1]
        q = dx * dx + dy * dy
        r = math.sqrt(q)
        h0 = np.array([-dx / r, -dy / r, 0.0, dx / r, dy / r])
        h1 = np.array([dy / q, -dx / q, -1.0, -dy / q, dx / q])
        if self.kind != "oc":
            return h0, h1
        D = self.first[lid] - self.propagated
        u = np.array([D[1] / 2, -D[0] / 2, 1.0, -D[1] / 2, D[0] / 2])
        den = 1.0 + float(D @ D) / 2
        return tuple(h - (h[2] + h[0] * D[1] - h[1] * D[0]) / den * u for h in (h0, h1))

    def update(self, lid: int, z_range: float, z_bearing: float,
               stamp: float) -> tuple[np.ndarray, np.ndarray] | None:
        """One sighting of a mapped landmark; (ν, S) when applied, None when gated."""
        x, P, n, a = self.x, self.P, self.n, self.index[lid]
        if self.extra.bias_sd:
            self._bring_bias_forward(lid, a, stamp)
        dx, dy = x[a] - x[0], x[a + 1] - x[1]
        r = math.hypot(dx, dy)
        bias = float(x[a + 2]) if self.extra.bias_sd else 0.0
        offset, bscale = self.bearing_camera()
        phi = _wrap(math.atan2(dy, dx) - x[2])
        nu = np.array([z_range - (self.scale * r + bias),
                       _wrap(z_bearing - ((1.0 + bscale) * phi + offset))])
        h0, h1 = self._rows(lid, a)
        H = np.zeros((2, n))
        H[0, [0, 1, 2, a, a + 1]] = h0 * self.scale
        H[1, [0, 1, 2, a, a + 1]] = h1 * (1.0 + bscale)
        if "offset" in self.camera:
            H[1, self.camera["offset"]] = 1.0
        if "scale" in self.camera:
            H[1, self.camera["scale"]] = phi
        if self.extra.scale_sd:
            H[0, 3] = r
        if self.extra.bias_sd:
            H[0, a + 2] = 1.0
        PHt = P[:n, :n] @ H.T
        R = (self.range_variance(z_range, z_bearing), self.s.sigma_bearing ** 2)
        S = H @ PHt + np.diag(R)
        gate = self.s.innovation_gate_chi2  # 0 = no gate (docs/estimator.md)
        if gate and float(nu @ np.linalg.solve(S, nu)) > gate:
            self.gated += 1
            return None
        self.parts.append((nu[0] ** 2, nu[1] ** 2, S[0, 0], S[1, 1], *R))
        K = np.linalg.solve(S, PHt.T).T
        x[:n] += K @ nu
        x[2] = _wrap(float(x[2]))
        P[:n, :n] -= K @ S @ K.T
        P[:n, :n] = 0.5 * (P[:n, :n] + P[:n, :n].T)
        return nu, S

    def initialise(self, lid: int, z_range: float, z_bearing: float, stamp: float) -> None:
        """A new landmark's block: Gv (at FEJ's robot point but for ``standard``), Gz, and
        ∂ℓ/∂ε, ∂ℓ/∂b, ∂ℓ/∂δ, ∂ℓ/∂s when carried."""
        x, P, n, a = self.x, self.P, self.n, self.n
        offset, bscale = self.bearing_camera()
        phi = (z_bearing - offset) / (1.0 + bscale)  #: the bearing the camera's reading says
        c, s = math.cos(x[2] + phi), math.sin(x[2] + phi)
        rr = z_range / self.scale
        mx, my = x[0] + rr * c, x[1] + rr * s
        p = x[:2] if self.kind == "standard" else self.propagated
        G = np.zeros((2, n))
        G[:, :3] = [[1.0, 0.0, -(my - p[1])], [0.0, 1.0, mx - p[0]]]
        if self.extra.scale_sd:
            G[:, 3] = [-rr / self.scale * c, -rr / self.scale * s]
        turn = rr / (1.0 + bscale)  #: ∂ℓ/∂z_φ's length
        Gz = np.array([[c / self.scale, -turn * s], [s / self.scale, turn * c]])
        if "offset" in self.camera:  # ∂φ/∂δ = −1/(1 + s)
            G[:, self.camera["offset"]] = [turn * s, -turn * c]
        if "scale" in self.camera:  # ∂φ/∂s = −φ/(1 + s)
            G[:, self.camera["scale"]] = [turn * s * phi, -turn * c * phi]
        R = np.diag([self.range_variance(z_range, z_bearing), self.s.sigma_bearing ** 2])
        P[a:a + 2, :n] = G @ P[:n, :n]
        P[:n, a:a + 2] = P[a:a + 2, :n].T
        P[a:a + 2, a:a + 2] = G @ P[:n, :n] @ G.T + Gz @ R @ Gz.T
        x[a], x[a + 1] = mx, my
        if self.extra.bias_sd:  # ℓ = p + (z − b)·dir: ∂ℓ/∂b = −dir/(1 + ε)
            g, var, b = -Gz[:, 0], self.extra.bias_sd ** 2, a + 2
            P[b, :] = 0.0
            P[:, b] = 0.0
            P[a:a + 2, a:a + 2] += np.outer(g, g) * var
            P[b, b] = var
            P[a:a + 2, b] = P[b, a:a + 2] = g * var
            x[b] = 0.0
            self.seen[lid] = stamp
        self.index[lid], self.first[lid] = a, np.array([mx, my])
        self.n += self.block

    def landmarks(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids, positions) in state order."""
        ids = sorted(self.index, key=self.index.__getitem__)
        return np.array(ids), np.array([self.x[self.index[i]:self.index[i] + 2] for i in ids])

    @property
    def pose_covariance(self) -> np.ndarray:
        """P_vv, the robot's 3×3 block."""
        return self.P[:3, :3]

    def covariance(self) -> np.ndarray:
        """P over robot and landmarks (without the extra states), in state order."""
        rows = [0, 1, 2] + [self.index[i] + k for i in self.landmarks()[0] for k in (0, 1)]
        return self.P[np.ix_(rows, rows)]
