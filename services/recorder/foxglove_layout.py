"""A Foxglove layout for one robot's channels (pure; docs/recording.md).

The layout a user imports in Foxglove (Layouts → Import from file), in the format the app
exports (``configById`` + ``layout``): a 3D panel following ``R/base_link`` with the scene,
the truth and the path; per camera an Image panel showing the picture with the scene drawn
over it (the camera's calibration and its ``map`` → ``camera_C`` transform place it); Plots
of NEES and NIS with their χ² bands and of the P_d sizes; the health as a Table.
``foxglove_layout.json`` beside this module is this layout for the demo's names
(``robot1``, camera ``overhead``); ``slamlens record --layout`` / ``slamlens foxglove
--layout`` write it for others.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from slamlens.services.recorder.channels import camera_topic, robot_frame_id, robot_topic

SHIPPED = Path(__file__).with_name("foxglove_layout.json")
#: the names the shipped layout is for (the demo's)
SHIPPED_ROBOT, SHIPPED_CAMERAS = "robot1", ("overhead",)

_CAMERA_STATE = {"distance": 14.0, "perspective": True, "phi": 45.0, "thetaOffset": 30.0,
                 "targetOffset": [0.0, 0.0, 0.0], "target": [0.0, 0.0, 0.0],
                 "targetOrientation": [0.0, 0.0, 0.0, 1.0], "fovy": 45.0, "near": 0.1,
                 "far": 5000.0}


def _series(topic: str, field: str, label: str, color: str, width: float = 1.5
            ) -> dict[str, Any]:
    return {"value": f"{topic}.{field}", "enabled": True, "timestampMethod": "receiveTime",
            "label": label, "color": color, "lineSize": width}


def _plot(title: str, series: list[dict[str, Any]]) -> dict[str, Any]:
    return {"title": title, "paths": series, "showXAxisLabels": True,
            "showYAxisLabels": True, "showLegend": True, "legendDisplay": "floating",
            "showPlotValuesInLegend": True, "isSynced": True, "xAxisVal": "timestamp",
            "sidebarDimension": 240}


def _split(direction: str, first: Any, second: Any, percent: float = 50.0) -> dict[str, Any]:
    return {"direction": direction, "first": first, "second": second,
            "splitPercentage": percent}


def _stack(direction: str, items: list[Any]) -> Any:
    """Items one after the other, equal shares."""
    if len(items) == 1:
        return items[0]
    return _split(direction, items[0], _stack(direction, items[1:]), 100.0 / len(items))


def layout(robot: str, cameras: tuple[str, ...] = ()) -> dict[str, Any]:
    """The layout of ``robot``'s channels and ``cameras``' (module docstring)."""
    scene, truth, path = (robot_topic(robot, leaf) for leaf in ("scene", "truth", "path"))
    health, covariance = robot_topic(robot, "health"), robot_topic(robot, "covariance")
    grey, band = "#9e9e9e", "#bdbdbd"
    panels: dict[str, Any] = {
        "3D!map": {"cameraState": _CAMERA_STATE, "followMode": "follow-position",
                   "followTf": robot_frame_id(robot), "scene": {}, "transforms": {},
                   "topics": {scene: {"visible": True}, truth: {"visible": True},
                              path: {"visible": True, "type": "line", "lineWidth": 0.02}},
                   "layers": {"grid": {"visible": True, "frameLocked": True, "label": "Grid",
                                       "instanceId": "grid", "layerId": "foxglove.Grid",
                                       "frameId": "map", "size": 20, "divisions": 20,
                                       "lineWidth": 1, "color": "#248eff80"}}},
        "Plot!nees": _plot("NEES (pose) and its χ² band", [
            _series(health, "statistics.nees_pose", "NEES pose", "#1f77e6"),
            _series(health, "statistics.nees_pose_lo", "band low", band, 1.0),
            _series(health, "statistics.nees_pose_hi", "band high", band, 1.0),
            _series(health, "statistics.nees_pose_window_mean", "window mean", "#f28c1a")]),
        "Plot!nis": _plot("NIS and its χ² band", [
            _series(health, "statistics.nis", "NIS", "#1f77e6"),
            _series(health, "statistics.nis_lo", "band low", band, 1.0),
            _series(health, "statistics.nis_hi", "band high", band, 1.0),
            _series(health, "statistics.nis_window_mean", "window mean", "#f28c1a")]),
        "Plot!pd": _plot("P_d size √λmax, m (all pairs)", [
            _series(covariance, "pd_min_m", "min", "#33b24d"),
            _series(covariance, "pd_mean_m", "mean", "#1f77e6"),
            _series(covariance, "pd_max_m", "max", "#dc1e1e"),
            _series(covariance, "pose_sigma_m", "robot σ", grey, 1.0)]),
        "Table!health": {"topicPath": health},
    }
    images = []
    for camera in cameras:
        panel = f"Image!{camera}"
        panels[panel] = {
            "cameraState": _CAMERA_STATE, "followMode": "follow-pose", "scene": {},
            "transforms": {}, "layers": {},
            "topics": {scene: {"visible": True}},
            "imageMode": {"imageTopic": camera_topic(camera, "image"),
                          "calibrationTopic": camera_topic(camera, "calibration")}}
        images.append(panel)
    left = _split("column", "3D!map", _stack("row", images), 55.0) if images else "3D!map"
    right = _split("column", _stack("column", ["Plot!nees", "Plot!nis", "Plot!pd"]),
                   "Table!health", 70.0)
    return {"configById": panels, "globalVariables": {}, "userNodes": {},
            "playbackConfig": {"speed": 1.0}, "layout": _split("row", left, right, 60.0)}
