"""Commands ``slamlens registration`` (camera capture + fiducial registration) and
``slamlens calibrate`` (intrinsics from ChArUco board photos).

Settings: :mod:`slamlens.services.registration.settings` (flags built from them by
services/commands/cli.py).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from slamlens.common.cli import command_bus, keys_from, log_flags, setup_logging, stop_event
from slamlens.common.config import settings_from_args
from slamlens.common.errors import ConfigError
from slamlens.common.status import Report, announce
from slamlens.services.registration.settings import (
    CalibrateSettings,
    DetectSettings,
    RegistrationSettings,
)

log = logging.getLogger("slamlens")


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, command)
    if command == "calibrate":
        return _run_calibrate(args)
    if command == "detect":
        return _run_detect(args)
    return _run_registration(args)


def _run_registration(args: argparse.Namespace) -> int:
    import cv2

    from slamlens.services.registration.assemble import build_service

    if not log_flags(args).verbose:  # our own one-line messages say when a camera is missing
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    settings = settings_from_args(RegistrationSettings, args)
    keys = keys_from(args)
    # a missing --source file or --calibration is said before the network is tried
    check_inputs(settings)
    stop = stop_event()
    bus = command_bus(args)
    try:
        service = build_service(bus, keys, settings)
        names = ", ".join(p.camera for p in service.pipelines)

        def status() -> Report:
            pipes = service.pipelines
            states = sorted({p.status or "starting" for p in pipes})
            return Report(state=", ".join(states), counts={
                "frames": float(sum(p.stats.published for p in pipes)),
                "registrations": float(sum(p.stats.registrations for p in pipes)),
                "tracked": float(sum(p.stats.tracked for p in pipes)),
                "skipped": float(sum(p.stats.skipped for p in pipes)),
                "refused": float(sum(p.stats.refused for p in pipes))},
                epoch=next((p.epoch for p in pipes if p.epoch is not None), None),
                dropped=int(service.summary()["dropped"]))

        announce(bus, args, "registration", status, robot=settings.robot,
                 camera=",".join(p.camera for p in service.pipelines))
        log.info("camera %s (%s, %s) registering robot %s with marker %d", names,
                 settings.source, settings.mode, settings.robot, settings.marker_id)
        print(f"registration ready: {names}", flush=True)
        service.run(stop)
        print(f"registration stopped: {json.dumps(service.summary())}", flush=True)
    finally:
        bus.close()
    return 0


def check_inputs(settings: RegistrationSettings) -> None:
    """The files the settings name exist and read (ConfigError naming the file if not)."""
    from slamlens.services.registration.calibration import load_calibration
    from slamlens.services.registration.sources import open_capture

    if settings.browser:
        if settings.calibration and not Path(settings.calibration).exists():
            raise ConfigError(f"--calibration {settings.calibration}: no such file or folder")
        if settings.calibration and Path(settings.calibration).is_file():
            load_calibration(settings.calibration)
        return
    if not settings.synthetic:
        open_capture(settings.source)  # a missing path fails here; a device is not opened
        if not settings.calibration:
            raise ConfigError("a real camera needs --calibration FILE.yml (see slamlens "
                              "calibrate)")
    if settings.calibration:
        load_calibration(settings.calibration)


def _run_calibrate(args: argparse.Namespace) -> int:
    import cv2

    from slamlens.services.registration.calibrate import calibrate_charuco
    from slamlens.services.registration.calibration import save_calibration

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


def _run_detect(args: argparse.Namespace) -> int:
    """``slamlens detect IMAGE…``: per image, the markers found (text, or one JSON object
    per line with ``--json``)."""
    import cv2

    from slamlens.services.registration.apriltag3 import make_detector

    s = settings_from_args(DetectSettings, args)
    detector = make_detector(s.detector, s.dictionary)
    for name in s.images:
        image = cv2.imread(name, cv2.IMREAD_COLOR) if Path(name).is_file() else None
        if image is None:
            raise ConfigError(f"detect: cannot read image {name}")
        found = detector.detect(image)
        if s.json:
            print(json.dumps({"image": name, "detections": [
                {"id": d.marker_id, "corners": [[round(float(x), 3), round(float(y), 3)]
                                                for x, y in d.corners_px]} for d in found]}),
                  flush=True)
            continue
        print(f"{name}: {len(found)} marker{'s' if len(found) != 1 else ''}", flush=True)
        for d in found:
            corners = " ".join(f"({x:.2f}, {y:.2f})" for x, y in d.corners_px)
            print(f"  id {d.marker_id}: {corners}", flush=True)
    return 0
