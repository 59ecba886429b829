"""The viewer's picture as a ``visualization_msgs/msg/MarkerArray`` for RViz (pure).

The geometry (pairs of the mode, glyph centres, axes, yaw, flags, colours) is
:mod:`slamlens.common.scene3d`'s; this module turns it into markers in the ``map`` frame
(z up), one namespace per part, ids stable from state to state:

========== ===== ============== ================================================================
namespace  id    type           what
========== ===== ============== ================================================================
robot      0     TRIANGLE_LIST  green cone, its tip at the estimated position
robot      1     ARROW          yellow heading arrow
path       0     LINE_STRIP     the estimated positions so far (thinned beyond a length)
features   0     TRIANGLE_LIST  a cyan cone per feature, tip at its estimate; magenta: suspect
labels     k     TEXT_VIEW_…    each feature's id; k = the feature's index in this map
pairs      0     LINE_LIST      a yellow line per pair drawn (magenta: flagged by the monitor)
ellipsoids key   SPHERE         a red ellipsoid per P_d glyph (magenta: flagged), scaled and
                                turned as scene3d says; key = the pair (all, inter: features
                                of indices a < b give b(b−1)/2 + a) or 3k + role (minmeanmax:
                                the k-th cluster pair's min 0 / mean 1 / max 2)
========== ===== ============== ================================================================

A feature's index is the order in which this map's features were first seen (kept for the
life of the map). What was shown and is gone (a pair no longer drawn, a feature forgotten)
is sent as a DELETE of its id; a new map (another epoch, or seq going back) starts with a
DELETEALL.
"""

from __future__ import annotations

import math
import struct

import numpy as np

from slamlens.common.messages import Health, SlamState
from slamlens.common.scene3d import (
    CONE_HEIGHT_M,
    CONE_RADIUS_M,
    ELLIPSOID,
    FEATURE,
    HEADING,
    LINE,
    MAP_FRAME,
    PATH,
    RGB,
    ROBOT,
    VIOLATION,
    SceneSettings,
    flagged_pairs,
    pair_glyphs,
)
from slamlens.services.ros2.cdr import Template, Writer, repeat
from slamlens.services.ros2.wire import CDR_LE

ARROW, SPHERE, LINE_STRIP, LINE_LIST, TEXT, TRIANGLE_LIST = 0, 2, 4, 5, 9, 11
ADD, DELETE, DELETEALL = 0, 2, 3
IDENTITY = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
CONE_SEGMENTS = 12
TEXT_HEIGHT_M = 0.08
ELLIPSOID_ALPHA = 0.8
WHITE: RGB = (1.0, 1.0, 1.0)


def write_marker(w: Writer, *, stamp_ns: int, ns: str, id: int, type: int,
                 action: int = ADD, pose: tuple[float, ...] = IDENTITY,
                 scale: tuple[float, float, float] = (1.0, 1.0, 1.0),
                 color: tuple[float, ...] = (*WHITE, 1.0), points: np.ndarray | None = None,
                 colors: np.ndarray | None = None, text: str = "", marks: bool = False) -> None:
    """One ``visualization_msgs/msg/Marker`` (humble's and jazzy's, alike); ``marks`` records
    where ``id``, ``pose``, ``scale``, ``color`` and ``text`` are (for :class:`Template`)."""
    def mark(name: str) -> str | None:
        return name if marks else None

    w.stamp(stamp_ns, mark=mark("stamp"))
    w.string(MAP_FRAME)
    w.string(ns)
    w.i32(id, mark=mark("id"))
    w.i32(type)
    w.i32(action)
    w.f64s(pose, mark=mark("pose"))
    w.f64s(scale, mark=mark("scale"))
    w.f32s(color, mark=mark("color"))
    w.i32(0)  # lifetime: 0 = until replaced or deleted
    w.u32(0)
    w.bool(False)  # frame_locked
    w.sequence(np.zeros((0, 3)) if points is None else points, "<f8", 3)
    w.sequence(np.zeros((0, 4)) if colors is None else colors, "<f4", 4)
    w.string("")  # texture_resource
    w.header(0, "")  # texture: sensor_msgs/CompressedImage
    w.string("")
    w.sequence(np.zeros(0, np.uint8), "u1")
    w.sequence(np.zeros((0, 2)), "<f4", 2)  # uv_coordinates
    w.string(text, mark=mark("text"))
    w.string("")  # mesh_resource
    w.string("")  # mesh_file: visualization_msgs/MeshFile
    w.sequence(np.zeros(0, np.uint8), "u1")
    w.bool(False)  # mesh_use_embedded_materials


def _rgba(rgb: RGB, a: float = 1.0) -> tuple[float, float, float, float]:
    return (rgb[0], rgb[1], rgb[2], a)


def yaw_pose(x: float, y: float, z: float, yaw: float) -> tuple[float, ...]:
    return (x, y, z, 0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw))


def _unit_cone(segments: int = CONE_SEGMENTS) -> np.ndarray:
    """Triangles (2·segments, 3 vertices, xyz) of a cone on its tip at the origin, height
    and radius 1: the side, then the top cap."""
    a = np.linspace(0.0, 2 * np.pi, segments + 1)
    rim = np.column_stack([np.cos(a), np.sin(a), np.ones_like(a)])
    tip, top = np.zeros((segments, 3)), np.tile([0.0, 0.0, 1.0], (segments, 1))
    side = np.stack([tip, rim[:-1], rim[1:]], axis=1)
    cap = np.stack([top, rim[1:], rim[:-1]], axis=1)
    return np.concatenate([side, cap])


_CONE = _unit_cone()


def cones(xy: np.ndarray, height: float, radius: float) -> np.ndarray:
    """The triangle vertices (n · 6·segments, 3) of a cone on its tip at each point."""
    unit = (_CONE * np.array([radius, radius, height])).reshape(-1, 3)
    base = np.column_stack([xy, np.zeros(len(xy))])
    return (base[:, None, :] + unit[None, :, :]).reshape(-1, 3)


class _Array:
    """A MarkerArray written marker by marker or in blocks, in order, all stamped alike."""

    def __init__(self, stamp_ns: int) -> None:
        self.stamp = np.array(divmod(stamp_ns, 1_000_000_000), dtype="<i4")
        self.parts: list[bytes] = []
        self.phase = 4  # the body starts with the uint32 count
        self.count = 0

    def one(self, **fields: object) -> None:
        w = Writer(phase=self.phase)
        write_marker(w, stamp_ns=int(self.stamp[0]) * 1_000_000_000
                     + int(self.stamp[1]), **fields)  # type: ignore[arg-type]
        w.align(4)
        self.parts.append(w.bytes())
        self.phase = (self.phase + len(w.buf)) % 8
        self.count += 1

    def many(self, template: Template, count: int, patches: dict[str, np.ndarray]) -> None:
        patches = {"stamp": np.tile(self.stamp, (count, 1)), **patches}
        data, self.phase = repeat(template, count, self.phase, patches)
        self.parts.append(data)
        self.count += count

    def payload(self) -> bytes:
        return CDR_LE + struct.pack("<I", self.count) + b"".join(self.parts)


class MarkerExport:
    """The successive MarkerArrays of one robot's states (module docstring)."""

    def __init__(self, settings: SceneSettings) -> None:
        self.settings = settings
        self._templates: dict[tuple[str, int, int], Template] = {}
        self._index: dict[int, int] = {}  #: feature id → its index in this map
        self._shown: dict[str, np.ndarray] = {}
        self._map: tuple[int, int] | None = None  #: (epoch, seq) of the last state
        self.arrays = 0

    def _template(self, ns: str, type: int, action: int, text_len: int = 0) -> Template:
        key = (ns, type, action, text_len)
        template = self._templates.get(key)  # type: ignore[arg-type]
        if template is None:
            def write(w: Writer) -> None:
                write_marker(w, stamp_ns=0, ns=ns, id=0, type=type,
                             action=action, text="x" * text_len, marks=True)

            template = self._templates[key] = Template(write)  # type: ignore[index]
        return template

    def _new_map(self, state: SlamState) -> bool:
        last, self._map = self._map, (state.epoch, state.seq)
        return last is not None and (state.epoch != last[0] or state.seq < last[1])

    def _indices(self, ids: np.ndarray) -> np.ndarray:
        index = self._index
        for i in ids.tolist():
            if i not in index:
                index[i] = len(index)
        return np.fromiter((index[i] for i in ids.tolist()), dtype=np.int64, count=len(ids))

    def _delete(self, out: _Array, ns: str, now: np.ndarray) -> None:
        before = self._shown.get(ns, np.zeros(0, np.int64))
        self._shown[ns] = now
        if before.shape == now.shape and np.array_equal(before, now):
            return  # the usual case: the same markers as last time (ids unique per ns)
        gone = np.setdiff1d(before, now, assume_unique=True)
        if len(gone):
            out.many(self._template(ns, SPHERE, DELETE), len(gone),
                     {"id": gone.astype("<i4").reshape(-1, 1)})

    def update(self, state: SlamState, *, health: Health | None = None,
               path_xy: np.ndarray | None = None) -> bytes:
        """The MarkerArray of ``state`` (CDR payload)."""
        from slamlens.services.ros2.cdr import stamp_ns as to_ns

        stamp = to_ns(state.stamp)
        out = _Array(stamp)
        if self._new_map(state):
            out.one(ns="", id=0, type=SPHERE, action=DELETEALL)
            self._index.clear()
            self._shown.clear()
        x, y, theta = (float(v) for v in state.pose)
        out.one(ns="robot", id=0, type=TRIANGLE_LIST,
                points=cones(np.array([[x, y]]), 1.4 * CONE_HEIGHT_M, 1.4 * CONE_RADIUS_M),
                color=_rgba(ROBOT))
        out.one(ns="robot", id=1, type=ARROW,
                pose=yaw_pose(x, y, 0.01, theta), scale=(0.22, 0.02, 0.02),
                color=_rgba(HEADING))
        self._path(out, path_xy)
        self._features(out, state, health)
        self._pairs(out, state, health)
        self.arrays += 1
        return out.payload()

    def _path(self, out: _Array, path_xy: np.ndarray | None) -> None:
        if path_xy is not None and len(path_xy) >= 2:
            points = np.column_stack([path_xy, np.zeros(len(path_xy))])
            out.one(ns="path", id=0, type=LINE_STRIP, points=points,
                    scale=(0.015, 0.0, 0.0), color=_rgba(PATH))
            self._shown["path"] = np.zeros(1, np.int64)
        else:
            self._delete(out, "path", np.zeros(0, np.int64))

    def _features(self, out: _Array, state: SlamState,
                  health: Health | None) -> None:
        n = state.n
        xy = state.landmarks.reshape(-1, 2)
        index = self._indices(state.landmark_ids)
        if n:
            suspect = np.isin(state.landmark_ids, health.suspects) if health is not None \
                else np.zeros(n, dtype=bool)
            colours = np.where(suspect[:, None], _rgba(VIOLATION), _rgba(FEATURE))
            per_cone = len(_CONE) * 3
            out.one(ns="features", id=0, type=TRIANGLE_LIST,
                    points=cones(xy, CONE_HEIGHT_M, CONE_RADIUS_M),
                    colors=np.repeat(colours, per_cone, axis=0), color=_rgba(FEATURE))
            self._shown["features"] = np.zeros(1, np.int64)
        else:
            self._delete(out, "features", np.zeros(0, np.int64))
        labels = [str(i) for i in state.landmark_ids.tolist()]
        lengths = np.array([len(s) for s in labels], dtype=np.int64)
        poses = np.zeros((n, 7))
        poses[:, :2], poses[:, 2], poses[:, 6] = xy, CONE_HEIGHT_M + 0.05, 1.0
        for length in np.unique(lengths).tolist():
            rows = np.flatnonzero(lengths == length)
            text = np.array([labels[k].encode() for k in rows.tolist()], dtype=f"S{length}")
            out.many(self._template("labels", TEXT, ADD, length), len(rows), {
                "id": index[rows].astype("<i4").reshape(-1, 1),
                "pose": poses[rows], "scale": np.tile([0.0, 0.0, TEXT_HEIGHT_M], (len(rows), 1)),
                "color": np.tile(np.array(_rgba(WHITE), "<f4"), (len(rows), 1)),
                "text": text.view(np.uint8).reshape(len(rows), length)})
        self._delete(out, "labels", np.sort(index))

    def _pairs(self, out: _Array, state: SlamState, health: Health | None) -> None:
        s = self.settings
        glyphs = pair_glyphs(state, s, flagged_pairs(health))
        segs = glyphs.lines_xy.reshape(-1, 2)
        if len(segs):
            colours = np.where(np.repeat(glyphs.line_flagged, 2)[:, None], _rgba(VIOLATION),
                               _rgba(LINE))
            out.one(ns="pairs", id=0, type=LINE_LIST,
                    points=np.column_stack([segs, np.zeros(len(segs))]), colors=colours,
                    scale=(0.01, 0.0, 0.0), color=_rgba(LINE))
            self._shown["pairs"] = np.zeros(1, np.int64)
        else:
            self._delete(out, "pairs", np.zeros(0, np.int64))
        g = len(glyphs.centres)
        if s.mode == "minmeanmax":
            c = g // 3
            ids = 3 * np.tile(np.arange(c), 3) + glyphs.role - 1
        else:
            index = self._indices(state.landmark_ids)
            a, b = index[glyphs.pairs[:, 0]], index[glyphs.pairs[:, 1]]
            lo, hi = np.minimum(a, b), np.maximum(a, b)
            ids = hi * (hi - 1) // 2 + lo
        poses = np.zeros((g, 7))
        poses[:, :3] = glyphs.centres
        poses[:, 5], poses[:, 6] = np.sin(0.5 * glyphs.yaw), np.cos(0.5 * glyphs.yaw)
        colours = np.where(glyphs.flagged[:, None], _rgba(VIOLATION, ELLIPSOID_ALPHA),
                           _rgba(ELLIPSOID, ELLIPSOID_ALPHA)).astype("<f4")
        out.many(self._template("ellipsoids", SPHERE, ADD), g, {
            "id": ids.astype("<i4").reshape(-1, 1), "pose": poses,
            "scale": 2.0 * glyphs.axes, "color": colours})
        self._delete(out, "ellipsoids", np.sort(ids.astype(np.int64)))
