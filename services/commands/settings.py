"""Settings of the composition-level commands: ``slamlens demo``, ``slamlens figures``,
``slamlens router`` and ``slamlens certs``.

Like every service's settings: each field a TOML key of ``--config FILE`` and a flag over it
(:func:`slamlens.common.config.setting`; docs/cli.md lists them all). ``slamlens router`` and
``slamlens certs`` take flags only: Zenoh's own configuration is ``--zenoh-config FILE``.
"""

from __future__ import annotations

from dataclasses import dataclass

from slamlens.common.config import setting
from slamlens.services.slam.settings import FAULT_KINDS, MAP_UPDATE
from slamlens.services.visualiser.settings import ViewSettings

#: features planted faulty by ``--faulty`` (ids of the paper world; one per cluster pair)
DEFAULT_FAULTY = (3, 12)


@dataclass(frozen=True)
class DemoSettings:
    """``slamlens demo``: the whole system on one machine, as separate processes."""

    robot: str = setting("robot1", doc="robot name")
    camera: str = setting("overhead", doc="name of the synthetic overhead camera")
    synthetic_camera: bool = setting(True, doc="run the synthetic camera with registration "
                                               "(without it the viewer shows the map view)",
                                     flag="--no-camera")
    http: str = setting("127.0.0.1:8080", doc="viewer address; port 0 = any free port (a "
                                              "taken port is refused)", metavar="HOST:PORT")
    rate: float = setting(1.0, doc="× real time", min=0.0)
    seed: int = setting(0, doc="simulator seed")
    loops: int = setting(1000, doc="laps of the loop: practically endless by default",
                         min=0)
    faulty: bool = setting(False, doc="plant the paper's programming fault in the estimator")
    fault: str = setting(MAP_UPDATE, doc="fault kind with --faulty",
                         choices=FAULT_KINDS)
    faulty_features: tuple[int, ...] = setting(DEFAULT_FAULTY, doc="feature ids the fault "
                                                                   "acts on", metavar="ID,ID")
    fault_onset: float = setting(0.0, doc="stamp from which the fault acts", unit="s")
    fault_magnitude: float | None = setting(
        None, doc="size of the fault (docs/estimator.md); none: for map-update the demo uses "
                  "5e-4 m², so the faulty glyphs grow clearly without covering the picture "
                  "(the estimator's own default, 2e-3, is the figures' stronger fault)",
        min=0.0)
    duration_s: float = setting(0.0, doc="stop after this long; 0 = until Ctrl-C", unit="s",
                                min=0.0, flag="--duration", metavar="SECONDS")
    log_dir: str = setting("", doc="folder for the services' logs; empty = a new temporary "
                                   "folder", metavar="DIR")


@dataclass(frozen=True)
class FigureSettings:
    """``slamlens figures``: the runs and the view behind the paper's Figs. 3-8."""

    output_dir: str = setting("docs/figures", doc="where fig3a.png … fig8b.png are written",
                              metavar="DIR")
    seed: int = setting(1, doc="simulator seed of both runs")
    world: str = setting("paper", doc="the simulated world (a packaged name or a TOML file)")
    fault: str = setting(MAP_UPDATE, doc="the faulty run's planted fault",
                         choices=FAULT_KINDS)
    faulty_features: tuple[int, ...] = setting((3, 12), doc="its features: one in cluster A, "
                                                            "one in C", metavar="ID,ID")
    fault_onset_s: float = setting(12.0, doc="the fault acts from this stamp: after the start "
                                             "picture (all 15 mapped at ~10 s)", unit="s")
    width: int = setting(960, doc="picture width: small enough to keep twelve PNGs in the "
                                  "repository", unit="px", min=16)
    height: int = setting(540, doc="picture height", unit="px", min=16)
    blur_px: int = setting(3, doc="the synthetic camera's lens blur (a real camera is never "
                                  "pin-sharp)", unit="px", min=0)
    eye_m: tuple[float, float, float] = setting(
        (0.5, -1.3, 3.0), doc="ceiling camera position (slightly oblique)", unit="m",
        metavar="X,Y,Z")
    target_m: tuple[float, float, float] = setting((0.5, 0.5, 0.0), doc="point it looks at",
                                                   unit="m", metavar="X,Y,Z")
    view: ViewSettings = setting(doc="how the state is drawn (a [view] table of "
                                     "ViewSettings keys)", flag=False,
                                 default_factory=ViewSettings)


@dataclass(frozen=True)
class RouterSettings:
    """``slamlens router``: Zenoh's router, in-process (its bus flags say where and how)."""

    print_acl: bool = setting(False, doc="print the access control generated from --secure DIR "
                                         "(docs/security.md) and exit")


@dataclass(frozen=True)
class CertsSettings:
    """``slamlens certs``: create or extend the certificate authority of docs/security.md."""

    directory: str = setting("", doc="folder of the authority (created 0700); existing files "
                                     "are kept", positional=True, required=True, metavar="DIR")
    names: tuple[str, ...] = setting(
        (), doc="identity to issue (repeatable): robot-R, camera-C, monitor-R, ros2-R, viewer-…, "
                "router-…", flag="--name", action="append", required=True, metavar="NAME")
    hosts: tuple[str, ...] = setting(
        (), doc="DNS name or IP address clients dial a router at, or browsers open a "
                "viewer's HTTPS page at (repeatable); added to the router-… and viewer-… "
                "certificates", flag="--host", action="append", metavar="HOST")


@dataclass(frozen=True)
class LaunchSettings:
    """``slamlens launch``: a described group of services, supervised (docs/launch.md)."""

    file: str = setting("", doc="the launch file (TOML; deploy/robot.toml …)", positional=True,
                        required=True, metavar="FILE.toml")
    values: tuple[str, ...] = setting(
        (), doc="give the launch file's variable NAME this value (repeatable; over its [vars])",
        flag="--set", action="append", metavar="NAME=VALUE")
    log_dir: str = setting("", doc="also write each service's output to DIR/NAME.log; empty = "
                                   "the file's [launch] log_dir, if any", metavar="DIR")
    check: bool = setting(False, doc="check the file, print each service's command line in "
                                     "start order, and exit")


@dataclass(frozen=True)
class StatusSettings:
    """``slamlens status``: every live service on every host linked to the router."""

    json: bool = setting(False, doc="print one JSON document (a list of services) and exit, "
                                    "for scripts")
    once: bool = setting(False, doc="print the table once and exit (default: refresh it "
                                    "until Ctrl-C)")
    interval_s: float = setting(1.0, doc="time between refreshes", unit="s", min=0.1,
                                flag="--interval", metavar="SECONDS")
    timeout_s: float = setting(2.0, doc="how long to wait for the services' answers", unit="s",
                               min=0.1, flag="--timeout", metavar="SECONDS")


@dataclass(frozen=True)
class RegisterSettings:
    """``slamlens register``: re-register a camera (its registration service does it)."""

    camera: str = setting("", doc="camera to re-register (its registration service must run)",
                          required=True)
    robot: str = setting("", doc="only the registration of this robot; empty = whichever robot "
                                 "the camera registers")
    timeout_s: float = setting(15.0, doc="how long to wait for the new registration (the "
                                         "robot must stand still at its map origin, in view)",
                               unit="s", min=0.1, flag="--timeout", metavar="SECONDS")
