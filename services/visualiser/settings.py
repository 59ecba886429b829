"""Settings of the viewer: ``ViewerConfig`` (the service) and ``ViewSettings`` (each view).

``ViewerConfig`` is ``slamlens viewer``'s: every field a TOML key of ``--config FILE`` and a
flag over it (:func:`slamlens.common.config.setting`; docs/cli.md lists them all).

``ViewSettings`` is what one viewer wants to see (docs/visualisation.md), one frozen object
per client. Colours are OpenCV BGR tuples with the paper's defaults (robot and path green,
heading arrow yellow, features cyan, pair lines yellow, correlation ellipsoids red);
violations and suspects are magenta, which the paper does not use, so they cannot be
mistaken for ordinary glyphs. Every field can come from a TOML file (``load_settings``),
from a web page's query string (``from_query``) or from code (``replace``); bad values raise
:class:`~slamlens.common.errors.ConfigError` naming the field.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from slamlens.common.config import setting, settings_from_mapping
from slamlens.common.errors import ConfigError
from slamlens.common.keys import check_name

VIEWS = ("auto", "camera", "map", "stereo")
CODECS = ("mp4v", "MJPG")
MODES = ("all", "inter", "minmeanmax")
GLYPHS = ("sigma", "linear")
LAYERS = ("robot", "path", "features", "lines", "ellipsoids", "legend", "labels", "health",
          "rejected")

BGR = tuple[int, int, int]
ALL_ROBOTS = "all"  #: --robot all: every robot whose estimator is alive
SOURCES = ("state", "summary")  #: --source: the full state, or the summary stream
#: a host name or IP literal ([…] for IPv6), with an optional port: the Host header's form
HOST_PATTERN = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+)(:[0-9]{1,5})?$")


def _colour(default: BGR, doc: str) -> Any:
    return field(default=default, metadata={"doc": doc, "colour": True})


@dataclass(frozen=True)
class ViewSettings:
    """How one viewer draws the estimator's state over its picture."""

    mode: str = field(default="all", metadata={
        "choices": MODES,
        "doc": "all pairs | inter: pairs whose features lie in different clusters | "
               "minmeanmax: per cluster pair only the min / mean / max P_d"})
    cluster_threshold_m: float = field(default=0.6, metadata={
        "min": 1e-6, "doc": "single-linkage cut distance, m (used when cluster_count is 0)"})
    cluster_count: int = field(default=0, metadata={
        "min": 0, "doc": ">0: cut the dendrogram into this many clusters instead"})
    glyph: str = field(default="sigma", metadata={
        "choices": GLYPHS,
        "doc": "sigma: semi-axes = sigma_k·sqrt(eigenvalue) (m) | linear: semi-axes = "
               "eigenvalue read as metres (the paper's glyph; m² shown as m)"})
    sigma_k: float = field(default=2.0, metadata={"min": 1e-6, "doc": "k of the k-sigma glyph"})
    scale: float = field(default=1.0, metadata={
        "min": 1e-6, "doc": "extra factor on every glyph axis, for readability"})
    minmeanmax_spread: float = field(default=0.15, metadata={
        "min": 0.0, "doc": "minmeanmax: min and max sit this fraction of the centroid line "
                           "before / after the mean (besides below / above it)"})
    cone_height_m: float = field(default=0.15, metadata={
        "min": 1e-3, "doc": "height of a feature cone, m (the robot's is 1.4 times that)"})
    cone_radius_m: float = field(default=0.045, metadata={
        "min": 1e-3, "doc": "base radius of a feature cone, m"})
    # layers
    robot: bool = field(default=True, metadata={"doc": "robot cone and heading arrow"})
    path: bool = field(default=True, metadata={"doc": "estimated robot path"})
    features: bool = field(default=True, metadata={"doc": "feature cones"})
    lines: bool = field(default=True, metadata={"doc": "yellow line of every drawn pair"})
    ellipsoids: bool = field(default=True, metadata={"doc": "red correlation ellipsoids"})
    legend: bool = field(default=True, metadata={"doc": "legend box in the top-left corner"})
    labels: bool = field(default=False, metadata={"doc": "feature ids next to the cones"})
    health: bool = field(default=True, metadata={"doc": "violations and suspects outlined"})
    rejected: bool = field(default=True, metadata={
        "doc": "observations the estimator's innovation gate rejected: grey crosses where "
               "they were seen, counted in the legend"})
    selected_feature: int | None = field(default=None, metadata={
        "doc": "only the pairs containing this feature id (None: no selection)"})
    selected_cluster: int | None = field(default=None, metadata={
        "doc": "only the pairs inside this cluster (its stable id, as the legend shows it), "
               "all of them whatever the glyph budget (None: no selection)"})
    glyph_budget: int = field(default=2000, metadata={
        "min": 0, "doc": "most glyphs a picture draws pair by pair; above it the picture is "
                         "the min/mean/max overview per cluster (or map tile) pair, with a "
                         "note; 0: no budget"})
    selected_robot: str | None = field(default=None, metadata={
        "doc": "whose map the selection is in, when several robots are shown (None: every "
               "robot's)"})
    # colours (BGR)
    colour_robot: BGR = _colour((40, 200, 40), "robot cone")
    colour_heading: BGR = _colour((0, 230, 255), "heading arrow")
    colour_path: BGR = _colour((40, 200, 40), "robot path")
    colour_features: BGR = _colour((230, 230, 0), "feature cones")
    colour_lines: BGR = _colour((0, 230, 255), "pair lines")
    colour_ellipsoids: BGR = _colour((30, 30, 220), "correlation ellipsoids")
    colour_violation: BGR = _colour((255, 0, 255), "violating pairs and suspect features")
    colour_background: BGR = _colour((92, 98, 96), "floor of the map view (no camera image)")

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            choices = f.metadata.get("choices")
            if choices is not None and value not in choices:
                raise ConfigError(f"view setting {f.name!r}: {value!r} is not one of "
                                  f"{list(choices)}")
            minimum = f.metadata.get("min")
            if minimum is not None and not (value >= minimum):  # also rejects NaN
                raise ConfigError(f"view setting {f.name!r}: {value!r} is below {minimum}")
            if f.metadata.get("colour"):
                ok = (isinstance(value, tuple) and len(value) == 3
                      and all(isinstance(c, int) and 0 <= c <= 255 for c in value))
                if not ok:
                    raise ConfigError(f"view setting {f.name!r}: expected three integers "
                                      f"0-255 (B, G, R), got {value!r}")

    def replace(self, **changes: Any) -> ViewSettings:
        """A copy with ``changes`` applied (validated like the constructor)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_query(cls, query: Mapping[str, str], *,
                   base: ViewSettings | None = None) -> ViewSettings:
        """Settings from a web page's query/JSON strings, applied over ``base``.

        Booleans accept true/false/1/0/yes/no/on/off; ``selected_feature`` accepts an id or
        ""/"none" for no selection; colours accept "B,G,R". Unknown keys are rejected.
        """
        base = base or cls()
        values: dict[str, Any] = {f.name: getattr(base, f.name) for f in dataclasses.fields(cls)}
        for key, raw in query.items():
            name = key.replace("-", "_")
            value: Any = raw
            if isinstance(raw, str):
                text = raw.strip()
                if name in ("selected_feature", "selected_robot", "selected_cluster") and \
                        text.lower() in {"", "none", "null"}:
                    value = None
                elif text.lower() in {"on", "off"}:
                    value = text.lower() == "on"
                else:
                    value = text
            if name not in values:
                raise ConfigError(f"unknown view setting {key!r}; known: "
                                  f"{', '.join(sorted(values))}")
            values[name] = value
        return settings_from_mapping(cls, values, source="view settings")

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able values (colours as lists), e.g. for the web page."""
        return {f.name: list(v) if isinstance(v := getattr(self, f.name), tuple) else v
                for f in dataclasses.fields(self)}


@dataclass(frozen=True)
class ViewerConfig:
    """``slamlens viewer``: the AR renderer and its web viewers (docs/viewer.md)."""

    robot: str = setting("robot1", doc="robot(s) shown: a name, names joined by commas "
                                       "(each in its own colour), or 'all': every robot whose "
                                       "estimator is alive, as it appears", metavar="R[,R…]")
    camera: str | None = setting(None, doc="camera to draw over; none: the map view",
                                 metavar="C")
    view: str = setting("auto", doc="auto: the camera if one is named, else the map; "
                                    "stereo: cameras C-left / C-right if registered, else a "
                                    "stereo pair of the map view", choices=VIEWS)
    http: str = setting("127.0.0.1:8080", doc="address of the web viewer (port 0: any free "
                                              "port; the URL is printed)", metavar="HOST:PORT")
    fps: float = setting(30.0, doc="render rate cap", unit="Hz", min=0.5)
    jpeg_quality: int = setting(80, doc="JPEG quality of the stream", min=10, max=100)
    recordings_dir: str = setting("recordings", doc="where video recordings are written",
                                  metavar="DIR")
    record_codec: str = setting("mp4v", doc="video codec: mp4v (.mp4) or MJPG (.avi)",
                                choices=CODECS)
    stereo_baseline_m: float = setting(0.065, doc="baseline of the map view's stereo pair",
                                       unit="m", min=1e-3, flag="--stereo-baseline",
                                       metavar="B")
    map_width: int = setting(1280, doc="map view width", unit="px", min=64)
    map_height: int = setting(720, doc="map view height", unit="px", min=64)
    series_length: int = setting(600, doc="samples kept per plot", min=2)
    series_interval_s: float = setting(0.2, doc="plot sampling interval", unit="s", min=0.0)
    client_ttl_s: float = setting(5.0, doc="a view nobody streams keeps rendering this long "
                                           "after its last request, then is dropped with its "
                                           "picture", unit="s", min=0.1)
    source: str = setting(
        "state", doc="what the viewer takes in of each robot: state = the full state "
                     "(subscribed); summary = the robot's summary stream (slamlens summary "
                     "on the robot: the map's blocks and the clustered min/mean/max, pulled "
                     "at the rate the link sustains; the picture is min/mean/max whatever "
                     "the mode; docs/remote_viewers.md)", choices=SOURCES)
    summary_budget: int = setting(
        2000, doc="with --source summary: the glyph budget the robot's summary is made for "
                  "(too many clusters for it: map tiles)", min=0)
    late_join_timeout_s: float = setting(2.0, doc="at start, wait this long for the latest "
                                                  "state and registrations (0 = do not ask)",
                                         unit="s", min=0.0)
    restart_note_s: float = setting(10.0, doc="how long 'map restarted' shows (page and "
                                              "legend) after an estimator begins a new map",
                                    unit="s", min=0.0)
    reregister_timeout_s: float = setting(3.0, doc="how long the page's 're-register camera' "
                                                   "waits for the registration service to "
                                                   "answer", unit="s", min=0.1)
    # -- the web viewer's guard (docs/security.md) ---------------------------------
    token_file: str | None = setting(
        None, doc="file holding the web viewer's access token (its first line); every "
                  "request must then carry it. Without it a viewer bound beyond loopback "
                  "makes a token and prints it in its URL; on loopback none is asked",
        metavar="FILE")
    allowed_hosts: tuple[str, ...] = setting(
        (), doc="more names the web viewer may be reached by (Host header), NAME or "
                "NAME:PORT, besides the address it is bound to (repeatable)",
        flag="--allow-host", action="append", metavar="NAME[:PORT]")
    allowed_origins: tuple[str, ...] = setting(
        (), doc="more web origins allowed to call the viewer (Origin header), e.g. "
                "https://dashboard.lab, besides its own page (repeatable)",
        flag="--allow-origin", action="append", metavar="ORIGIN")
    tls_cert: str | None = setting(
        None, doc="serve HTTPS with this certificate (PEM; slamlens certs DIR --name "
                  "viewer-… --host ADDRESS makes one): a phone's browser opens its camera "
                  "only for a secure page (docs/viewer.md, \"AR on a phone\")",
        metavar="FILE.pem")
    tls_key: str | None = setting(None, doc="the private key of --tls-cert (PEM)",
                                  metavar="FILE.key")
    # -- the AR page (docs/viewer.md "AR on a phone") --------------------------------
    ar_camera: str = setting(
        "phone", doc="camera name of the /ar page's browsers: each page is camera NAME-… "
                     "(its own), registered by slamlens registration --source browser "
                     "--camera NAME", metavar="NAME")
    max_ar_cameras: int = setting(4, doc="AR pages (browser cameras) served at once", min=0)
    max_ar_frame_bytes: int = setting(2 << 20, doc="an AR page's frame (a JPEG) larger than "
                                                   "this is refused", unit="bytes", min=1024)
    max_ar_fps: float = setting(30.0, doc="frames a second one AR page may send; faster ones "
                                          "are refused", unit="Hz", min=1.0)
    ar_wait_s: float = setting(0.5, doc="an AR frame whose registration has not come this "
                                        "long after it is shown without the overlay",
                               unit="s", min=0.01)
    # -- bounded resources (docs/viewer.md "Limits") -------------------------------
    max_views: int = setting(64, doc="distinct view settings kept at once besides the "
                                     "default view (oldest idle evicted; beyond: refused)",
                             min=1)
    other_views_share: float = setting(
        0.3, doc="share of the render thread the views other than the default may take "
                 "while somebody watches the default view", min=0.05, max=1.0)
    max_frame_pixels: int = setting(
        16_777_216, doc="camera frames whose JPEG header claims more pixels are refused "
                        "before decoding (also more than 4 × the camera's registered size)",
        min=1)
    max_recordings: int = setting(2, doc="recordings running at once", min=0)
    max_recording_s: float = setting(600.0, doc="a recording stops after this long",
                                     unit="s", min=1.0)
    max_recording_mb: float = setting(1000.0, doc="a recording stops at this file size",
                                      unit="MB", min=1.0)
    min_free_disk_mb: float = setting(
        1000.0, doc="no recording starts, and a running one stops, when the recordings "
                    "folder's disk has less free space than this", unit="MB", min=0.0)

    def __post_init__(self) -> None:
        if self.robot != ALL_ROBOTS:
            names = [r.strip() for r in self.robot.split(",")]
            for name in names:
                check_name("robot", name)
            if len(set(names)) != len(names):
                raise ConfigError(f"setting 'robot': {self.robot!r} names a robot twice")
        if self.camera is not None:
            check_name("camera", self.camera)
        check_name("camera", self.ar_camera)
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ConfigError("settings 'tls_cert' and 'tls_key': give both (HTTPS) or "
                              "neither")
        if self.view == "camera" and self.camera is None:
            raise ConfigError("setting 'view': 'camera' needs a camera (--camera C)")
        for host in self.allowed_hosts:
            if not HOST_PATTERN.match(host):
                raise ConfigError(f"setting 'allowed_hosts': {host!r} is not NAME or "
                                  "NAME:PORT (e.g. viewer.lab or viewer.lab:8080)")
        for origin in self.allowed_origins:
            scheme, sep, host = origin.partition("://")
            if scheme not in ("http", "https") or not sep or not HOST_PATTERN.match(host):
                raise ConfigError(f"setting 'allowed_origins': {origin!r} is not an origin "
                                  "like https://host or http://host:port")

    @property
    def robots(self) -> tuple[str, ...]:
        """The robots named (none with 'all': they are discovered)."""
        if self.robot == ALL_ROBOTS:
            return ()
        return tuple(r.strip() for r in self.robot.split(","))

    @property
    def discover(self) -> bool:
        """Show every robot whose estimator is alive (``robot = "all"``)."""
        return self.robot == ALL_ROBOTS

    @property
    def resolved_view(self) -> str:
        if self.view == "auto":
            return "camera" if self.camera else "map"
        return self.view

    @property
    def cameras(self) -> tuple[str, ...]:
        """Cameras whose frames and registrations this viewer subscribes to."""
        view = self.resolved_view
        if view == "camera" and self.camera:
            return (self.camera,)
        if view == "stereo" and self.camera:
            return (f"{self.camera}-left", f"{self.camera}-right")
        return ()
