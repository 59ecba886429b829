"""Settings of ``slamlens registration``: one frozen dataclass, a TOML file then flags.

Every field is a TOML key of ``--config FILE`` (see deploy/camera_overhead.toml); the flags
of SPEC §9 override them. Lengths in metres, angles in degrees, rates in Hz.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from common.errors import ConfigError
from common.keys import check_name

MODES = ("overhead", "head-mounted")
POSE_SOURCES = ("board", "tracker")


@dataclass(frozen=True)
class RegistrationSettings:
    """``slamlens registration`` settings (TOML keys = these names)."""

    camera: str = "overhead"  #: camera name (key segment); stereo adds -left / -right
    robot: str = "robot1"  #: robot whose marker registers the map frame
    #: a device index ("0"), a video file, a stream URL, a folder of images, or "synthetic"
    source: str = "synthetic"
    #: OpenCV calibration YAML; empty = the synthetic camera's own (synthetic source only)
    calibration: str = ""
    dictionary: str = "apriltag_36h11"  #: robot (and board) marker dictionary
    marker_id: int = field(default=0, metadata={"min": 0})
    marker_size: float = field(default=0.2, metadata={"min": 1e-3})  #: black square side, m
    #: marker centre in the robot frame, m (SPEC §3: flat, face up, x = robot forward)
    marker_offset: tuple[float, ...] = (0.0, 0.0, 0.2)
    mode: str = field(default="overhead", metadata={"choices": MODES})
    #: head-mounted: where the camera pose comes from — the marker board in view, or an
    #: external tracker publishing CameraPose on slamlens/camera/{camera}/pose
    camera_pose_source: str = field(default="board", metadata={"choices": POSE_SOURCES})
    board: str = ""  #: board TOML (services.registration.board); empty = default board
    stereo_baseline: float = field(default=0.0, metadata={"min": 0.0})  #: m; 0 = mono
    fps: float = field(default=30.0, metadata={"min": 0.1})  #: frame rate (files, synthetic)
    jpeg_quality: int = field(default=80, metadata={"min": 1})
    loop: bool = False  #: replay a video file / image folder from the start when it ends
    #: frames averaged for a registration (the robot must stand still at the map origin)
    register_frames: int = field(default=5, metadata={"min": 1})
    #: a sample further than this from the first one means the robot moved: stop averaging
    still_tolerance_m: float = field(default=0.01, metadata={"min": 0.0})
    still_tolerance_deg: float = field(default=1.0, metadata={"min": 0.0})
    #: marker poses with a larger RMS reprojection error are not used
    max_reprojection_error_px: float = field(default=2.0, metadata={"min": 0.0})
    registration_period_s: float = field(default=1.0, metadata={"min": 0.05})  #: re-publish
    reconnect_max_s: float = field(default=5.0, metadata={"min": 0.1})  #: back-off cap
    # -- the synthetic camera ----------------------------------------------------------
    width: int = field(default=1280, metadata={"min": 16})
    height: int = field(default=720, metadata={"min": 16})
    hfov: float = field(default=0.0, metadata={"min": 0.0})  #: deg; 0 = fit the arena
    camera_height: float = field(default=3.0, metadata={"min": 0.1})  #: overhead camera, m
    #: overhead camera turned about the vertical, deg: a real mount is never exactly square
    #: to the map, and the default keeps the marker's edges off the pixel grid
    camera_yaw: float = 8.0
    arena: tuple[float, ...] = (-1.0, -1.0, 2.0, 2.0)  #: xmin, ymin, xmax, ymax (map frame)
    noise: float = field(default=2.0, metadata={"min": 0.0})  #: sensor noise σ, grey levels
    blur: int = field(default=3, metadata={"min": 0})  #: Gaussian blur kernel, px (0 = none)
    gain: float = field(default=1.0, metadata={"min": 0.0})
    offset: float = 0.0  #: brightness offset, grey levels
    gradient: float = 0.0  #: brightness change left → right edge, relative
    seed: int = 0
    robot_radius: float = field(default=0.25, metadata={"min": 0.01})
    orbit_radius: float = field(default=3.0, metadata={"min": 0.1})  #: head-mounted path, m
    orbit_height: float = field(default=2.5, metadata={"min": 0.1})  #: eye height, m
    orbit_period: float = field(default=60.0, metadata={"min": 0.1})  #: s per lap

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
        if not 1 <= self.jpeg_quality <= 100:
            raise ConfigError(f"setting 'jpeg_quality': {self.jpeg_quality} is not in 1..100")
        if self.hfov >= 180.0:
            raise ConfigError(f"setting 'hfov': {self.hfov} must be below 180 degrees")
        if not self.source:
            raise ConfigError("setting 'source': empty; give a device index, a file, a "
                              "folder, a URL or 'synthetic'")
        if self.stereo_baseline > 0 and self.source != "synthetic":
            raise ConfigError("setting 'stereo_baseline': stereo needs --source synthetic; "
                              "run one service per real camera (names C-left, C-right)")

    @property
    def synthetic(self) -> bool:
        return self.source == "synthetic"

    def camera_names(self) -> tuple[str, ...]:
        """The camera names this service publishes (one, or a left/right stereo pair)."""
        if self.stereo_baseline > 0:
            return (f"{self.camera}-left", f"{self.camera}-right")
        return (self.camera,)
