"""Settings of ``slamlens rerun`` (docs/rerun.md).

One frozen dataclass whose fields are declared once with
:func:`slamlens.common.config.setting` (TOML key, flag, help and docs/cli.md row in one). It
inherits :class:`~slamlens.common.scene3d.SceneSettings` (mode, clustering, glyph), so what the
Rerun picture shows is chosen with the same flags as the Foxglove one.
"""

from __future__ import annotations

from dataclasses import dataclass

from slamlens.common.config import setting
from slamlens.common.errors import ConfigError
from slamlens.common.keys import check_name
from slamlens.common.scene3d import SceneSettings

SOURCES = ("state", "summary")
#: where Rerun's own viewer listens when it is started alone (``rerun``)
DEFAULT_VIEWER_URL = "rerun+http://127.0.0.1:9876/proxy"
_URL_SCHEMES = ("rerun://", "rerun+http://", "rerun+https://")


@dataclass(frozen=True)
class RerunSettings(SceneSettings):
    """``slamlens rerun``: the live picture into Rerun (docs/rerun.md)."""

    robot: str = setting("robot1", doc="robot whose state is shown")
    camera: tuple[str, ...] = setting((), doc="also show this camera: its picture, intrinsics "
                                              "and pose, with the scene projected into it "
                                              "(repeatable)", action="append", metavar="C")
    save: str = setting("", doc="write the recording to this .rrd file (open it with "
                                "`rerun FILE.rrd`)", metavar="FILE.rrd")
    viewer: str = setting("", doc="stream to the Rerun viewer (or gRPC proxy) at this URL; "
                                  "with neither --save nor --serve: "
                                  f"{DEFAULT_VIEWER_URL}, where `rerun` started alone "
                                  "listens", metavar="URL")
    serve: bool = setting(False, doc="host a gRPC server for Rerun viewers to connect to "
                                     "(`rerun --connect URL`; the URL is printed)")
    host: str = setting("127.0.0.1", doc="--serve: address to serve on (loopback unless "
                                         "asked)")
    port: int = setting(9876, doc="--serve: gRPC port", min=1, max=65535)
    serve_memory: str = setting("1GiB", doc="--serve: data kept for viewers that connect "
                                            "late (oldest dropped beyond it; e.g. 500MB, 25%)",
                                metavar="SIZE")
    overwrite: bool = setting(False, doc="replace FILE.rrd if it exists")
    source: str = setting("state", doc="state: the full states (every pair the mode draws) | "
                                       "summary: pull the robot's summary stream (min / mean "
                                       "/ max per pair of clusters or map tiles; needs "
                                       "`slamlens summary`, for large maps)", choices=SOURCES)
    summary_budget: int = setting(2000, doc="--source summary: glyph budget asked for (too "
                                            "many clusters for it: map tiles instead)", min=0)
    scene_hz: float = setting(0.0, doc="states drawn per second of robot time, at most (0 = "
                                       "every state the sink takes; it takes the newest and "
                                       "skips what it cannot keep up with)", unit="Hz",
                              min=0.0)
    truth: bool = setting(True, doc="also show the ground truth where it is on the bus "
                                    "(robot/R/truth: the simulator, a dataset)")
    late_join_timeout_s: float = setting(2.0, doc="at start, ask this long for the newest "
                                                  "state, health and registrations (0 = do "
                                                  "not ask)", unit="s", min=0.0)

    def __post_init__(self) -> None:
        check_name("robot", self.robot)
        for camera in self.camera:
            check_name("camera", camera)
        if self.save and not self.save.endswith(".rrd"):
            raise ConfigError(f"setting 'save': {self.save!r} should end in .rrd")
        if self.viewer and not self.viewer.startswith(_URL_SCHEMES):
            raise ConfigError(f"setting 'viewer': {self.viewer!r} is not a Rerun URL; "
                              f"expected e.g. {DEFAULT_VIEWER_URL}")

    @property
    def viewer_url(self) -> str:
        """Where to stream: --viewer, or Rerun's default when no other output is asked for."""
        if self.viewer:
            return self.viewer
        return "" if self.save or self.serve else DEFAULT_VIEWER_URL
