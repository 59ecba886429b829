"""Commands ``slamlens registration`` (camera capture + fiducial registration) and
``slamlens calibrate`` (intrinsics from ChArUco board photos)."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

from common.cli import add_common_flags, bus_settings, keys_from, setup_logging, stop_event
from common.config import load_settings
from common.errors import ConfigError
from common.session import open_bus

log = logging.getLogger("slamlens")

#: flags that override RegistrationSettings fields of the same name
_REGISTRATION_FLAGS = (
    "camera", "robot", "source", "calibration", "dictionary", "marker_id", "marker_size",
    "marker_offset", "mode", "camera_pose_source", "board", "stereo_baseline", "fps",
    "jpeg_quality", "loop", "register_frames", "width", "height", "hfov", "camera_height",
    "camera_yaw", "arena", "noise", "blur", "gain", "offset", "gradient", "seed")


def add_arguments(command: str, parser: argparse.ArgumentParser) -> None:
    if command == "calibrate":
        _add_calibrate_arguments(parser)
        return
    add_common_flags(parser)
    g = parser.add_argument_group("camera and marker")
    g.add_argument("--camera", help="camera name (default overhead)")
    g.add_argument("--robot", help="robot name (default robot1)")
    g.add_argument("--source", help="device index, video file, image folder, stream URL or "
                   "'synthetic' (default)")
    g.add_argument("--calibration", metavar="FILE.yml",
                   help="OpenCV calibration YAML (synthetic: its own by default)")
    g.add_argument("--dictionary", help="marker dictionary (default apriltag_36h11)")
    g.add_argument("--marker-id", type=int, help="the robot's marker id (default 0)")
    g.add_argument("--marker-size", type=float, help="marker black square side, m (0.2)")
    g.add_argument("--marker-offset", metavar="X,Y,Z",
                   help="marker centre in the robot frame, m (default 0,0,0.2)")
    g.add_argument("--mode", help="overhead (fixed camera) or head-mounted (moving)")
    g.add_argument("--camera-pose-source", help="head-mounted: board (markers in view) or "
                   "tracker (CameraPose on slamlens/camera/C/pose)")
    g.add_argument("--board", metavar="FILE.toml", help="world marker board (head-mounted)")
    g.add_argument("--stereo-baseline", type=float, metavar="B",
                   help="run cameras C-left and C-right B metres apart (synthetic)")
    g.add_argument("--fps", type=float, help="frame rate of files and synthetic (30)")
    g.add_argument("--jpeg-quality", type=int, help="JPEG quality of published frames (80)")
    g.add_argument("--loop", action="store_true", default=None,
                   help="replay a video file or image folder when it ends")
    g.add_argument("--register-frames", type=int, help="frames averaged per registration (5)")
    s = parser.add_argument_group("synthetic camera")
    s.add_argument("--width", type=int, help="pixels (1280)")
    s.add_argument("--height", type=int, help="pixels (720)")
    s.add_argument("--hfov", type=float, help="horizontal field of view, deg (0 = fit arena)")
    s.add_argument("--camera-height", type=float, help="overhead camera height, m (3)")
    s.add_argument("--camera-yaw", type=float, help="overhead camera turn about the "
                   "vertical, deg (8)")
    s.add_argument("--arena", metavar="XMIN,YMIN,XMAX,YMAX", help="arena in the map frame")
    s.add_argument("--noise", type=float, help="sensor noise σ, grey levels (2)")
    s.add_argument("--blur", type=int, help="Gaussian blur kernel, px (3; 0 = none)")
    s.add_argument("--gain", type=float, help="brightness gain (1)")
    s.add_argument("--offset", type=float, help="brightness offset, grey levels (0)")
    s.add_argument("--gradient", type=float, help="brightness change left→right (0)")
    s.add_argument("--seed", type=int, help="floor texture and noise seed (0)")


def _add_calibrate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+", help="photos of a ChArUco board")
    parser.add_argument("--squares-x", type=int, default=5, help="squares across (5)")
    parser.add_argument("--squares-y", type=int, default=7, help="squares down (7)")
    parser.add_argument("--square", type=float, default=0.04, help="square side, m (0.04)")
    parser.add_argument("--marker", type=float, default=0.02, help="marker side, m (0.02)")
    parser.add_argument("--dictionary", default="aruco_6x6_250",
                        help="board dictionary (aruco_6x6_250)")
    parser.add_argument("--legacy-pattern", action="store_true",
                        help="boards laid out by OpenCV < 4.6 with an even number of rows")
    parser.add_argument("--output", "-o", required=True, help="calibration YAML to write")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging")
    parser.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, command)
    if command == "calibrate":
        return _run_calibrate(args)
    return _run_registration(args)


def registration_settings(args: argparse.Namespace) -> Any:
    from services.registration.settings import RegistrationSettings

    overrides = {name: getattr(args, name, None) for name in _REGISTRATION_FLAGS}
    return load_settings(RegistrationSettings, args.config, overrides)


def _run_registration(args: argparse.Namespace) -> int:
    import cv2

    from services.registration.assemble import build_service

    if not args.verbose:  # our own one-line messages say when a camera is missing
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    settings = registration_settings(args)
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
        for p in service.pipelines:
            log.info("camera %s stopped: %d frames published, %d registrations, %d tracked",
                     p.camera, p.stats.published, p.stats.registrations, p.stats.tracked)
    finally:
        bus.close()
    return 0


def _run_calibrate(args: argparse.Namespace) -> int:
    import cv2

    from services.registration.calibrate import calibrate_charuco
    from services.registration.calibration import save_calibration

    images = []
    for name in args.images:
        # check first: OpenCV would add its own warning line for a missing file
        image = cv2.imread(name, cv2.IMREAD_COLOR) if Path(name).is_file() else None
        if image is None:
            raise ConfigError(f"calibrate: cannot read image {name}")
        images.append(image)
    if args.square <= 0 or args.marker <= 0:
        raise ConfigError("calibrate: --square and --marker must be positive")
    calib, rms = calibrate_charuco(images, squares_x=args.squares_x, squares_y=args.squares_y,
                                   square_m=args.square, marker_m=args.marker,
                                   dictionary=args.dictionary,
                                   legacy_pattern=args.legacy_pattern)
    output = Path(args.output)
    save_calibration(output, calib, rms=rms)
    print(f"RMS reprojection error {rms:.4f} px from {len(images)} images; "
          f"fx {calib.fx:.2f} fy {calib.fy:.2f} cx {calib.cx:.2f} cy {calib.cy:.2f}; "
          f"written to {output}", flush=True)
    return 0
