"""Two states the shipped estimator does not have, tried on MRCLAM dataset 6 with a dense
OC-EKF — the experiments behind docs/consistency.md, "Why the NIS is low on real data".

The filter here is the shipped one written densely (the same models, OC's Jacobians, FEJ's
points, the gate, new landmarks after a batch's updates): with no extra state it gives the
shipped estimator's figures (``--check`` prints both). It can carry, beside robot and map:

* **a range bias per landmark** (``bias``): the range error that persists from one sighting
  of a landmark to the next (docs/consistency.md) as a first-order Gauss-Markov state b_i —
  z_r = |ℓ_i − p| + b_i + white, b_i(t + Δ) = φ b_i(t) + w with φ = exp(−Δ/τ) and
  var w = σ_b²(1 − φ²); new landmarks start with b_i = 0, var σ_b²; the white range variance
  is the profile's times ``white``²;
* **a range scale for the robot's camera** (``scale``): z_r = (1 + ε)|ℓ − p|, ε a constant
  with prior N(0, σ_ε²) — the maps' shape errors follow each camera's median range ratio
  (1.012, 1.010, 0.995, 1.020, 1.002 on robots 1–5);
* and, without either, the motion σ scaled back (×0.44 ≈ 1/c: the profile's σ before the
  scale that brings the pose NEES to 3).

Neither is in the global rotation or translation, so OC's null space N is unchanged (their
rows of N are 0) and the published marginal of robot and map would keep every covariance
theorem. Each robot runs with its left-out profile (benchmarks/profiles/without-robotK.toml);
printed: pose NEES, map shape (landmark RMSE after a rigid fit), NIS mean / median and the
share of the monitor's 50-innovation NIS windows outside their band, the final ε; and,
for the runs without an extra state, where S comes from (median |ν|, √S and √R).

Run: ``.venv/bin/python benchmarks/mrclam_augmented.py [--check]`` (≈ 1.5 min on 2 cores;
``--check`` ≈ 2 min).
"""

from __future__ import annotations

import argparse
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from slamlens.common.config import load_settings
from slamlens.common.messages import Odometry
from slamlens.services.harness.mrclam_pipeline import DATA
from slamlens.services.slam.mrclam import load_mrclam
from slamlens.services.slam.noise_model import NoiseModel
from slamlens.services.slam.scoring import Evaluation, Scorer, TruthTrack, evaluate
from slamlens.services.slam.settings import EstimatorSettings

REPO = Path(__file__).resolve().parents[1]
ROBOTS = (1, 2, 3, 4, 5)
NIS_WINDOW = 50
NIS_SIGNIFICANCE = 1e-6  #: the monitor's two-sided significance per window
CAPACITY = 40  #: landmarks (MRCLAM has 15 and 5 robots' barcodes)


@dataclass(frozen=True)
class Extra:
    """The states added to robot and map (0 = not carried)."""

    bias_sd: float = 0.0  #: σ_b, m
    bias_tau: float = 10.0  #: τ, s
    white: float = 1.0  #: the white range σ as a share of the profile's
    scale_sd: float = 0.0  #: σ_ε
    motion: float = 1.0  #: the profile's motion σ times this (1/c undoes its NEES scale)

    def label(self) -> str:
        parts = []
        if self.bias_sd:
            parts.append(f"bias σ {self.bias_sd} m τ {self.bias_tau:g} s white ×{self.white}")
        if self.scale_sd:
            parts.append(f"scale σ {self.scale_sd}")
        if self.motion != 1.0:
            parts.append(f"motion σ ×{self.motion}")
        return ", ".join(parts) or "none (the shipped filter)"


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


class DenseOc:
    """A dense OC-EKF over [x, y, θ, (ε), (mx, my, (b)) …] (docs/estimator.md's OC)."""

    def __init__(self, noise: NoiseModel, gate: float, extra: Extra) -> None:
        self.noise, self.gate, self.extra = noise, gate, extra
        self.base = 4 if extra.scale_sd else 3
        self.block = 3 if extra.bias_sd else 2
        size = self.base + self.block * CAPACITY
        self.x, self.P = np.zeros(size), np.zeros((size, size))
        if extra.scale_sd:
            self.P[3, 3] = extra.scale_sd ** 2
        self.n = self.base
        self.index: dict[int, int] = {}  #: landmark id → first row of its block
        self.first: dict[int, np.ndarray] = {}  #: FEJ's first estimates
        self.seen: dict[int, float] = {}  #: when each bias was last brought forward
        self.propagated = np.zeros(2)  #: FEJ's p̂(k|k−1)
        self.gated = 0
        self.parts: list[tuple[float, ...]] = []  #: (ν_r², ν_φ², S_rr, S_φφ, R_rr, R_φφ) a sighting

    @property
    def scale(self) -> float:
        return 1.0 + float(self.x[3]) if self.extra.scale_sd else 1.0

    def predict(self, v: float, w: float, dt: float) -> None:
        x, P, n, th = self.x, self.P, self.n, float(self.x[2])
        nx, ny = x[0] + v * dt * math.cos(th), x[1] + v * dt * math.sin(th)
        dx, dy = nx - self.propagated[0], ny - self.propagated[1]
        F = np.array([[1.0, 0.0, -dy], [0.0, 1.0, dx], [0.0, 0.0, 1.0]])
        Fu = np.array([[dt * math.cos(th), 0.0], [dt * math.sin(th), 0.0], [0.0, dt]])
        x[0], x[1], x[2] = nx, ny, _wrap(th + w * dt)
        P[:3, :n] = F @ P[:3, :n]
        P[:n, :3] = P[:n, :3] @ F.T
        P[:3, :3] += Fu @ np.diag([self.noise.var_v, self.noise.var_w]) @ Fu.T
        self.propagated = x[:2].copy()

    def _bring_bias_forward(self, lid: int, a: int, stamp: float) -> None:
        phi = math.exp(-(stamp - self.seen[lid]) / self.extra.bias_tau)
        self.seen[lid] = stamp
        b, n = a + 2, self.n
        self.x[b] *= phi
        self.P[b, :n] *= phi
        self.P[:n, b] *= phi
        self.P[b, b] += self.extra.bias_sd ** 2 * (1.0 - phi * phi)

    def _range_variance(self, z_range: float, z_bearing: float) -> float:
        var = self.noise.range_variance(z_range, z_bearing)
        return var * self.extra.white ** 2 if self.extra.bias_sd else var

    def update(self, lid: int, z_range: float, z_bearing: float,
               stamp: float) -> tuple[np.ndarray, np.ndarray] | None:
        """One sighting of a mapped landmark; (ν, S) when applied, None when gated."""
        x, P, n, a = self.x, self.P, self.n, self.index[lid]
        if self.extra.bias_sd:
            self._bring_bias_forward(lid, a, stamp)
        dx, dy = x[a] - x[0], x[a + 1] - x[1]
        q = dx * dx + dy * dy
        r = math.sqrt(q)
        bias = float(x[a + 2]) if self.extra.bias_sd else 0.0
        nu = np.array([z_range - (self.scale * r + bias),
                       _wrap(z_bearing - (math.atan2(dy, dx) - x[2]))])
        rows = self._oc_rows(lid, [-dx / r, -dy / r, 0.0, dx / r, dy / r],
                             [dy / q, -dx / q, -1.0, -dy / q, dx / q])
        H = np.zeros((2, n))
        H[0, [0, 1, 2, a, a + 1]] = rows[0] * self.scale
        H[1, [0, 1, 2, a, a + 1]] = rows[1]
        if self.extra.scale_sd:
            H[0, 3] = r
        if self.extra.bias_sd:
            H[0, a + 2] = 1.0
        PHt = P[:n, :n] @ H.T
        R = (self._range_variance(z_range, z_bearing), self.noise.var_b)
        S = H @ PHt + np.diag(R)
        if float(nu @ np.linalg.solve(S, nu)) > self.gate:
            self.gated += 1
            return None
        self.parts.append((nu[0] ** 2, nu[1] ** 2, S[0, 0], S[1, 1], *R))
        K = np.linalg.solve(S, PHt.T).T
        x[:n] += K @ nu
        x[2] = _wrap(float(x[2]))
        P[:n, :n] -= K @ S @ K.T
        P[:n, :n] = 0.5 * (P[:n, :n] + P[:n, :n].T)
        return nu, S

    def _oc_rows(self, lid: int, h0: list[float], h1: list[float]) -> list[np.ndarray]:
        """Each row moved the least that makes it blind to N (docs/estimator.md's h*)."""
        D = self.first[lid] - self.propagated
        u = np.array([D[1] / 2, -D[0] / 2, 1.0, -D[1] / 2, D[0] / 2])
        out = []
        for h in (np.array(h0), np.array(h1)):
            alpha = (h[2] + h[0] * D[1] - h[1] * D[0]) / (1.0 + float(D @ D) / 2)
            out.append(h - alpha * u)
        return out

    def initialise(self, lid: int, z_range: float, z_bearing: float, stamp: float) -> None:
        """A new landmark's block: Gv at FEJ's robot point, Gz, and ∂ℓ/∂ε, ∂ℓ/∂b."""
        x, P, n, a = self.x, self.P, self.n, self.n
        c, s = math.cos(x[2] + z_bearing), math.sin(x[2] + z_bearing)
        rr = z_range / self.scale
        mx, my = x[0] + rr * c, x[1] + rr * s
        G = np.zeros((2, n))
        G[:, :3] = [[1.0, 0.0, -(my - self.propagated[1])], [0.0, 1.0, mx - self.propagated[0]]]
        if self.extra.scale_sd:
            G[:, 3] = [-rr / self.scale * c, -rr / self.scale * s]
        Gz = np.array([[c / self.scale, -rr * s], [s / self.scale, rr * c]])
        R = np.diag([self._range_variance(z_range, z_bearing), self.noise.var_b])
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
        ids = sorted(self.index, key=self.index.__getitem__)
        return np.array(ids), np.array([self.x[self.index[i]:self.index[i] + 2] for i in ids])


def run(robot: int, extra: Extra) -> tuple[Evaluation, float, np.ndarray]:
    """The dense filter over one robot with its left-out profile; (scores, final ε, the
    applied sightings' (ν_r², ν_φ², S_rr, S_φφ, R_rr, R_φφ))."""
    settings = load_settings(EstimatorSettings,
                             REPO / "benchmarks" / "profiles" / f"without-robot{robot}.toml")
    data = load_mrclam(DATA, robot)
    noise = NoiseModel.of(settings)
    noise = replace(noise, var_v=noise.var_v * extra.motion ** 2,
                    var_w=noise.var_w * extra.motion ** 2)
    ekf = DenseOc(noise, settings.innovation_gate_chi2, extra)
    scorer = Scorer(TruthTrack.from_mrclam(data), robot=data.robot)
    for m in data.events(truth=False):
        if isinstance(m, Odometry):
            ekf.predict(m.v, m.w, m.dt)
        else:
            new = []
            for lid, zr, zb in zip(m.ids.tolist(), m.ranges.tolist(), m.bearings.tolist(),
                                   strict=True):
                if lid not in ekf.index:
                    new.append((lid, zr, zb))
                elif (done := ekf.update(lid, zr, zb, m.stamp)) is not None:
                    scorer.add_innovations(done[0][None], done[1][None])
            for lid, zr, zb in new:  # FEJ's and OC's order: after the updates, once
                if lid not in ekf.index:
                    ekf.initialise(lid, zr, zb, m.stamp)
        scorer.add(m.stamp, ekf.x[:3].copy(), ekf.P[:3, :3].copy())
    ids, landmarks = ekf.landmarks()
    return (scorer.finish(ids, landmarks, {"gated": ekf.gated}), ekf.scale - 1.0,
            np.array(ekf.parts))


def nis_windows_out(nis: np.ndarray) -> tuple[float, float]:
    """Shares of the monitor's NIS windows (χ²(2N)/N band) below and above their band."""
    k = nis.size // NIS_WINDOW
    means = nis[:k * NIS_WINDOW].reshape(k, NIS_WINDOW).mean(axis=1)
    dof = 2 * NIS_WINDOW
    lo = chi2.ppf(NIS_SIGNIFICANCE / 2, dof) / NIS_WINDOW
    hi = chi2.ppf(1 - NIS_SIGNIFICANCE / 2, dof) / NIS_WINDOW
    return float(np.mean(means < lo)), float(np.mean(means > hi))


def row(what: str, robot: int, ev: Evaluation, scale: float | None) -> str:
    eps = "" if scale is None else f"{scale:+.4f}"
    below, above = nis_windows_out(ev.nis)
    return (f"{what:<48} robot{robot}  NEES {ev.nees_mean:6.2f}  map {ev.landmark_rmse_rigid:.3f} m"
            f"  NIS {ev.nis_mean:.2f} / {float(np.median(ev.nis)):.2f}"
            f"  windows out {below + above:4.0%} ({below:.0%} below)  ε {eps}")


def similarity_fit(ev: Evaluation) -> tuple[float, float]:
    """(scale, RMSE m) of the final map after the rotation, translation and scale that fit
    it best to the truth (Umeyama): how much of the shape error is a scale."""
    est = ev.landmarks
    true = est + ev.landmark_errors
    X, Y = est - est.mean(0), true - true.mean(0)
    U, S, Vt = np.linalg.svd(X.T @ Y)
    D = np.diag([1.0, float(np.sign(np.linalg.det(Vt.T @ U.T)))])
    R = Vt.T @ D @ U.T
    scale = float((S * np.diag(D)).sum() / (X ** 2).sum())
    fitted = scale * X @ R.T + true.mean(0)
    return scale, float(np.sqrt(np.mean(np.sum((fitted - true) ** 2, axis=1))))


def where_s_comes_from(robot: int, parts: np.ndarray) -> str:
    """Median innovation against median S and R, range and bearing, as σ (the NIS is low
    where the innovations are smaller than S; which part of S makes it large)."""
    nu_r, nu_b, s_r, s_b, r_r, r_b = np.sqrt(np.median(parts, axis=0)).tolist()
    return (f"{'':<48} robot{robot}  range: |ν| {nu_r:.3f} m, √S {s_r:.3f}, √R {r_r:.3f};"
            f"  bearing: |ν| {math.degrees(nu_b):.2f}°, √S {math.degrees(s_b):.2f}°,"
            f" √R {math.degrees(r_b):.2f}°  (medians)")


def _job(args: tuple[int, Extra]) -> str:
    robot, extra = args
    ev, scale, parts = run(robot, extra)
    line = row(extra.label(), robot, ev, scale if extra.scale_sd else None)
    if extra.bias_sd or extra.scale_sd:
        return line
    scale, rmse = similarity_fit(ev)
    return (f"{line}\n{where_s_comes_from(robot, parts)}\n{'':<48} robot{robot}  map after a "
            f"similarity fit: scale {scale:.3f}, RMSE {rmse:.3f} m")


def _shipped(robot: int) -> str:
    settings = load_settings(EstimatorSettings,
                             REPO / "benchmarks" / "profiles" / f"without-robot{robot}.toml")
    return row("the shipped Estimator (reference)", robot,
               evaluate(load_mrclam(DATA, robot), settings), None)


EXTRAS = (Extra(), Extra(motion=0.44),
          Extra(bias_sd=0.12, bias_tau=5.0, white=0.35),
          Extra(bias_sd=0.12, bias_tau=20.0, white=0.35),
          Extra(bias_sd=0.08, bias_tau=5.0, white=0.25),
          Extra(scale_sd=0.01), Extra(scale_sd=0.02))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true",
                        help="also run the shipped Estimator on each robot (the reference)")
    args = parser.parse_args(argv)
    jobs = [(robot, extra) for extra in EXTRAS for robot in ROBOTS]
    with ProcessPoolExecutor(2) as pool:
        if args.check:
            for line in pool.map(_shipped, ROBOTS):
                print(line, flush=True)
        for line in pool.map(_job, jobs):
            print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
