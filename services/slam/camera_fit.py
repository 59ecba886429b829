"""Each robot's camera against the ground truth: the calibration a lab would give it.

A profile fitted on several robots holds one noise model for all their cameras; it cannot
hold a camera's *systematic* error. Measured per robot from the same residuals the noise
fit uses (z − h with the truth's pose and landmark, gross errors left out):

* **bearing offset** δ and **bearing scale** s — the least-squares line of the bearing
  error on the measured bearing, z_φ − φ = δ + s·z_φ (the camera's yaw on the robot, its
  field of view); with the truth's turn rate ω, a **latency** column as well (a camera
  reporting a picture τ old reads the bearing of τ·ω ago);
* **range scale** — the median measured / true range.

A camera that differs from the others' median by more than :data:`ODD` (each ≈ 3 cm at
3 m, the arena's ranges) and by more than :data:`SPREAD` scaled median absolute deviations
of the others (an outlier among them, not one of an even spread) is one the lab should
calibrate: a profile fitted on other robots cannot teach it (docs/consistency.md,
"Robot 4's camera": MRCLAM dataset 6's robot 4 is −1.30° and +3.8 % off, and meets the
map target once calibrated).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from slamlens.common.errors import SourceError

#: |bearing error| (rad) and |range error| (m) beyond these are misreads, left out
GROSS_BEARING = 0.3
GROSS_RANGE = 0.5
#: how far from the other cameras' median a camera may be before it is named: bearing
#: offset (rad), bearing scale, range scale − 1 — each ≈ 3 cm at 3 m
ODD = {"offset": math.radians(0.5), "scale": 0.02, "range_scale": 0.01}
#: … and by more than this many of the others' scaled median absolute deviations
SPREAD = 3.0


@dataclass(frozen=True)
class CameraFit:
    """One camera's systematic errors (module docstring)."""

    offset: float  #: bearing offset δ, rad
    scale: float  #: bearing scale s (error per rad of bearing)
    range_scale: float  #: median measured / true range
    sightings: int  #: sightings the fit used
    latency: float | None = None  #: s, when the turn rates were given

    def text(self) -> str:
        """E.g. "bearing −1.28° +3.74%, range ×1.0197"."""
        lag = "" if self.latency is None else f", latency {self.latency * 1e3:.0f} ms"
        return (f"bearing {math.degrees(self.offset):+.2f}° {self.scale:+.2%}, "
                f"range ×{self.range_scale:.4f}{lag}").replace("-", "−")


def fit_camera(bearings: np.ndarray, bearing_errors: np.ndarray, ranges: np.ndarray,
               range_errors: np.ndarray, rates: np.ndarray | None = None) -> CameraFit:
    """The camera of these sightings: measured bearings and ranges, their errors against
    the truth (z − h), and optionally the truth's turn rate at each (rad/s). Fewer than
    three fair sightings: :class:`SourceError`."""
    b, eb = np.asarray(bearings, float), np.asarray(bearing_errors, float)
    r, er = np.asarray(ranges, float), np.asarray(range_errors, float)
    fair = (np.abs(eb) < GROSS_BEARING) & (np.abs(er) < GROSS_RANGE) & (r - er > 0)
    if fair.sum() < 3:
        raise SourceError(f"{int(fair.sum())} fair sightings: too few to fit a camera")
    columns = [np.ones(int(fair.sum())), b[fair]]
    if rates is not None:
        columns.append(np.asarray(rates, float)[fair])
    coef, *_ = np.linalg.lstsq(np.column_stack(columns), eb[fair], rcond=None)
    return CameraFit(offset=float(coef[0]), scale=float(coef[1]),
                     range_scale=float(np.median(r[fair] / (r[fair] - er[fair]))),
                     sightings=int(fair.sum()),
                     latency=None if rates is None else float(coef[2]))


def odd_cameras(cameras: Mapping[int, CameraFit]) -> dict[int, list[str]]:
    """Robots whose camera is further from the *other* cameras' median than :data:`ODD` and
    than :data:`SPREAD` of their scaled MADs, with what differs ("bearing offset", …); needs
    three cameras or more (with two, neither can be told apart from the other)."""
    if len(cameras) < 3:
        return {}
    out: dict[int, list[str]] = {}
    names = {"offset": "bearing offset", "scale": "bearing scale",
             "range_scale": "range scale"}
    for k, cam in cameras.items():
        others = [c for j, c in cameras.items() if j != k]
        odd = []
        for key, limit in ODD.items():
            values = np.array([getattr(c, key) for c in others])
            centre = float(np.median(values))
            spread = SPREAD * 1.4826 * float(np.median(np.abs(values - centre)))
            if abs(getattr(cam, key) - centre) > max(limit, spread):
                odd.append(names[key])
        if odd:
            out[k] = odd
    return out
