"""The legend of a picture, and the colours of the robots it shows.

One robot: :func:`draw_legend` (robot and seq, mode, glyph meaning, colours, clusters or
map tiles, the overview note, the monitor's verdict, notes). Several robots in one picture:
:func:`draw_robots_legend` (mode and glyph meaning once, a row per robot in its colour);
the first robot keeps the settings' colours, the others get :data:`ROBOT_COLOURS`
(:func:`robot_settings`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from slamlens.common.clusters import cluster_colour
from slamlens.common.messages import Health, SlamState
from slamlens.common.verdict import summary_text
from slamlens.services.visualiser import draw
from slamlens.services.visualiser.render_steps import MAX_ROLE_LABELS, REJECTED_COLOUR, Canvas
from slamlens.services.visualiser.settings import ViewSettings

#: a legend row: [(text, swatch colour or None), …]
LegendRow = list[tuple[str, tuple[int, int, int] | None]]


#: colours (BGR) of the second, third … robot of one picture; the first robot keeps the
#: settings' (the paper's green); none is red (glyphs), yellow (lines) or magenta (faults)
ROBOT_COLOURS = ((0, 140, 255), (255, 170, 40), (235, 235, 235), (255, 110, 150),
                 (60, 200, 190))


def robot_settings(settings: ViewSettings, index: int) -> ViewSettings:
    """``settings`` for the ``index``-th robot of a picture: the first as given, the others
    with their own colour for the robot, its path and (lighter) its features."""
    if index <= 0:
        return settings
    colour = ROBOT_COLOURS[(index - 1) % len(ROBOT_COLOURS)]
    return settings.replace(colour_robot=colour, colour_path=colour,
                            colour_features=draw.shade(colour, 0.85, 0.4))


@dataclass(frozen=True, eq=False)
class RobotLegend:
    """One robot's rows of a shared legend."""

    state: SlamState
    health: Health | None
    glyphs_shown: int
    colour: tuple[int, int, int]
    notes: Sequence[LegendRow] = ()


def draw_robots_legend(img: np.ndarray, settings: ViewSettings, robots: Sequence[RobotLegend],
                       *, waiting: Sequence[str] = ()) -> None:
    """The legend of a picture of several robots: mode and glyph meaning once, then one
    row per robot (its colour, seq, features, glyphs, verdict) and any notes."""
    rows: list[LegendRow] = [[(f"mode: {_MODE_TEXT[settings.mode]}", None)],
                             [(_glyph_text(settings), settings.colour_ellipsoids)]]
    for r in robots:
        s = r.state
        rows.append([(f"robot {s.robot}", r.colour),
                     (f"seq {s.seq} {s.step}  {s.n} features  {r.glyphs_shown} glyphs", None)])
        if settings.health and r.health is not None:
            rows.append(_health_row(r.health, settings))
        rows += [list(row) for row in r.notes]
    rows += [[(text, None)] for text in waiting]
    draw.text_box(img, rows, scale=max(0.35, 0.45 * img.shape[0] / 720))


def rejected_legend(state: SlamState, settings: ViewSettings) -> list[LegendRow]:
    """"rejected observations: 2 in this update, 17 in all" when the state says."""
    if not settings.rejected:
        return []
    ids = getattr(state, "gated_ids", None)
    diagnostics = getattr(state, "diagnostics", None) or {}
    total = diagnostics.get("gated")
    now = 0 if ids is None else int(np.asarray(ids).size)
    if ids is None and total is None:
        return []
    text = f"rejected observations (gate): {now} in this {state.step}"
    if total is not None:
        text += f", {int(total)} in all"
    return [[(text, REJECTED_COLOUR)]]


_MODE_TEXT = {"all": "all pairs", "inter": "inter-cluster pairs",
              "minmeanmax": "min/mean/max per cluster pair (size = sqrt of largest eigenvalue)"}


def _glyph_text(settings: ViewSettings) -> str:
    if settings.glyph == "sigma":
        text = f"{settings.sigma_k:g}-sigma ellipsoid of P_d"
    else:
        text = "semi-axes = eigenvalues of P_d (m^2 drawn as m)"
    if settings.scale != 1.0:
        text += f" x{settings.scale:g}"
    return text


OVERVIEW_COLOUR = (0, 215, 255)  # BGR amber: the picture is not pair by pair

#: legend colour of a "tuning" verdict (BGR orange: the filter computes right, its noise
#: or models do not fit the data); a fault is in the violation colour
TUNING_COLOUR = (0, 165, 255)


def _health_row(health: Health, settings: ViewSettings) -> LegendRow:
    """The monitor's verdict, as the page and the terminal say it (slamlens.common.verdict)."""
    colour = {"fault": settings.colour_violation, "tuning": TUNING_COLOUR}.get(health.verdict)
    return [(f"verdict: {summary_text(health)}", colour)]


def draw_legend(c: Canvas, *, health: Health | None, glyphs_shown: int,
                 notes: Sequence[LegendRow] = ()) -> None:
    """The legend box: robot and seq, mode, glyph meaning, colours, clusters, health."""
    state, scene, settings = c.state, c.scene, c.settings
    rows: list[LegendRow] = [
        [(f"robot {state.robot}  seq {state.seq}  {state.step}", None)],
        [(f"mode: {_MODE_TEXT[scene.mode]}", None)],
        [(f"{glyphs_shown} glyphs: {_glyph_text(settings)}", settings.colour_ellipsoids)],
        [("robot", settings.colour_robot), ("heading", settings.colour_heading),
         (f"features ({state.n})", settings.colour_features),
         (f"pair lines ({len(scene.lines_xy)})", settings.colour_lines)],
    ]
    if settings.selected_feature is not None:
        note = " (not in the map)" if scene.selected_missing else ""
        rows.append([(f"selected feature {settings.selected_feature}{note}", None)])
    if settings.selected_cluster is not None:
        rows.append([(f"selected cluster {settings.selected_cluster}: all its pairs",
                      cluster_colour(settings.selected_cluster))])
    if scene.tile_m is not None:
        rows.append([(f"map tiles of {scene.tile_m:g} m ({len(scene.centroids)})",
                      None)])
    elif scene.cluster_ids is not None:
        ids = np.unique(scene.cluster_ids).tolist()
        row: LegendRow = [(f"clusters ({len(ids)}):", None)]
        row += [(f"{c}", cluster_colour(int(c))) for c in ids[:12]]
        rows.append(row)
    if scene.overview:
        rows.append([(scene.overview, OVERVIEW_COLOUR)])
    if scene.mode == "minmeanmax" and glyphs_shown > MAX_ROLE_LABELS:
        rows.append([("per group pair: min below the line, mean at its middle, max above",
                      None)])
    if settings.health and health is not None:
        rows.append(_health_row(health, settings))
    rows += [list(row) for row in notes]
    draw.text_box(c.img, rows, scale=max(0.35, 0.45 * c.camera.height / 720))
