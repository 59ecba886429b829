"""The robot's path: the points remembered and their drawing, kept from picture to picture.

A lab leaves the viewer running, and the path grows with every state the viewer takes in
(up to :data:`MAX_POINTS`; beyond, the older half is thinned to every other point). Drawn
whole for every picture — a 2 px anti-aliased polyline, ~1.9 ms per 1000 points — it
became the most expensive part of a picture: a small map is drawn straight onto every
camera frame, so after ~15 min of ``slamlens demo`` (20 000 points) the path alone took
~37 ms of each frame; at n = 1000 it was drawn once per state, ~6 ms after the large
world's seven minutes (``benchmarks/bench_render.py``, "a long run's path").

So each camera view keeps the path drawn on a layer of its own (:func:`draw.new_layer`)
and draws onto it only the segments added since its last picture; the layer is then put
over the picture (a camera frame, or a large state's under-layer) in the box the path
covers (:func:`draw.put_layer`). The same pixels as drawing the path straight onto the
picture, to rounding (the layer holds each anti-aliased segment's cover to 1/255). A trace
starts again from scratch when points were removed (another robot or map, a seq that went
back, thinning) or the view's camera, colour or width changed; a view whose camera moves
with every frame (head-mounted) therefore draws the whole path each time, as before.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass

import cv2
import numpy as np

from slamlens.services.visualiser import draw
from slamlens.services.visualiser.camera_model import CameraModel

MAX_POINTS = 20_000  #: beyond this the older path is thinned (every other point)
MAX_TRACES = 4  #: views' traces kept (distinct cameras, colours, widths), oldest out first


@dataclass
class _Trace:
    """The path as drawn for one view: its layer and how much of the path is on it."""

    generation: int  #: the path's generation it was drawn from
    drawn: int  #: points of the path drawn onto ``layer``
    layer: np.ndarray  #: a layer (BGRA: colour drawn, 4th channel what shows through)
    box: tuple[int, int, int, int] | None = None  #: rows y0:y1, columns x0:x1 drawn on
    open: bool = False  #: a segment ends at the last point drawn (the next one needs no cap)


class Trail:
    """One robot's path (map frame, m) and its traces; shared by the viewer's threads."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._xy = np.empty((256, 2))
        self._count = 0
        #: changes whenever points are removed (a trace must then start again)
        self._generation = 0
        self._robot: str | None = None
        self._seq = -1
        self._epoch: int | None = None
        self._traces: OrderedDict[tuple[object, ...], _Trace] = OrderedDict()

    def points(self) -> np.ndarray:
        """The remembered path (k, 2), a copy."""
        with self._lock:
            return self._xy[:self._count].copy()

    def reset(self, *, forget_robot: bool = False) -> None:
        """Forget the points (and, with ``forget_robot``, whose path and which map it was)."""
        with self._lock:
            self._clear()
            if forget_robot:
                self._epoch = None

    def track(self, robot: str, seq: int, xy: tuple[float, float], epoch: int = 0) -> None:
        """Add the robot's position at state ``seq`` (a later state than the last one)."""
        with self._lock:
            # a new path for another robot, another map (epoch), or — epoch 0, unknown — a
            # seq that went back; the same epoch with a lower seq is a resumed estimator
            if (robot != self._robot or epoch != self._epoch
                    or (epoch == 0 and seq < self._seq)):
                self._clear()
                self._robot, self._epoch = robot, epoch
            if seq <= self._seq:
                return
            self._seq = seq
            if self._count and self._xy[self._count - 1, 0] == xy[0] \
                    and self._xy[self._count - 1, 1] == xy[1]:
                return
            if self._count == len(self._xy):
                self._xy = np.concatenate([self._xy, np.empty_like(self._xy)])
            self._xy[self._count] = xy
            self._count += 1
            if self._count > MAX_POINTS:
                half = self._count // 2
                kept = np.concatenate([self._xy[:half:2], self._xy[half:self._count]])
                self._count = len(kept)
                self._xy[:self._count] = kept
                self._generation += 1

    def _clear(self) -> None:
        self._count, self._seq = 0, -1
        self._generation += 1

    def draw(self, img: np.ndarray, camera: CameraModel, *, colour: draw.BGR,
             thickness: int) -> None:
        """The path over ``img`` (a picture or a layer of ``camera``'s size), through
        ``camera``: what its view's trace lacks is drawn onto it, then it is put over."""
        key = (camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes(),
               camera.T_camera_from_map.tobytes(), colour, thickness)
        with self._lock:
            trace = self._traces.get(key)
            if trace is None or trace.generation != self._generation \
                    or trace.drawn > self._count:
                trace = _Trace(self._generation, 0, draw.new_layer(camera.height,
                                                                   camera.width))
                self._traces[key] = trace
                while len(self._traces) > MAX_TRACES:
                    self._traces.popitem(last=False)
            self._traces.move_to_end(key)
            if self._count - trace.drawn >= 1 and self._count >= 2:
                start = max(trace.drawn - 1, 0)  # the new segments join the last point
                _draw_segments(trace, camera, self._xy[start:self._count],
                               colour=colour, thickness=thickness)
                trace.drawn = self._count
            if trace.box is not None:
                draw.put_layer(img, trace.layer, trace.box)


def _draw_segments(trace: _Trace, camera: CameraModel, xy: np.ndarray, *,
                   colour: draw.BGR, thickness: int) -> None:
    """The path's points ``xy`` (map frame) onto the trace's layer: all of them in one
    polyline if the trace is empty, else the segments after ``xy[0]`` (its last point
    drawn) as one polyline call would have drawn them (:func:`_continue`); the box grown."""
    uv, _ = camera.project(np.column_stack([xy, np.zeros(len(xy))]))
    if trace.drawn == 0:
        polylines = draw.polylines_from_uv(uv)
        draw.draw_polylines(trace.layer, polylines, colour=colour, thickness=thickness)
        trace.open = bool(np.isfinite(uv[-2:]).all())  # the last segment was drawn
    else:
        polylines = _continue(trace, uv, colour=colour, thickness=thickness)
    h, w = trace.layer.shape[:2]
    pad = thickness + 2
    for line in polylines:
        x, y, bw, bh = cv2.boundingRect(line >> draw.SHIFT)
        box = (max(y - pad, 0), min(y + bh + pad, h), max(x - pad, 0), min(x + bw + pad, w))
        if box[0] >= box[1] or box[2] >= box[3]:
            continue  # wholly off the picture
        if trace.box is not None:
            box = (min(box[0], trace.box[0]), max(box[1], trace.box[1]),
                   min(box[2], trace.box[2]), max(box[3], trace.box[3]))
        trace.box = box


#: a segment's ends within this many pixels are drawn exactly as one polyline call would
_EXACT_PX = 30_000  # (OpenCV's 16-bit fixed point in int32: ±32 768 px)


def _continue(trace: _Trace, uv: np.ndarray, *, colour: draw.BGR,
              thickness: int) -> list[np.ndarray]:
    """The segments after ``uv[0]`` (the last point drawn) onto the trace's layer, pixel
    for pixel as ``cv2.polylines`` draws them inside one call over the whole path: a
    segment is its quadrilateral and the round cap at its end, and only a run's first
    segment has a cap at its start (a new polylines call would give each batch's first
    point a second cap, whose anti-aliased rim then darkens by up to 50 levels). This is
    OpenCV's ``ThickLine`` (imgproc/drawing.cpp; tests/unit/test_trail.py holds the two
    equal), in its 16-bit fixed point. Returns the segments drawn, as polylines."""
    ok = np.isfinite(uv).all(axis=1)
    pts = draw.fixed(np.nan_to_num(uv)).tolist()
    half = thickness << 15  # the cap's radius and the half width, 16-bit fixed point
    odd = (thickness & 1) * 65536 * 0.5
    drawn: list[np.ndarray] = []
    for i in range(1, len(pts)):
        if not (ok[i - 1] and ok[i]):
            trace.open = False
            continue
        (u0, v0), (u1, v1) = pts[i - 1], pts[i]
        start_cap = not trace.open
        trace.open = True
        drawn.append(np.array([pts[i - 1], pts[i]], np.int32))
        if max(abs(u0), abs(v0), abs(u1), abs(v1)) > _EXACT_PX << draw.SHIFT:
            # far off the picture: OpenCV's own line (its second cap is out there too)
            cv2.line(trace.layer, (u0, v0), (u1, v1), colour, thickness, cv2.LINE_AA,
                     draw.SHIFT)
            continue
        x0, y0, x1, y1 = u0 << 12, v0 << 12, u1 << 12, v1 << 12  # 4 → 16 fractional bits
        dx, dy = (x0 - x1) * (1.0 / 65536), (y1 - y0) * (1.0 / 65536)
        r = dx * dx + dy * dy
        if abs(r) > _DBL_EPSILON:
            r = (half + odd) / math.sqrt(r)
            px, py = _round(dy * r), _round(dx * r)
            quad = np.array([[x0 + px, y0 + py], [x0 - px, y0 - py], [x1 - px, y1 - py],
                             [x1 + px, y1 + py]], np.int32)
            cv2.fillConvexPoly(trace.layer, quad, colour, cv2.LINE_AA, 16)
        if start_cap:
            cv2.circle(trace.layer, (x0, y0), half, colour, -1, cv2.LINE_AA, 16)
        cv2.circle(trace.layer, (x1, y1), half, colour, -1, cv2.LINE_AA, 16)
    return drawn


_DBL_EPSILON = float(np.finfo(float).eps)


def _round(value: float) -> int:
    """OpenCV's cvRound: to the nearest integer, halves to even."""
    return int(np.rint(value))
