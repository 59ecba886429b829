"""Settings of ``slamlens record``, ``slamlens play`` and ``slamlens foxglove``.

Each is one frozen dataclass whose fields are declared once with
:func:`slamlens.common.config.setting` (TOML key, flag, help and docs/cli.md row in one).
:class:`~slamlens.common.scene3d.SceneSettings` is what the Foxglove scene shows (the three
modes, the clustering, the glyph); the recorder's and the live server's settings inherit its
fields, so they are flags of both.
"""

from __future__ import annotations

from dataclasses import dataclass

from slamlens.common.config import setting
from slamlens.common.errors import ConfigError
from slamlens.common.keys import check_name
from slamlens.common.scene3d import SceneSettings


def _names(kind: str, names: tuple[str, ...]) -> None:
    for name in names:
        check_name(kind, name)


@dataclass(frozen=True)
class RecordSettings(SceneSettings):
    """``slamlens record``: the bus into an MCAP file (docs/recording.md)."""

    path: str = setting("", doc="the MCAP file to write", positional=True, required=True,
                        metavar="FILE.mcap")
    robot: tuple[str, ...] = setting((), doc="record only this robot's keys (repeatable; "
                                             "none given with no --camera/--keys: every key "
                                             "under the prefix)", action="append",
                                     metavar="R")
    camera: tuple[str, ...] = setting((), doc="record only this camera's keys (repeatable)",
                                      action="append", metavar="C")
    keys: tuple[str, ...] = setting((), doc="record these Zenoh key expressions (repeatable)",
                                    action="append", metavar="EXPR")
    foxglove: bool = setting(True, doc="also write the Foxglove channels (scene, images, "
                                       "calibration, plots)")
    scene_hz: float = setting(10.0, doc="Foxglove scenes per second of robot time, at most "
                                        "(0 = one per state)", unit="Hz", min=0.0)
    history_s: float = setting(0.0, doc="also fetch what the publishers cached this long "
                                        "before the recorder started", unit="s", min=0.0,
                               flag="--history")
    chunk_kb: int = setting(1024, doc="MCAP chunk size", unit="KiB", min=4)
    compression: str = setting("zstd", doc="chunk compression", choices=("zstd", "lz4", "none"))
    flush_s: float = setting(1.0, doc="write the open chunk out at least this often (what a "
                                      "killed recorder can lose)", unit="s", min=0.05)
    overwrite: bool = setting(False, doc="replace FILE.mcap if it exists")
    nice: int = setting(10, doc="lower the recorder's CPU priority by this much: on a busy "
                                "machine the estimator goes first and the recorder catches "
                                "up afterwards (it drops nothing)", min=0, max=19)
    progress: bool = setting(True, doc="show a progress line on a terminal")
    layout: str = setting("", doc="also write a Foxglove layout for the --robot (exactly one) "
                                  "and --camera channels to this file (Layouts → Import from "
                                  "file)", metavar="FILE.json")

    def __post_init__(self) -> None:
        _names("robot", self.robot)
        _names("camera", self.camera)
        if self.path and not self.path.endswith(".mcap"):
            raise ConfigError(f"setting 'path': {self.path!r} should end in .mcap")
        if self.layout and len(self.robot) != 1:
            raise ConfigError("setting 'layout': a layout names one robot's channels: give "
                              f"exactly one --robot (given: {len(self.robot)})")


@dataclass(frozen=True)
class PlaySettings:
    """``slamlens play``: a recording back on the bus (docs/recording.md)."""

    path: str = setting("", doc="the MCAP file to play", positional=True, required=True,
                        metavar="FILE.mcap")
    rate: float = setting(1.0, doc="× the recorded timing; 0 = as fast as the consumers take "
                                   "it (with --inputs-only: paced on the estimator)", min=0.0)
    start_s: float = setting(0.0, doc="start this far into the recording", unit="s", min=0.0,
                             flag="--start", metavar="S")
    end_s: float = setting(0.0, doc="stop this far into the recording (0 = at its end)",
                           unit="s", min=0.0, flag="--end", metavar="S")
    loop: bool = setting(False, doc="play again from --start when the end is reached")
    inputs_only: bool = setting(False, doc="publish only odometry and observations (renumbered "
                                           "like a driver) for a fresh estimator to re-run")
    robot: tuple[str, ...] = setting((), doc="play only this robot's keys (repeatable)",
                                     action="append", metavar="R")
    keys: tuple[str, ...] = setting((), doc="play only the recorded keys matching this Zenoh "
                                            "key expression (repeatable)", action="append",
                                    metavar="EXPR")
    mix: bool = setting(False, doc="play even though an estimator is live for a played robot "
                                   "(its states and the recording's would mix)")
    wait_timeout_s: float = setting(60.0, doc="--inputs-only: wait this long for the "
                                              "estimator", unit="s", min=0.0)
    control: str = setting("127.0.0.1:0", doc="address of the pause/seek page and API (port 0: "
                                              "any free port, printed; empty: none)",
                           metavar="HOST:PORT")
    paused: bool = setting(False, doc="start paused (resume from the control page)")

    def __post_init__(self) -> None:
        _names("robot", self.robot)
        if self.end_s and self.end_s <= self.start_s:
            raise ConfigError(f"setting 'end_s': {self.end_s:g} must be after --start "
                              f"{self.start_s:g}")


@dataclass(frozen=True)
class FoxgloveSettings(SceneSettings):
    """``slamlens foxglove``: the live scene over Foxglove's WebSocket protocol."""

    robot: str = setting("robot1", doc="robot whose state is shown")
    camera: tuple[str, ...] = setting((), doc="also serve this camera's image, calibration "
                                              "and pose (repeatable)", action="append",
                                      metavar="C")
    host: str = setting("127.0.0.1", doc="address to serve on (loopback unless asked)")
    port: int = setting(8765, doc="WebSocket port (0: any free port; the URL is printed)",
                        min=0, max=65535)
    late_join_timeout_s: float = setting(2.0, doc="at start, ask this long for the latest "
                                                  "state (0 = do not ask)", unit="s", min=0.0)
    layout: str = setting("", doc="also write a Foxglove layout for the robot's and the "
                                  "cameras' channels to this file (Layouts → Import from "
                                  "file)", metavar="FILE.json")

    def __post_init__(self) -> None:
        check_name("robot", self.robot)
        _names("camera", self.camera)
