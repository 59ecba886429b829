"""Settings of ``slamlens registration`` and ``slamlens calibrate``: one frozen dataclass each.

Every field is a TOML key of ``--config FILE`` (see deploy/camera_overhead.toml) and a flag
over it (:func:`slamlens.common.config.setting`; docs/cli.md lists them all). Lengths in metres,
angles in degrees, rates in Hz.
"""

from __future__ import annotations

from dataclasses import dataclass

from slamlens.common.config import setting
from slamlens.common.errors import ConfigError
from slamlens.common.keys import check_name

MODES = ("overhead", "head-mounted")
DETECTORS = ("opencv", "apriltag3")
POSE_SOURCES = ("board", "tracker")

_CAMERA = "camera and marker"
_REGISTER = "registration"
_SYNTHETIC = "synthetic camera"
_BROWSER = "browser cameras"


@dataclass(frozen=True)
class RegistrationSettings:
    """``slamlens registration``: camera capture and registration (docs/registration.md)."""

    camera: str = setting("overhead", doc="camera name (a key segment); stereo adds -left / "
                                          "-right", group=_CAMERA)
    robot: str = setting("robot1", doc="robot whose marker registers the map frame",
                         group=_CAMERA)
    source: str = setting("synthetic", doc="a device index (\"0\"), a video file, a stream URL "
                                           "(http://…, rtsp://…), a folder of images, "
                                           "synthetic, or browser: every camera C or C-… whose "
                                           "frames a viewer's /ar page sends "
                                           "(slamlens/camera/C/capture)", group=_CAMERA)
    calibration: str = setting("", doc="OpenCV calibration YAML; empty = the synthetic "
                                       "camera's own (synthetic source only). Browser "
                                       "cameras: a file for all, or a folder of CAMERA.yml; "
                                       "without one, the default phone model",
                               metavar="FILE.yml", group=_CAMERA)
    dictionary: str = setting("apriltag_36h11", doc="robot (and board) marker dictionary",
                              group=_CAMERA)
    detector: str = setting(
        "opencv", doc="marker detector: opencv (ArUco, every dictionary) or apriltag3 (the "
                      "AprilTag 3 C library, pupil-apriltags: apriltag_16h5, _25h9, _36h11; "
                      "finds more small tags, ~6x the CPU; docs/registration_vision.md)",
        choices=DETECTORS, group=_CAMERA)
    marker_id: int = setting(0, doc="the robot's marker id", min=0, group=_CAMERA)
    marker_size: float = setting(0.2, doc="marker black square side", unit="m", min=1e-3,
                                 group=_CAMERA)
    marker_offset: tuple[float, ...] = setting(
        (0.0, 0.0, 0.2), doc="marker centre in the robot frame, m (protocol.md: flat, face up, "
                             "x = robot forward)", metavar="X,Y,Z", group=_CAMERA)
    mode: str = setting("overhead", doc="overhead (a fixed camera) or head-mounted (moving)",
                        choices=MODES, group=_CAMERA)
    camera_pose_source: str = setting(
        "board", doc="head-mounted: where the camera pose comes from — the marker board in "
                     "view, or an external tracker publishing CameraPose on "
                     "slamlens/camera/{camera}/pose", choices=POSE_SOURCES, group=_CAMERA)
    board: str = setting("", doc="world marker board TOML (services/registration/board.py); "
                                 "empty = the default board", metavar="FILE.toml",
                         group=_CAMERA)
    stereo_baseline: float = setting(0.0, doc="run cameras C-left and C-right this far apart "
                                              "(synthetic source); 0 = mono", unit="m",
                                     min=0.0, metavar="B", group=_CAMERA)
    fps: float = setting(30.0, doc="frame rate of files and the synthetic camera", unit="Hz",
                         min=0.1, group=_CAMERA)
    jpeg_quality: int = setting(80, doc="JPEG quality of published frames", min=1, max=100,
                                group=_CAMERA)
    detect_full_every: int = setting(
        15, doc="a fixed camera looks over the whole image every this many frames and, in "
                "between, only around the markers of the last frame (the same detections: "
                "docs/registration.md, \"Detection windows\"); 1 = every frame whole",
        min=1, group=_CAMERA)
    detect_full_every_moving: int = setting(
        3, doc="as --detect-full-every, for a head-mounted camera (markers come into its "
               "view all the time: a new one is found at most this many frames later); "
               "1 = every frame whole", min=1, group=_CAMERA)
    fourcc: str = setting("", doc="a USB camera's pixel format, four characters (MJPG: most "
                                  "give 1280x720 at 30 Hz only compressed); empty = its "
                                  "default", metavar="CODE", group=_CAMERA)
    buffer_size: int = setting(0, doc="frames a USB camera's driver queues (1: always the "
                                      "newest frame); 0 = its default", min=0,
                               group=_CAMERA)
    stall_s: float = setting(5.0, doc="a camera or stream that delivers no frame this long "
                                      "has stalled: it is reopened (with back-off)",
                             unit="s", min=0.1, group=_CAMERA)
    loop: bool = setting(False, doc="replay a video file / image folder from the start when "
                                    "it ends", group=_CAMERA)
    register_frames: int = setting(5, doc="frames averaged for a registration (the robot "
                                          "must stand still at the map origin)", min=1,
                                   group=_REGISTER)
    still_tolerance_m: float = setting(0.01, doc="a sample further than this from the first "
                                                 "one means the robot moved: stop averaging",
                                       unit="m", min=0.0, group=_REGISTER)
    still_tolerance_deg: float = setting(1.0, doc="the same for the turn", unit="deg",
                                         min=0.0, group=_REGISTER)
    max_reprojection_error_px: float = setting(
        2.0, doc="marker poses with a larger RMS reprojection error are not used", unit="px",
        min=0.0, group=_REGISTER)
    max_reregister_move_m: float = setting(
        0.05, doc="a requested re-registration that would move the map origin further than "
                  "this while the robot is not at its map origin is refused", unit="m",
        min=0.0, group=_CAMERA)
    max_reregister_turn_deg: float = setting(
        5.0, doc="… or turn the map frame more than this", unit="deg", min=0.0, group=_CAMERA)
    origin_tolerance_m: float = setting(
        0.05, doc="the robot counts as at its map origin when its estimate is this close to "
                  "(0, 0) (and within max_reregister_turn_deg of heading 0)", unit="m",
        min=0.0, group=_CAMERA)
    registration_period_s: float = setting(1.0, doc="re-publish the registration this often",
                                           unit="s", min=0.05, group=_REGISTER)
    reconnect_max_s: float = setting(5.0, doc="longest wait between reconnection attempts of "
                                              "a lost camera", unit="s", min=0.1,
                                     group=_REGISTER)
    # -- browser cameras (--source browser) -------------------------------------------
    browser_hfov: float = setting(
        67.0, doc="horizontal field of view of the default camera model of a browser "
                  "camera without a calibration (a phone's main camera in 16:9)", unit="deg",
        min=1.0, group=_BROWSER)
    browser_idle_s: float = setting(3.0, doc="a browser camera that sent no frame this long "
                                             "has left: its pipeline is released", unit="s",
                                    min=0.1, group=_BROWSER)
    max_browser_cameras: int = setting(8, doc="browser cameras served at once (more are "
                                              "refused)", min=1, group=_BROWSER)
    max_browser_frame_pixels: int = setting(
        8_294_400, doc="browser frames whose JPEG claims more pixels are refused before "
                       "decoding (3840x2160)", min=1, group=_BROWSER)
    # -- the synthetic camera ----------------------------------------------------------
    width: int = setting(1280, doc="image width (a USB camera is asked for it too)", unit="px",
                         min=16, group=_SYNTHETIC)
    height: int = setting(720, doc="image height (a USB camera is asked for it too)",
                          unit="px", min=16, group=_SYNTHETIC)
    hfov: float = setting(0.0, doc="horizontal field of view; 0 = fit the arena (head-mounted: "
                                   "75°)", unit="deg", min=0.0, group=_SYNTHETIC)
    camera_height: float = setting(3.0, doc="overhead camera height above the arena centre",
                                   unit="m", min=0.1, group=_SYNTHETIC)
    camera_yaw: float = setting(8.0, doc="overhead camera turn about the vertical: a real "
                                         "mount is never exactly square to the map, and the "
                                         "default keeps the marker's edges off the pixel grid",
                                unit="deg", group=_SYNTHETIC)
    arena: tuple[float, ...] = setting((-1.0, -1.0, 2.0, 2.0), doc="arena in the map frame, m",
                                       metavar="XMIN,YMIN,XMAX,YMAX", group=_SYNTHETIC)
    noise: float = setting(2.0, doc="sensor noise σ", unit="grey levels", min=0.0,
                           group=_SYNTHETIC)
    blur: int = setting(3, doc="Gaussian blur kernel; 0 = none", unit="px", min=0,
                        group=_SYNTHETIC)
    gain: float = setting(1.0, doc="brightness gain", min=0.0, group=_SYNTHETIC)
    offset: float = setting(0.0, doc="brightness offset", unit="grey levels",
                            group=_SYNTHETIC)
    gradient: float = setting(0.0, doc="brightness change from the left to the right edge, "
                                       "relative", group=_SYNTHETIC)
    seed: int = setting(0, doc="floor texture and noise seed", group=_SYNTHETIC)
    robot_radius: float = setting(0.25, doc="radius of the drawn robot", unit="m", min=0.01,
                                  group=_SYNTHETIC)
    orbit_radius: float = setting(3.0, doc="head-mounted: radius of the viewer's walk round "
                                           "the arena", unit="m", min=0.1, group=_SYNTHETIC)
    orbit_height: float = setting(2.5, doc="head-mounted: eye height", unit="m", min=0.1,
                                  group=_SYNTHETIC)
    orbit_period: float = setting(60.0, doc="head-mounted: time per lap", unit="s", min=0.1,
                                  group=_SYNTHETIC)

    def __post_init__(self) -> None:
        check_name("camera", self.camera)
        check_name("robot", self.robot)
        if len(self.marker_offset) != 3:
            raise ConfigError(f"setting 'marker_offset': expected X,Y,Z, got "
                              f"{list(self.marker_offset)}")
        if len(self.arena) != 4 or self.arena[0] >= self.arena[2] \
                or self.arena[1] >= self.arena[3]:
            raise ConfigError(f"setting 'arena': expected xmin,ymin,xmax,ymax, got "
                              f"{list(self.arena)}")
        if self.hfov >= 180.0 or self.browser_hfov >= 180.0:
            raise ConfigError(f"setting 'hfov' / 'browser_hfov': {self.hfov} / "
                              f"{self.browser_hfov} must be below 180 degrees")
        if not self.source:
            raise ConfigError("setting 'source': empty; give a device index, a file, a "
                              "folder, a URL, 'synthetic' or 'browser'")
        if self.fourcc and (len(self.fourcc) != 4 or not self.fourcc.isascii()):
            raise ConfigError(f"setting 'fourcc': {self.fourcc!r} is not four characters "
                              "(e.g. MJPG, YUYV)")
        if self.stereo_baseline > 0 and self.source != "synthetic":
            raise ConfigError("setting 'stereo_baseline': stereo needs --source synthetic; "
                              "run one service per real camera (names C-left, C-right)")

    @property
    def synthetic(self) -> bool:
        return self.source == "synthetic"

    @property
    def browser(self) -> bool:
        """Frames from browsers through the bus (``--source browser``)."""
        return self.source == "browser"

    def camera_names(self) -> tuple[str, ...]:
        """The camera names this service publishes (one, or a left/right stereo pair)."""
        if self.stereo_baseline > 0:
            return (f"{self.camera}-left", f"{self.camera}-right")
        return (self.camera,)


@dataclass(frozen=True)
class CalibrateSettings:
    """``slamlens calibrate``: camera intrinsics from photos of a ChArUco board."""

    images: tuple[str, ...] = setting((), doc="photos of a ChArUco board", positional=True,
                                      required=True, metavar="IMAGE")
    squares_x: int = setting(5, doc="board squares across")
    squares_y: int = setting(7, doc="board squares down")
    square: float = setting(0.04, doc="square side (> 0)", unit="m", min=0.0)
    marker: float = setting(0.02, doc="marker side (> 0)", unit="m", min=0.0)
    dictionary: str = setting("aruco_6x6_250", doc="board dictionary")
    legacy_pattern: bool = setting(False, doc="the board was laid out by OpenCV < 4.6 with an "
                                              "even number of rows")
    output: str = setting("", doc="calibration YAML to write", short="-o", required=True,
                          metavar="FILE.yml")

    def __post_init__(self) -> None:
        if not (self.square > 0 and self.marker > 0):
            raise ConfigError("calibrate: --square and --marker must be positive")


@dataclass(frozen=True)
class DetectSettings:
    """``slamlens detect``: the fiducial markers in images."""

    images: tuple[str, ...] = setting((), doc="images to look at", positional=True,
                                      required=True, metavar="IMAGE")
    dictionary: str = setting("apriltag_36h11", doc="marker dictionary (a name, or a custom "
                                                    "FILE.yml)")
    detector: str = setting("opencv", doc="opencv or apriltag3 (the AprilTag 3 C library)",
                            choices=DETECTORS)
    json: bool = setting(False, doc="one JSON object per image: {\"image\": PATH, "
                                    "\"detections\": [{\"id\": ID, \"corners\": [[x, y] x4]}]} "
                                    "(pixels, OpenCV's convention: pixel centres at integers; "
                                    "corners top-left, top-right, bottom-right, bottom-left of "
                                    "the marker)")
