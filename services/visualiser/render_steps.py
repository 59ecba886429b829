"""The drawing steps of one picture of a state, each on a :class:`Canvas` (order: :mod:`render`).

:func:`draw_under` draws steps 1 and 2: the floor layer (map grid in the map view only,
cluster outlines, robot path, pair lines, heading arrow), then the glyphs and cones far to
near; :func:`draw_reference` the camera-tracked pose and :func:`draw_over` the rest of
step 3 but the legend (:mod:`legend`): rejected observations, health outlines and rings,
labels, roles. Nothing here is kept between pictures (that is :mod:`render_cache`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from slamlens.common.clusters import cluster_colour
from slamlens.common.messages import SlamState
from slamlens.services.visualiser import draw
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.glyphs import ImageEllipses, project_ellipsoids
from slamlens.services.visualiser.scene import ROLE_NAMES, ROLE_PAIR, Scene
from slamlens.services.visualiser.settings import ViewSettings
from slamlens.services.visualiser.trail import Trail

_AA_LINES_LIMIT = 400  # anti-aliased pair lines up to this many, plain beyond (frame time)
_AA_GLYPH_LIMIT = 400  # same for the inner shading layers of glyphs
#: "min" / "mean" / "max" labels up to this many glyphs (beyond: the legend says where)
MAX_ROLE_LABELS = 30


@dataclass(frozen=True, eq=False)
class Canvas:
    """One picture being drawn, and what every drawing step of it shares."""

    img: np.ndarray  #: BGR uint8, drawn in place
    camera: CameraModel  #: the camera, fitted to ``img``'s size
    state: SlamState  #: the state drawn
    scene: Scene  #: what of it is drawn under ``settings`` (pairs, glyphs, lines)
    settings: ViewSettings
    px: int  #: line width unit for this resolution (1 up to 720 rows, 2 at 1440, …)


@dataclass(frozen=True, eq=False)
class Lines:
    """The pair lines as drawn: image polylines and, for each, its index in the scene."""

    polylines: list[np.ndarray]
    index: np.ndarray


@dataclass(frozen=True, eq=False)
class Glyphs:
    """The glyphs' projections, those on screen, and their shaded drawing (if drawn)."""

    ellipses: ImageEllipses  #: every scene glyph, projected
    shown: np.ndarray  #: indices of the glyphs on screen
    shaded: draw.ShadedEllipses | None  #: None when ellipsoids are off or there are none


def draw_under(c: Canvas, path: Trail) -> tuple[Lines, Glyphs]:
    """Steps 1 and 2 (module docstring): the floor layer, then glyphs and cones."""
    settings, scene = c.settings, c.scene
    # outlines: every cluster (or overview group) in the clustered pictures; in "all"
    # pairs only a selected cluster's
    pairwise = settings.mode == "all" and scene.mode == "all"
    outlined = None if pairwise else scene.cluster_ids
    if pairwise and scene.cluster_ids is not None and \
            settings.selected_cluster is not None:
        outlined = np.where(scene.cluster_ids == settings.selected_cluster,
                            settings.selected_cluster, -1)
    lines = _draw_floor_layer(c, path=path, cluster_ids=outlined)
    return lines, _draw_objects(c)


def draw_over(c: Canvas, *, glyphs: Glyphs, lines: Lines, suspects: np.ndarray) -> int:
    """Step 3 but the reference pose and the legend: rejected observations, health,
    labels, roles; returns the number of rejected observations drawn."""
    settings, scene = c.settings, c.scene
    rejected = rejected_observations(c.state) if settings.rejected else np.zeros((0, 2))
    if len(rejected):
        _draw_rejected(c, rejected)
    if settings.health:
        _draw_health(c, glyphs=glyphs, lines=lines, suspects=suspects)
    if settings.labels and settings.features:
        _draw_labels(c)
    if (glyphs.shaded is not None and scene.mode == "minmeanmax"
            and len(glyphs.shown) <= MAX_ROLE_LABELS):
        _draw_roles(c, glyphs)
    return len(rejected)


def feature_pixels(state: SlamState, camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """(ids (n,), pixels (n, 2)) of the feature estimates (cone tips); NaN if not visible."""
    uv, _ = camera.project(np.column_stack([state.landmarks, np.zeros(state.n)]))
    return state.landmark_ids.copy(), uv


def _on_screen(ie: ImageEllipses, camera: CameraModel) -> np.ndarray:
    a, b, t = ie.axes[:, 0], ie.axes[:, 1], ie.angle
    half_w = np.sqrt((a * np.cos(t)) ** 2 + (b * np.sin(t)) ** 2)
    half_h = np.sqrt((a * np.sin(t)) ** 2 + (b * np.cos(t)) ** 2)
    cu, cv = ie.centre[:, 0], ie.centre[:, 1]
    ok = (ie.valid & (cu + half_w >= 0) & (cu - half_w < camera.width)
          & (cv + half_h >= 0) & (cv - half_h < camera.height))
    return np.flatnonzero(ok)


def _floor_bounds(camera: CameraModel) -> tuple[float, float, float, float] | None:
    """Map-frame xy bounds of the floor seen by an undistorted camera (None: horizon)."""
    corners = np.array([[0, 0], [camera.width, 0], [0, camera.height],
                        [camera.width, camera.height]], dtype=float)
    rays_cam = np.column_stack([corners, np.ones(4)]) @ np.linalg.inv(camera.K).T
    R = camera.T_camera_from_map[:3, :3]
    rays = rays_cam @ R  # = (Rᵀ·ray) per row: directions in the map frame
    origin = camera.centre_map
    if np.any(rays[:, 2] >= 0) or origin[2] <= 0:
        return None
    t = -origin[2] / rays[:, 2]
    pts = origin[:2] + t[:, None] * rays[:, :2]
    return float(pts[:, 0].min()), float(pts[:, 1].min()), float(pts[:, 0].max()), \
        float(pts[:, 1].max())


def draw_grid(img: np.ndarray, camera: CameraModel, *, step_m: float = 0.5) -> None:
    bounds = _floor_bounds(camera)
    if bounds is None:
        return
    xmin, ymin, xmax, ymax = bounds
    if (xmax - xmin) / step_m > 400 or (ymax - ymin) / step_m > 400:
        return
    xs = np.arange(math.floor(xmin / step_m), math.ceil(xmax / step_m) + 1) * step_m
    ys = np.arange(math.floor(ymin / step_m), math.ceil(ymax / step_m) + 1) * step_m
    p0 = np.concatenate([np.column_stack([xs, np.full_like(xs, ys[0]), np.zeros_like(xs)]),
                         np.column_stack([np.full_like(ys, xs[0]), ys, np.zeros_like(ys)])])
    p1 = np.concatenate([np.column_stack([xs, np.full_like(xs, ys[-1]), np.zeros_like(xs)]),
                         np.column_stack([np.full_like(ys, xs[-1]), ys, np.zeros_like(ys)])])
    major = np.concatenate([np.isclose(xs, 0.0), np.isclose(ys, 0.0)])
    b, g, r = (int(c) for c in img[0, 0])
    minor_colour = (min(b + 14, 255), min(g + 14, 255), min(r + 14, 255))
    major_colour = (min(b + 45, 255), min(g + 45, 255), min(r + 45, 255))
    draw.draw_polylines(img, draw.project_segments(camera, p0[~major], p1[~major])[0],
                        colour=minor_colour, thickness=1)
    draw.draw_polylines(img, draw.project_segments(camera, p0[major], p1[major])[0],
                        colour=major_colour, thickness=1)


def _draw_floor_layer(c: Canvas, *, path: Trail,
                      cluster_ids: np.ndarray | None) -> Lines:
    """Cluster outlines, the robot path, the pair lines and the heading arrow, flat on the
    floor; returns the pair lines as drawn (health outlines the violating ones)."""
    settings = c.settings
    if cluster_ids is not None:
        draw_cluster_outlines(c, cluster_ids)
    if settings.path:
        path.draw(c.img, c.camera, colour=settings.colour_path, thickness=2 * c.px)
    lines = Lines([], np.zeros(0, dtype=np.int64))
    lines_xy = c.scene.lines_xy
    if settings.lines and len(lines_xy):
        zeros = np.zeros((len(lines_xy), 1))
        lines = Lines(*draw.project_segments(c.camera, np.hstack([lines_xy[:, 0], zeros]),
                                              np.hstack([lines_xy[:, 1], zeros])))
        draw.draw_polylines(c.img, lines.polylines, colour=settings.colour_lines,
                            thickness=c.px, line_type=draw.line_type_for(
                                len(lines.polylines), limit=_AA_LINES_LIMIT))
    if settings.robot:
        _draw_heading(c)
    return lines


def _draw_objects(c: Canvas) -> Glyphs:
    """Glyphs and cones, far to near by camera depth (painter's algorithm)."""
    settings, camera, state = c.settings, c.camera, c.state
    ie = project_ellipsoids(c.scene.glyphs, camera)
    shown = np.zeros(0, dtype=np.int64)
    shaded = None
    if settings.ellipsoids and len(c.scene.glyphs):
        shown = _on_screen(ie, camera)
        shaded = draw.ShadedEllipses(ie, shown, colour=settings.colour_ellipsoids,
                                     max_axis_px=4.0 * (camera.width + camera.height))
    cone_sets: list[draw.Cones] = []
    if settings.features and state.n:
        cone_sets.append(draw.Cones(camera, state.landmarks, height_m=settings.cone_height_m,
                                    radius_m=settings.cone_radius_m,
                                    colour=settings.colour_features))
    if settings.robot:
        cone_sets.append(draw.Cones(camera, state.pose[None, :2],
                                    height_m=1.4 * settings.cone_height_m,
                                    radius_m=1.4 * settings.cone_radius_m,
                                    colour=settings.colour_robot))
    depth = np.concatenate([ie.depth[shown]] + [cones.depth for cones in cone_sets])
    kind = np.concatenate([np.full(len(shown), -1)]
                          + [np.full(len(cones), s) for s, cones in enumerate(cone_sets)])
    item = np.concatenate([np.arange(len(shown))]
                          + [np.arange(len(cones)) for cones in cone_sets])
    lt = draw.line_type_for(len(shown), limit=_AA_GLYPH_LIMIT)
    kinds, items = kind.tolist(), item.tolist()  # Python ints: ~1000 items per picture
    for k in np.argsort(-depth, kind="stable").tolist():
        s, i = kinds[k], items[k]
        if s < 0:
            shaded.draw(c.img, i, line_type=lt)  # type: ignore[union-attr]
        else:
            cone_sets[s].draw(c.img, i)
    return Glyphs(ie, shown, shaded)


def draw_cluster_outlines(c: Canvas, cluster_ids: np.ndarray) -> None:
    """A rounded hull around each cluster's features, in the cluster's colour: the convex
    hull of its members grown by a ring of ``pad`` (the hull of the members' hull vertices
    ⊕ the ring, the same polygon as the hull of every member ⊕ the ring), all clusters
    projected in one call (a large map has hundreds, many of one feature)."""
    pad = 2.5 * c.settings.cone_radius_m
    ring = draw.floor_circle(np.zeros(2), pad, vertices=16)[:, :2]
    outlined = cluster_ids >= 0  # the rest are not outlined
    if not outlined.any():
        return
    ids, xy = cluster_ids[outlined], c.state.landmarks[outlined]
    order = np.argsort(ids, kind="stable")
    ids, xy = ids[order], xy[order]
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    ends = np.r_[starts[1:], len(ids)]
    polygons = []
    for s, e in zip(starts.tolist(), ends.tolist(), strict=True):
        members = xy[s:e]
        if e - s == 1:  # one feature: the ring around it
            polygons.append(members[0] + ring)
            continue
        if e - s > 2:  # only the members' hull vertices can be on the grown hull
            members = members[cv2.convexHull(members.astype(np.float32),
                                             returnPoints=False).ravel()]
        pts = (members[:, None, :] + ring[None]).reshape(-1, 2).astype(np.float32)
        polygons.append(cv2.convexHull(pts).reshape(-1, 2).astype(float))
    bounds = np.r_[0, np.cumsum([len(p) for p in polygons])]
    flat = np.concatenate(polygons)
    uv, _ = c.camera.project(np.column_stack([flat, np.zeros(len(flat))]))
    whole = np.logical_and.reduceat(np.isfinite(uv).all(axis=1), bounds[:-1]).tolist()
    points = draw.fixed(np.nan_to_num(uv))
    for k, (cid, a, b) in enumerate(zip(ids[starts].tolist(), bounds[:-1].tolist(),
                                        bounds[1:].tolist(), strict=True)):
        colour = cluster_colour(int(cid))
        if whole[k]:  # the common case: every vertex projected
            cv2.polylines(c.img, [points[a:b]], True, colour, c.px, cv2.LINE_AA, draw.SHIFT)
        else:  # split where the lens cannot project (draw.polylines_from_uv)
            draw.draw_polylines(c.img, draw.polylines_from_uv(uv[a:b], closed=True),
                                colour=colour, thickness=c.px)


def _draw_heading(c: Canvas) -> None:
    """A flat arrow on the floor from the robot's position along its heading."""
    pose = c.state.pose
    length = 2.2 * c.settings.cone_height_m
    shaft, head, half = 0.018 * length / 0.33, 0.3 * length, 0.16 * length
    outline = np.array([[0, -shaft], [length - head, -shaft], [length - head, -half],
                        [length, 0], [length - head, half], [length - head, shaft],
                        [0, shaft]])
    cos, sin = math.cos(float(pose[2])), math.sin(float(pose[2]))
    xy = outline @ np.array([[cos, sin], [-sin, cos]]) + pose[:2]
    uv, _ = c.camera.project(np.column_stack([xy, np.full(len(xy), 0.002)]))
    if np.isfinite(uv).all():
        cv2.fillPoly(c.img, [draw.fixed(uv)], c.settings.colour_heading, cv2.LINE_AA,
                     draw.SHIFT)


REFERENCE_COLOUR = (255, 255, 255)  # BGR: the independent pose is white, the estimate green


def draw_reference(c: Canvas, *, estimate: np.ndarray, reference: np.ndarray) -> None:
    """The independently measured robot pose: a ring, a line to the estimate, the error."""
    px = c.px
    uv, _ = c.camera.project(np.array([[reference[0], reference[1], 0.0],
                                       [estimate[0], estimate[1], 0.0]]))
    if not np.isfinite(uv).all():
        return
    ref_px = tuple(int(v) for v in draw.fixed(uv[:1])[0])
    est_px = tuple(int(v) for v in draw.fixed(uv[1:])[0])
    cv2.line(c.img, ref_px, est_px, REFERENCE_COLOUR, px, cv2.LINE_AA, draw.SHIFT)
    cv2.circle(c.img, ref_px, (9 * px) << draw.SHIFT, REFERENCE_COLOUR, 2 * px, cv2.LINE_AA,
               draw.SHIFT)
    error_cm = 100.0 * float(np.hypot(*(reference[:2] - estimate[:2])))
    u, v = (int(x) for x in uv[0])
    draw.put_text(c.img, f"tracked: {error_cm:.1f} cm", (u + 12 * px, v - 12 * px),
                  0.45 * px, REFERENCE_COLOUR, px)


REJECTED_COLOUR = (170, 170, 170)  # BGR grey: an observation the filter did not use


def rejected_observations(state: SlamState) -> np.ndarray:
    """Map positions (g, 2) of the observations the estimator's innovation gate refused in
    this update (``SlamState.gated_observations``: range, bearing from the state's pose);
    none when the state does not carry them (an estimator without the gate)."""
    obs = getattr(state, "gated_observations", None)
    if obs is None:
        return np.zeros((0, 2))
    obs = np.asarray(obs, dtype=float).reshape(-1, 2)
    x, y, theta = (float(v) for v in state.pose)
    angle = theta + obs[:, 1]
    return np.column_stack([x + obs[:, 0] * np.cos(angle), y + obs[:, 0] * np.sin(angle)])


def _draw_rejected(c: Canvas, xy: np.ndarray) -> None:
    """A small grey cross at each rejected observation's position, on the floor."""
    uv, _ = c.camera.project(np.column_stack([xy, np.zeros(len(xy))]))
    half = 5 * c.px
    for u, v in uv.tolist():
        if not (math.isfinite(u) and math.isfinite(v)):
            continue
        p = (int(round(u)), int(round(v)))
        for colour, width in (((0, 0, 0), 3 * c.px), (REJECTED_COLOUR, c.px)):
            cv2.line(c.img, (p[0] - half, p[1] - half), (p[0] + half, p[1] + half), colour,
                     width, cv2.LINE_AA)
            cv2.line(c.img, (p[0] - half, p[1] + half), (p[0] + half, p[1] - half), colour,
                     width, cv2.LINE_AA)


def _draw_health(c: Canvas, *, glyphs: Glyphs, lines: Lines, suspects: np.ndarray) -> None:
    """Violating pair lines and glyphs outlined, suspect features ringed and labelled."""
    colour, scene, camera, state = c.settings.colour_violation, c.scene, c.camera, c.state
    if lines.polylines and scene.line_violation.any():
        bad = [lines.polylines[k] for k in np.flatnonzero(scene.line_violation[lines.index])]
        draw.draw_polylines(c.img, bad, colour=colour, thickness=2 * c.px)
    shaded = glyphs.shaded
    if shaded is not None and scene.glyph_violation.any():
        for k in np.flatnonzero(scene.glyph_violation[shaded.index]).tolist():
            shaded.outline(c.img, k, colour=colour, thickness=2 * c.px)
    if len(suspects):
        scale = 0.45 * camera.height / 720
        for fid in suspects.tolist():
            xy = state.landmarks[int(np.flatnonzero(state.landmark_ids == fid)[0])]
            ring = draw.floor_circle(xy, 2.2 * c.settings.cone_radius_m,
                                     z=0.5 * c.settings.cone_height_m)
            polys = draw.project_polyline(camera, ring, closed=True)
            draw.draw_polylines(c.img, polys, colour=colour, thickness=2 * c.px)
            uv, _ = camera.project(ring[:1])
            if np.isfinite(uv).all():
                draw.text(c.img, str(fid), (int(uv[0, 0]) + 4, int(uv[0, 1])), scale=scale,
                          colour=colour)


def _draw_labels(c: Canvas) -> None:
    """Each feature's id beside its cone tip."""
    ids, uv = feature_pixels(c.state, c.camera)
    scale = 0.42 * c.camera.height / 720
    offset = 8 * c.camera.height / 720
    for fid, (u, v) in zip(ids.tolist(), uv.tolist(), strict=True):
        if math.isfinite(u) and math.isfinite(v):
            draw.text(c.img, str(fid), (int(u + offset), int(v - offset)), scale=scale,
                      colour=c.settings.colour_features)


def _draw_roles(c: Canvas, glyphs: Glyphs) -> None:
    """'min' / 'mean' / 'max' beside the minmeanmax glyphs."""
    ie, scene = glyphs.ellipses, c.scene
    scale = 0.42 * c.camera.height / 720
    for g in glyphs.shown.tolist():
        role = int(scene.glyph_role[g])
        if role == ROLE_PAIR:
            continue
        a, b, t = ie.axes[g, 0], ie.axes[g, 1], ie.angle[g]
        half_w = math.sqrt((a * math.cos(t)) ** 2 + (b * math.sin(t)) ** 2)
        u, v = ie.centre[g]
        draw.text(c.img, ROLE_NAMES[role], (int(u + half_w + 4), int(v + 5)), scale=scale)
