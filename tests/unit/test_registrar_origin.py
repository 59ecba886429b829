"""A new map registered from the remembered frame nearest its origin instant."""

from __future__ import annotations

import math

import numpy as np

from slamlens.common.geometry import T_from_pose2
from slamlens.services.registration.calibration import CameraCalibration
from slamlens.services.registration.tracking import Registrar, RegistrarSettings, frame_change


def _registrar() -> Registrar:
    calib = CameraCalibration(K=np.array([[800.0, 0, 640], [0, 800.0, 360], [0, 0, 1]]),
                              dist=np.zeros(5), width=1280, height=720)
    return Registrar(RegistrarSettings(marker_id=0, marker_size_m=0.2,
                                       marker_offset_xyz=(0.0, 0.0, 0.2)), calib)


def test_frame_change_measures_translation_and_turn() -> None:
    a = T_from_pose2(np.array([0.0, 0.0, 0.0]))
    b = T_from_pose2(np.array([0.3, 0.4, math.radians(30)]))
    change = frame_change(a, b)
    assert math.isclose(change.moved_m, 0.5) and math.isclose(change.moved_deg, 30.0)


def test_register_at_takes_the_nearest_frame_within_tolerance() -> None:
    r = _registrar()
    r.T_anchor_from_map = T_from_pose2(np.zeros(3))
    for k in range(10):  # the robot drives along x at 0.1 m per frame (0.05 s apart)
        r._history.append((0.05 * k, T_from_pose2(np.array([0.1 * k, 0.0, 0.0]))))
    assert r.register_at(10.0, tolerance_s=0.1) is None  # no frame of that instant
    change = r.register_at(0.21, tolerance_s=0.1)
    assert change is not None and math.isclose(change.moved_m, 0.4)
    assert r.T_anchor_from_map is not None and r.stamp == 0.2
    np.testing.assert_allclose(r.T_anchor_from_map[:3, 3], [0.4, 0.0, 0.0])
    assert r.history_span == (0.0, 0.45)
