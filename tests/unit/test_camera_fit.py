"""Each robot's camera against the truth (services/slam/camera_fit.py): a simulated camera's
known offset, bearing scale, latency and range scale recovered through misreads; the odd
camera named among several, none in an even spread and none among two; the profile's header
saying both."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from slamlens.common.errors import SourceError
from slamlens.services.slam import tuning
from slamlens.services.slam.camera_fit import CameraFit, fit_camera, odd_cameras
from slamlens.services.slam.mrclam import load_mrclam

SMALL = Path(__file__).resolve().parents[1] / "fixtures" / "mrclam_small"


def simulated(rng: np.random.Generator, n: int, *, offset: float, scale: float,
              latency: float, range_scale: float) -> tuple[np.ndarray, ...]:
    """(measured bearings, bearing errors, measured ranges, range errors, turn rates) of a
    camera with those errors, white noise and 3 % misreads."""
    true_b, true_r = rng.uniform(-0.5, 0.5, n), rng.uniform(0.5, 4.5, n)
    rate = rng.normal(0.0, 0.3, n)
    b = (1 + scale) * true_b + offset + latency * rate + rng.normal(0.0, 0.01, n)
    r = range_scale * true_r + rng.normal(0.0, 0.05, n)
    misread = rng.random(n) < 0.03
    b[misread] += rng.choice([-1.0, 1.0], misread.sum()) * rng.uniform(0.4, 3.0, misread.sum())
    r[misread] += rng.uniform(0.6, 2.0, misread.sum())
    # the errors as the fit sees them: z − h, h from the truth; the line is on the measured b
    return b, b - true_b, r, r - true_r, rate


def test_a_simulated_cameras_errors_are_recovered_through_misreads() -> None:
    rng = np.random.default_rng(7)
    b, eb, r, er, rate = simulated(rng, 4000, offset=-0.0227, scale=0.038, latency=0.035,
                                   range_scale=1.02)
    cam = fit_camera(b, eb, r, er, rates=rate)
    # z_φ − φ = δ + s·φ + τω with φ = (z_φ − δ − τω)/(1 + s): on the measured bearing the
    # line's slope is s/(1 + s) and its offset δ/(1 + s) (the bearing noise, in both z_φ and
    # the error, adds var(noise)/var(z_φ) ≈ 0.001 to the slope)
    assert cam.offset == pytest.approx(-0.0227 / 1.038, abs=1e-3)
    assert cam.scale == pytest.approx(0.038 / 1.038, abs=2e-3)
    assert cam.latency == pytest.approx(0.035 / 1.038, abs=3e-3)
    assert cam.range_scale == pytest.approx(1.02, abs=3e-3)
    assert 0.95 * 4000 < cam.sightings < 0.99 * 4000  # the misreads left out
    plain = fit_camera(b, eb, r, er)
    assert plain.latency is None and "latency" not in plain.text()
    assert re.fullmatch(r"bearing −1\.2\d° \+3\.\d\d%, range ×1\.0\d{3}, latency 3\d ms",
                        cam.text()), cam.text()


def test_too_few_fair_sightings_is_a_clear_error() -> None:
    with pytest.raises(SourceError, match="too few"):
        fit_camera(np.zeros(2), np.zeros(2), np.ones(2), np.zeros(2))


def camera(offset_deg: float = 0.0, scale: float = 0.0, range_scale: float = 1.0) -> CameraFit:
    return CameraFit(math.radians(offset_deg), scale, range_scale, sightings=1000)


def test_the_odd_camera_is_named_with_what_differs() -> None:
    fits = {1: camera(0.1, -0.01, 1.005), 2: camera(-0.1, 0.005, 1.0), 3: camera(0.0, 0.0, 0.998),
            4: camera(-1.3, 0.038, 1.02)}
    assert odd_cameras(fits) == {4: ["bearing offset", "bearing scale", "range scale"]}
    fits[4] = camera(0.4, 0.015, 1.008)  # each within its bound (0.5°, 2 %, 1 %)
    assert odd_cameras(fits) == {}
    # an even spread of range scales, 2.4 % from end to end: no one camera stands out
    even = {k: camera(range_scale=s) for k, s in enumerate((0.995, 1.002, 1.011, 1.019))}
    assert odd_cameras(even) == {}
    even[4] = camera(range_scale=1.06)  # … until one does
    assert odd_cameras(even) == {4: ["range scale"]}
    # two cameras: neither can be told apart from the other
    assert odd_cameras({1: camera(), 2: camera(-3.0)}) == {}


def test_the_profile_header_lists_the_cameras_and_the_one_to_calibrate() -> None:
    run = load_mrclam(SMALL, 1)
    fit = tuning.fit_noise([run])
    assert set(fit.cameras) == {1} and fit.cameras[1].sightings > 50
    lines = tuning.camera_lines({1: fit.cameras[1], 2: fit.cameras[1], 3: fit.cameras[1],
                                 4: camera(-1.3, 0.038, fit.cameras[1].range_scale)})
    assert lines[0].startswith("cameras against the truth") and "robot4 bearing −1.30°" in lines[0]
    assert lines[1:] == ["robot4's camera differs from the others' (bearing offset, bearing "
                         "scale): calibrate it — a profile fitted on other robots cannot hold "
                         "that (docs/estimator.md)"]
