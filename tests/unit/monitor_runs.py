"""Runs for the monitor's tests: a small dense textbook EKF written here from
docs/estimator.md (correct, and with the two planted faults of the paper scenario done by
hand), the states and truths it makes, and helpers to feed them to a Monitor."""

from __future__ import annotations

import math

import numpy as np

from slamlens.common.geometry import wrap_angle
from slamlens.common.messages import Health, SlamState, Truth
from slamlens.services.monitor.monitor import Monitor

SIGMAS = dict(sigma_v=0.05, sigma_w=0.05, sigma_r=0.05, sigma_b=0.02)


# -- a dense textbook EKF (docs/estimator.md), the oracle of "correct" sequences --
class DenseEkf:
    """Full-size Jacobians, no tricks. Faults are planted by the run, not here."""

    def __init__(self) -> None:
        self.x = np.zeros(3)
        self.P = np.zeros((3, 3))
        self.ids: list[int] = []
        self.M = np.diag([SIGMAS["sigma_v"] ** 2, SIGMAS["sigma_w"] ** 2])
        self.R = np.diag([SIGMAS["sigma_r"] ** 2, SIGMAS["sigma_b"] ** 2])

    def predict(self, v: float, w: float, dt: float, *, frozen: tuple[int, ...] = ()) -> None:
        th = self.x[2]
        N = self.x.size
        F = np.eye(N)
        F[0, 2], F[1, 2] = -v * dt * math.sin(th), v * dt * math.cos(th)
        G = np.zeros((N, 2))
        G[:3] = [[dt * math.cos(th), 0.0], [dt * math.sin(th), 0.0], [0.0, dt]]
        old = self.P.copy()
        self.x[:3] += [v * dt * math.cos(th), v * dt * math.sin(th), w * dt]
        self.x[2] = wrap_angle(self.x[2])
        self.P = F @ self.P @ F.T + G @ self.M @ G.T
        for f in frozen:  # planted fault: P_v,f not propagated
            c = 3 + 2 * self.ids.index(f)
            self.P[:3, c:c + 2] = old[:3, c:c + 2]
            self.P[c:c + 2, :3] = old[c:c + 2, :3]

    def observe(self, fid: int, r: float, b: float) -> tuple[np.ndarray, np.ndarray] | None:
        if fid not in self.ids:
            a = self.x[2] + b
            m = self.x[:2] + r * np.array([math.cos(a), math.sin(a)])
            N = self.x.size
            G = np.zeros((2, N))
            G[:, :3] = [[1, 0, -r * math.sin(a)], [0, 1, r * math.cos(a)]]
            Gz = np.array([[math.cos(a), -r * math.sin(a)], [math.sin(a), r * math.cos(a)]])
            Pmm = G @ self.P @ G.T + Gz @ self.R @ Gz.T
            Pmx = G @ self.P
            self.P = np.block([[self.P, Pmx.T], [Pmx, Pmm]])
            self.x = np.concatenate([self.x, m])
            self.ids.append(fid)
            return None
        c = 3 + 2 * self.ids.index(fid)
        dx, dy = self.x[c] - self.x[0], self.x[c + 1] - self.x[1]
        q = dx * dx + dy * dy
        sq = math.sqrt(q)
        H = np.zeros((2, self.x.size))
        H[:, :3] = [[-dx / sq, -dy / sq, 0], [dy / q, -dx / q, -1]]
        H[:, c:c + 2] = [[dx / sq, dy / sq], [-dy / q, dx / q]]
        nu = np.array([r - sq, wrap_angle(b - (math.atan2(dy, dx) - self.x[2]))])
        S = H @ self.P @ H.T + self.R
        K = self.P @ H.T @ np.linalg.inv(S)
        self.x = self.x + K @ nu
        self.x[2] = wrap_angle(self.x[2])
        self.P = self.P - K @ S @ K.T
        self.P = 0.5 * (self.P + self.P.T)
        return nu, S

    def state(self, seq: int, stamp: float, step: str, innov: list | None = None) -> SlamState:
        n = len(self.ids)
        kw = {}
        if innov:
            kw = dict(innovation_ids=np.array([i for i, _, _ in innov]),
                      innovations=np.array([nu for _, nu, _ in innov]),
                      innovation_covariances=np.array([S for _, _, S in innov]))
        return SlamState(robot="r", seq=seq, stamp=stamp, step=step, pose=self.x[:3],
                         landmark_ids=np.array(self.ids, dtype=np.int64),
                         landmarks=self.x[3:].reshape(n, 2), covariance=self.P, **kw)


LANDMARKS = {i + 1: 2.2 * np.array([math.cos(a), math.sin(a)]) + [0.0, 1.0]
             for i, a in enumerate(np.linspace(0, 2 * math.pi, 7)[:-1])}


def run(*, seed: int = 0, steps: int = 260, map_fault: tuple[int, ...] = (),
        cross_fault: tuple[int, ...] = (), onset: float = 1e9, magnitude: float = 2e-3
        ) -> tuple[list[SlamState], list[Truth]]:
    """A robot driving a 1 m circle among 6 landmarks; states after every event."""
    rng = np.random.default_rng(seed)
    ekf, pose = DenseEkf(), np.zeros(3)
    states = [ekf.state(0, 0.0, "init")]
    truths = [Truth(robot="r", stamp=0.0, pose=pose, landmark_ids=np.array(list(LANDMARKS)),
                    landmarks=np.array(list(LANDMARKS.values())))]
    dt, v, w = 0.1, 0.3, 0.3
    for k in range(1, steps + 1):
        t = k * dt
        pose = pose + [v * dt * math.cos(pose[2]), v * dt * math.sin(pose[2]), w * dt]
        pose[2] = wrap_angle(pose[2])
        vm = v + rng.normal(0, SIGMAS["sigma_v"])
        wm = w + rng.normal(0, SIGMAS["sigma_w"])
        ekf.predict(vm, wm, dt, frozen=cross_fault if t >= onset else ())
        states.append(ekf.state(len(states), t, "predict"))
        truths.append(Truth(robot="r", stamp=t, pose=pose, landmark_ids=truths[0].landmark_ids,
                            landmarks=truths[0].landmarks))
        innov = []
        for fid, m in LANDMARKS.items():
            d = m - pose[:2]
            r = math.hypot(*d)
            b = wrap_angle(math.atan2(d[1], d[0]) - pose[2])
            if r > 2.8 or abs(b) > math.pi / 2:
                continue
            out = ekf.observe(fid, r + rng.normal(0, SIGMAS["sigma_r"]),
                              wrap_angle(b + rng.normal(0, SIGMAS["sigma_b"])))
            if out is not None:
                innov.append((fid, *out))
        if t >= onset:
            for f in map_fault:
                c = 3 + 2 * ekf.ids.index(f)
                ekf.P[c:c + 2, c:c + 2] += magnitude * np.eye(2)
        states.append(ekf.state(len(states), t, "update", innov))
    return states, truths


def feed(monitor: Monitor, states: list[SlamState], truths: list[Truth] | None = None
         ) -> list[Health]:
    by_stamp = {} if truths is None else {t.stamp: t for t in truths}
    out = []
    for s in states:
        if s.stamp in by_stamp:
            monitor.add_truth(by_stamp.pop(s.stamp))
        out.append(monitor.check(s))
    return out


def violations(healths: list[Health]) -> list:
    return [v for h in healths for v in h.violations]


def with_cov(state: SlamState, P: np.ndarray, *, seq: int | None = None,
             step: str | None = None) -> SlamState:
    return SlamState(robot=state.robot, seq=state.seq + 1 if seq is None else seq,
                     stamp=state.stamp, step=step or state.step, pose=state.pose,
                     landmark_ids=state.landmark_ids, landmarks=state.landmarks, covariance=P)

