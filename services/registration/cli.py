"""Commands ``slamlens registration`` (camera capture + fiducial registration) and
``slamlens calibrate`` (intrinsics from ChArUco board photos).

Settings: :mod:`services.registration.settings` (flags built from them by services/cli.py).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from common.cli import bus_settings, keys_from, log_flags, setup_logging, stop_event
from common.config import settings_from_args
from common.errors import ConfigError
from common.session import open_bus
from services.registration.settings import CalibrateSettings, RegistrationSettings

log = logging.getLogger("slamlens")


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, command)
    if command == "calibrate":
        return _run_calibrate(args)
    return _run_registration(args)


def _run_registration(args: argparse.Namespace) -> int:
    import cv2

    from services.registration.assemble import build_service

    if not log_flags(args).verbose:  # our own one-line messages say when a camera is missing
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    settings = settings_from_args(RegistrationSettings, args)
    keys = keys_from(args)
    stop = stop_event()
    bus = open_bus(bus_settings(args))
    try:
        service = build_service(bus, keys, settings)
        names = ", ".join(p.camera for p in service.pipelines)
        log.info("camera %s (%s, %s) registering robot %s with marker %d", names,
                 settings.source, settings.mode, settings.robot, settings.marker_id)
        print(f"registration ready: {names}", flush=True)
        service.run(stop)
        print(f"registration stopped: {json.dumps(service.summary())}", flush=True)
    finally:
        bus.close()
    return 0


def _run_calibrate(args: argparse.Namespace) -> int:
    import cv2

    from services.registration.calibrate import calibrate_charuco
    from services.registration.calibration import save_calibration

    s = settings_from_args(CalibrateSettings, args)
    images = []
    for name in s.images:
        # check first: OpenCV would add its own warning line for a missing file
        image = cv2.imread(name, cv2.IMREAD_COLOR) if Path(name).is_file() else None
        if image is None:
            raise ConfigError(f"calibrate: cannot read image {name}")
        images.append(image)
    calib, rms = calibrate_charuco(images, squares_x=s.squares_x, squares_y=s.squares_y,
                                   square_m=s.square, marker_m=s.marker,
                                   dictionary=s.dictionary, legacy_pattern=s.legacy_pattern)
    output = Path(s.output)
    save_calibration(output, calib, rms=rms)
    print(f"RMS reprojection error {rms:.4f} px from {len(images)} images; "
          f"fx {calib.fx:.2f} fy {calib.fy:.2f} cx {calib.cx:.2f} cy {calib.cy:.2f}; "
          f"written to {output}", flush=True)
    return 0
