"""A simulated run made in the test: a robot driving a loop among 15 landmarks in three
clusters, a forward range-bearing sensor, noise from a seeded RNG. Its inputs are what a
third-party driver publishes; the dense oracle applied to them in order is the answer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from kit_ekf import DenseEkf, wrap

#: the noise the estimator is told (flags) and the simulation draws from
SIGMA = {"sigma_v": 0.05, "sigma_w": 0.05, "sigma_range": 0.05, "sigma_bearing": 0.02}
DT = 0.1
MAX_RANGE = 3.0
MIN_RANGE = 0.3  #: nearer landmarks are not seen (a noisy range stays positive)
FOV = math.pi / 2  #: half the field of view: bearings within ±90°


def estimator_flags() -> list[str]:
    """The estimator's settings the oracle assumes: the noise above, the innovation gate
    off (all flags of ``slamlens estimator``, docs/cli.md)."""
    flags = []
    for name, value in SIGMA.items():
        flags += [f"--{name.replace('_', '-')}", repr(value)]
    return flags + ["--innovation-gate-chi2", "0"]


@dataclass(frozen=True)
class Input:
    leaf: str  #: "odometry" or "observations"
    stamp: float
    fields: dict[str, Any]  #: dt, v, w — or ids, ranges, bearings (lists)


def landmarks(rng: np.random.Generator) -> tuple[list[int], np.ndarray]:
    centres = np.array([[1.8, 0.6], [0.3, 2.6], [-1.4, 1.0]])
    points = np.concatenate([c + rng.uniform(-0.45, 0.45, size=(5, 2)) for c in centres])
    ids = [int(i) for i in rng.permutation(np.arange(1, 60))[:15]]
    return ids, points


#: every this many steps the sensor sees nothing: an empty batch (k = 0 is a valid input)
BLIND_EVERY = 25


def simulate(seed: int = 7, steps: int = 150) -> list[Input]:
    """``2 × steps`` inputs: per step an odometry message, then an observation batch with
    the same stamp (empty every :data:`BLIND_EVERY` steps)."""
    rng = np.random.default_rng(seed)
    ids, points = landmarks(rng)
    pose = np.zeros(3)
    out: list[Input] = []
    for k in range(1, steps + 1):
        stamp = round(k * DT, 6)
        v_true = 0.3
        w_true = 0.35 + 0.1 * math.sin(k / 15.0)
        pose = np.array([pose[0] + v_true * DT * math.cos(pose[2]),
                         pose[1] + v_true * DT * math.sin(pose[2]),
                         wrap(pose[2] + w_true * DT)])
        out.append(Input("odometry", stamp, {
            "dt": DT, "v": v_true + float(rng.normal(0, SIGMA["sigma_v"])),
            "w": w_true + float(rng.normal(0, SIGMA["sigma_w"]))}))
        seen_ids, ranges, bearings = [], [], []
        for j in rng.permutation(len(ids)):
            dx, dy = points[j] - pose[:2]
            r = math.hypot(dx, dy)
            b = wrap(math.atan2(dy, dx) - pose[2])
            if MIN_RANGE <= r <= MAX_RANGE and abs(b) <= FOV and k % BLIND_EVERY:
                seen_ids.append(ids[j])
                ranges.append(r + float(rng.normal(0, SIGMA["sigma_range"])))
                bearings.append(wrap(b + float(rng.normal(0, SIGMA["sigma_bearing"]))))
        out.append(Input("observations", stamp,
                         {"ids": seen_ids, "ranges": ranges, "bearings": bearings}))
    return out


def oracle(inputs: list[Input], make: type[DenseEkf] = DenseEkf) -> DenseEkf:
    """The dense EKF (or ``make``'s) after every input, in order."""
    ekf = make(**SIGMA)
    for item in inputs:
        apply(ekf, item)
    return ekf


def apply(ekf: DenseEkf, item: Input) -> None:
    """One input into the dense filter."""
    if item.leaf == "odometry":
        ekf.predict(item.fields["v"], item.fields["w"], item.fields["dt"])
    else:
        ekf.observe(item.fields["ids"], item.fields["ranges"], item.fields["bearings"])
