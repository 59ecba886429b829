"""Drawing primitives for the renderer: floor polylines, cones, shaded glyphs, text boxes.

Every function draws onto a BGR uint8 image in place. Coordinates go to OpenCV as int32
with ``SHIFT`` fractional bits, so sub-pixel positions survive. Items whose projection
fails (behind the camera) are skipped or clipped at the near plane, never drawn wrongly.

A *layer* (:func:`new_layer`) is a BGRA picture to draw on instead, once, and put over
many camera frames (:class:`Overlay`): its BGR is what was drawn, already weighted by its
coverage, and its 4th channel how much of the picture below still shows (255: all, 0:
none). Every drawing step is a blend ``dst·(1 − α) + colour·α`` with the same α on every
channel, and OpenCV draws a 3-component colour on 4 channels as (b, g, r, 0): the 4th
channel ends as 255 × the product of (1 − α) over the steps, so frame × it / 255 + BGR is
the picture drawn over that frame (the same to ±3 levels of OpenCV's integer rounding on
anti-aliased edges; exact where nothing, or something opaque, was drawn). Text is the
exception (OpenCV's anti-aliased text does not blend the 4th channel so):
:func:`put_text` draws it through a coverage mask on a layer.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from slamlens.services.visualiser.camera_model import NEAR_M, CameraModel
from slamlens.services.visualiser.glyphs import ImageEllipses, ellipse_polygons, unit_circle

SHIFT = 4  #: fractional bits of the fixed-point coordinates given to OpenCV
_ONE = 1 << SHIFT
_LIMIT_PX = 2.0e5  # clamp before fixed point: far-off points must not overflow int32
LIGHT_DIR = np.array([-0.45, -0.89])  # image-space direction towards the light (up, left)


BGR = tuple[int, int, int]


def fixed(uv: np.ndarray) -> np.ndarray:
    """Float pixels → OpenCV fixed-point int32 (``SHIFT`` bits)."""
    return np.round(np.clip(uv, -_LIMIT_PX, _LIMIT_PX) * _ONE).astype(np.int32)


def shade(colour: BGR, factor: float, white: float = 0.0) -> BGR:
    """``colour`` darkened by ``factor`` then mixed with ``white`` of white."""
    c = np.clip(np.asarray(colour, dtype=float) * factor, 0, 255)
    c = c + white * (255.0 - c)
    return int(c[0]), int(c[1]), int(c[2])


def line_type_for(count: int, *, limit: int) -> int:
    """Anti-aliased up to ``limit`` items, plain 8-connected beyond (keeps frames on time)."""
    return cv2.LINE_AA if count <= limit else cv2.LINE_8


# -- floor polylines --------------------------------------------------------------------
def project_segments(camera: CameraModel, p0: np.ndarray, p1: np.ndarray, *,
                     subdivisions: int | None = None) -> tuple[list[np.ndarray], np.ndarray]:
    """Segments p0→p1 (m, 3) in the map frame as image polylines (fixed point).

    Segments are clipped at the camera's near plane; wholly hidden ones are dropped, so
    the index (into p0) of each returned polyline comes with them. With lens distortion
    each segment is subdivided so that its image curves as the lens bends it.
    """
    if len(p0) == 0:
        return [], np.zeros(0, dtype=np.int64)
    T = camera.T_camera_from_map
    c0 = p0 @ T[:3, :3].T + T[:3, 3]
    c1 = p1 @ T[:3, :3].T + T[:3, 3]
    z0, z1 = c0[:, 2], c1[:, 2]
    near = 2 * NEAR_M
    keep = (z0 > near) | (z1 > near)
    c0, c1, z0, z1 = c0[keep], c1[keep], z0[keep], z1[keep]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip((near - z0) / (z1 - z0), 0.0, 1.0)
    c0 = np.where((z0 < near)[:, None], c0 + t[:, None] * (c1 - c0), c0)
    c1 = np.where((z1 < near)[:, None], c1 + t[:, None] * (c0 - c1), c1)
    if subdivisions is None:
        subdivisions = 8 if camera.has_distortion else 1
    s = np.linspace(0.0, 1.0, subdivisions + 1)
    pts = c0[:, None, :] + s[None, :, None] * (c1 - c0)[:, None, :]
    uv = _camera_points_to_pixels(camera, pts.reshape(-1, 3))
    return list(fixed(uv).reshape(len(c0), subdivisions + 1, 2)), np.flatnonzero(keep)


def _camera_points_to_pixels(camera: CameraModel, pc: np.ndarray) -> np.ndarray:
    xy = pc[:, :2] / pc[:, 2:3]
    if camera.has_distortion:
        xy = camera.distort_normalised(xy)
    K = camera.K
    return np.column_stack([K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2],
                            K[1, 1] * xy[:, 1] + K[1, 2]])


def project_polyline(camera: CameraModel, points_map: np.ndarray, *,
                     closed: bool = False) -> list[np.ndarray]:
    """A map-frame polyline (k, 3) as image polylines, split where points are unprojectable."""
    if len(points_map) < 2:
        return []
    uv, _ = camera.project(points_map)
    return polylines_from_uv(uv, closed=closed)


def polylines_from_uv(uv: np.ndarray, *, closed: bool = False) -> list[np.ndarray]:
    """Projected points (k, 2) of one polyline as fixed-point image polylines, split where
    a point is unprojectable (NaN); ``closed`` closes it when every point projected."""
    if len(uv) < 2:
        return []
    ok = np.isfinite(uv).all(axis=1)
    if ok.all():
        pts = fixed(uv)
        return [np.concatenate([pts, pts[:1]]) if closed else pts]
    runs, start = [], None
    for k, good in enumerate(ok.tolist() + [False]):
        if good and start is None:
            start = k
        elif not good and start is not None:
            if k - start >= 2:
                runs.append(fixed(uv[start:k]))
            start = None
    return runs


def draw_polylines(img: np.ndarray, polylines: list[np.ndarray], *, colour: BGR,
                   thickness: int, line_type: int = cv2.LINE_AA) -> None:
    """Open fixed-point polylines (from :func:`project_segments` / :func:`project_polyline`)."""
    if polylines:
        cv2.polylines(img, polylines, False, colour, thickness, line_type, SHIFT)


def floor_circle(centre_xy: np.ndarray, radius_m: float, *, z: float = 0.0,
                 vertices: int = 32) -> np.ndarray:
    """(vertices, 3) points of a horizontal circle in the map frame."""
    circle = unit_circle(vertices) * radius_m + np.asarray(centre_xy, dtype=float)[:2]
    return np.column_stack([circle, np.full(vertices, z)])


# -- cones ------------------------------------------------------------------------------
class Cones:
    """Projected upright cones, tip down on the floor, flat base up (paper §3.2 markers)."""

    VERTICES = 20
    DOT_BELOW_PX = 5.0  #: cones whose picture is narrower than this are drawn as a dot
    FULL_DETAIL = 300  #: more cones than this: the lit cap and the tip only (no side, edge)

    def __init__(self, camera: CameraModel, tips_xy: np.ndarray, *, height_m: float,
                 radius_m: float, colour: BGR) -> None:
        self._side, self._cap = shade(colour, 0.6), shade(colour, 1.0)
        self._edge, self._dot = shade(colour, 0.45), shade(colour, 0.3)
        tips_xy = np.asarray(tips_xy, dtype=float).reshape(-1, 2)
        c = len(tips_xy)
        circle = unit_circle(self.VERTICES) * radius_m
        base = np.empty((c, self.VERTICES, 3))
        base[:, :, :2] = tips_xy[:, None, :] + circle[None]
        base[:, :, 2] = height_m
        tips = np.column_stack([tips_xy, np.zeros(c)])
        uv, depth = camera.project(np.concatenate([tips, base.reshape(-1, 3)]))
        self.tip_uv = uv[:c]
        base_uv = uv[c:].reshape(c, self.VERTICES, 2)
        self.valid = np.isfinite(uv[:c]).all(axis=1) & np.isfinite(base_uv).all(axis=(1, 2))
        mid = np.column_stack([tips_xy, np.full(c, height_m / 2)])
        self.depth = camera.to_camera(mid)[:, 2] if c else np.zeros(0)
        self.cap_visible = bool(camera.centre_map[2] > height_m)
        self._tip = fixed(np.nan_to_num(self.tip_uv))
        self._base = fixed(np.nan_to_num(base_uv))
        # level of detail: a cone a few pixels wide is drawn as one dot (a large map shows
        # hundreds of them), and one wholly off the picture not at all
        with np.errstate(invalid="ignore"):
            # (c, 2, V): NumPy reduces over a contiguous last axis ~6× faster than over
            # the middle one (0.1 against 0.8 ms for 1000 cones)
            around = np.ascontiguousarray(base_uv.transpose(0, 2, 1))
            lo = np.minimum(around.min(axis=2), self.tip_uv)
            hi = np.maximum(around.max(axis=2), self.tip_uv)
        extent = (hi - lo).max(axis=1) if c else np.zeros(0)
        self.valid &= ~((hi[:, 0] < 0) | (hi[:, 1] < 0) | (lo[:, 0] >= camera.width)
                        | (lo[:, 1] >= camera.height)) if c else self.valid
        self._dot_radius = (np.where(extent < self.DOT_BELOW_PX, np.maximum(extent / 2, 1.5),
                                     0.0) * _ONE).astype(np.int64).tolist() if c else []
        self._dot_centre = [tuple(p) for p in fixed(np.nan_to_num(
            (lo + hi) / 2)).tolist()] if c else []
        self._simple = c > self.FULL_DETAIL and self.cap_visible

    def __len__(self) -> int:
        return len(self.depth)

    def draw(self, img: np.ndarray, k: int) -> None:
        """Draw cone ``k``: shaded side (hull of tip and base), lit cap, tip dot."""
        if not self.valid[k]:
            return
        if self._dot_radius[k] > 0:
            cv2.circle(img, self._dot_centre[k], self._dot_radius[k], self._cap, -1,
                       cv2.LINE_AA, SHIFT)
            return
        base = self._base[k]
        if self._simple:  # hundreds of cones: a third of the drawing calls
            cv2.fillConvexPoly(img, base, self._cap, cv2.LINE_AA, SHIFT)
            cv2.circle(img, tuple(self._tip[k].tolist()), 2 * _ONE, self._dot, -1,
                       cv2.LINE_AA, SHIFT)
            return
        hull = cv2.convexHull(np.concatenate([base, self._tip[k:k + 1]]))
        cv2.fillConvexPoly(img, hull, self._side, cv2.LINE_AA, SHIFT)
        if self.cap_visible:
            cv2.fillConvexPoly(img, base, self._cap, cv2.LINE_AA, SHIFT)
            cv2.polylines(img, [base], True, self._edge, 1, cv2.LINE_AA, SHIFT)
        # The tip is the estimate itself: mark it even when the cap hides it (view from above).
        cv2.circle(img, tuple(self._tip[k].tolist()), 2 * _ONE, self._dot, -1,
                   cv2.LINE_AA, SHIFT)


# -- glyphs -----------------------------------------------------------------------------
#: level of detail by projected major semi-axis: (below px, shading layers, polygon vertices);
#: the vertex counts keep the polygon within half a pixel of the true ellipse
GLYPH_LOD = ((2.5, 1, 12), (20.0, 2, 20), (60.0, 3, 24), (150.0, 5, 40), (np.inf, 8, 96))


def shading_profile(layers: int) -> list[tuple[float, float, float]]:
    """(scale, colour factor, white) of each nested layer, rim first, highlight last.

    A lit-sphere look: a dark rim (which also separates overlapping glyphs), the body
    colour, then a whitened highlight shifted towards the light.
    """
    if layers == 1:
        return [(1.0, 0.8, 0.0)]
    if layers == 2:
        return [(1.0, 0.55, 0.0), (0.62, 1.0, 0.1)]
    out = []
    for layer in range(layers):
        t = layer / (layers - 1)
        out.append((1.0 - 0.75 * t, 0.5 + 0.5 * min(1.0, t / 0.6),
                    0.45 * max(0.0, (t - 0.5) / 0.5) ** 1.2))
    return out


class ShadedEllipses:
    """Image ellipses as nested polygons shaded darker (rim) to lighter (lit highlight).

    Nested ellipses are shifted towards ``LIGHT_DIR`` so the glyph reads as a lit solid.
    Level of detail (``GLYPH_LOD``): tiny glyphs get one or two layers and few vertices,
    big ones a smoother gradient and rounder outlines.
    """

    def __init__(self, ie: ImageEllipses, index: np.ndarray, *, max_axis_px: float,
                 colour: BGR) -> None:
        self.index = np.asarray(index, dtype=np.int64)
        g = len(self.index)
        centre = ie.centre[self.index]
        axes = np.minimum(ie.axes[self.index], max_axis_px)
        angle = ie.angle[self.index]
        level = np.searchsorted(np.array([lod[0] for lod in GLYPH_LOD]), axes[:, 0],
                                side="right")
        # Polygons per level and layer; glyph k is row _row[k] of level _level[k].
        self._polys: dict[int, list[list[np.ndarray]]] = {}
        self._colours: dict[int, list[BGR]] = {}
        row = np.zeros(g, dtype=np.int64)
        for lv in np.unique(level).tolist():
            _, layers, vertices = GLYPH_LOD[lv]
            sel = np.flatnonzero(level == lv)
            row[sel] = np.arange(len(sel))
            profile = shading_profile(layers)
            self._colours[lv] = [shade(colour, f, w) for _, f, w in profile]
            polys = []
            for scale, _, _ in profile:
                offset = (1.0 - scale) * 0.55 * axes[sel, 1:2] * LIGHT_DIR  # stays inside
                polygons = ellipse_polygons(centre[sel] + offset, scale * axes[sel],
                                            angle[sel], vertices=vertices)
                polys.append(list(fixed(polygons)))
            self._polys[lv] = polys
        self._level = level.tolist()
        self._row = row.tolist()

    def draw(self, img: np.ndarray, k: int, *, line_type: int) -> None:
        """Draw glyph ``k`` (a position in ``index``); inner layers with ``line_type``."""
        lv, r = self._level[k], self._row[k]
        polys, colours = self._polys[lv], self._colours[lv]
        cv2.fillConvexPoly(img, polys[0][r], colours[0], cv2.LINE_AA, SHIFT)
        for layer in range(1, len(polys)):
            cv2.fillConvexPoly(img, polys[layer][r], colours[layer], line_type, SHIFT)

    def outline(self, img: np.ndarray, k: int, *, colour: BGR, thickness: int) -> None:
        """The rim of glyph ``k`` in ``colour`` (a violation mark)."""
        polygon = self._polys[self._level[k]][0][self._row[k]]
        cv2.polylines(img, [polygon], True, colour, thickness, cv2.LINE_AA, SHIFT)


# -- layers -----------------------------------------------------------------------------
def new_layer(height: int, width: int) -> np.ndarray:
    """An empty layer (module docstring): nothing drawn, the picture below shows."""
    layer = np.zeros((height, width, 4), np.uint8)
    layer[:, :, 3] = 255
    return layer


def is_layer(img: np.ndarray) -> bool:
    return img.ndim == 3 and img.shape[2] == 4


class Overlay:
    """A finished layer, ready to be put over pictures of its size (module docstring).

    Only the rows and columns where something was drawn are kept and blended."""

    def __init__(self, layer: np.ndarray) -> None:
        self.shape = layer.shape[:2]
        alpha = cv2.extractChannel(layer, 3)
        drawn = cv2.threshold(alpha, 254, 255, cv2.THRESH_BINARY_INV)[1]  # alpha < 255
        x, y, w, h = cv2.boundingRect(drawn)
        if w == 0 or h == 0:
            self.box: tuple[int, int, int, int] | None = None
            self._keep: np.ndarray = np.zeros((0, 0, 3), np.uint8)
            self._add: np.ndarray = self._keep
            return
        self.box = (y, y + h, x, x + w)
        self._keep = cv2.cvtColor(alpha[y:y + h, x:x + w], cv2.COLOR_GRAY2BGR)
        self._add = cv2.cvtColor(layer[y:y + h, x:x + w], cv2.COLOR_BGRA2BGR)

    @property
    def nbytes(self) -> int:
        return self._keep.nbytes + self._add.nbytes

    def put_over(self, img: np.ndarray) -> None:
        """Blend onto ``img`` (BGR uint8 of the layer's size) in place."""
        if self.box is None:
            return
        y0, y1, x0, x1 = self.box
        out = cv2.multiply(img[y0:y1, x0:x1], self._keep, scale=1.0 / 255.0)
        cv2.add(out, self._add, dst=out)
        img[y0:y1, x0:x1] = out


def put_layer(img: np.ndarray, layer: np.ndarray, box: tuple[int, int, int, int]) -> None:
    """``layer`` over ``img`` in ``box`` (rows y0:y1, columns x0:x1), in place: ``img`` a
    picture (BGR) or another layer of the same size (module docstring). Over a layer, what
    shows through both is what showed through each: the 4th channels multiply."""
    y0, y1, x0, x1 = box
    src, dst = layer[y0:y1, x0:x1], img[y0:y1, x0:x1]
    through = src[:, :, 3]
    if is_layer(img):
        keep = cv2.merge([through] * 4)
        add = src.copy()
        add[:, :, 3] = 0
    else:
        keep = cv2.cvtColor(through, cv2.COLOR_GRAY2BGR)
        add = cv2.cvtColor(src, cv2.COLOR_BGRA2BGR)
    out = cv2.multiply(dst, keep, scale=1.0 / 255.0)
    cv2.add(out, add, dst=out)
    img[y0:y1, x0:x1] = out


def _blend_mask(roi: np.ndarray, mask: np.ndarray, colour: BGR) -> None:
    """``colour`` over ``roi`` (a layer's) with coverage ``mask`` (0–255), in place."""
    m = mask.astype(np.uint16)[:, :, None]
    paint = np.array([*colour, 0], np.uint16)
    roi[:] = ((roi.astype(np.uint16) * (255 - m) + paint * m + 127) // 255).astype(np.uint8)


# -- text -------------------------------------------------------------------------------
FONT = cv2.FONT_HERSHEY_SIMPLEX


@lru_cache(maxsize=4096)
def text_size(message: str, scale: float, thickness: int = 1,
              font: int = FONT) -> tuple[tuple[int, int], int]:
    """``cv2.getTextSize`` (remembered: a legend asks for the same texts every picture)."""
    (w, h), base = cv2.getTextSize(message, font, scale, thickness)
    return (w, h), base


def put_text(img: np.ndarray, message: str, org: tuple[int, int], scale: float,
             colour: BGR, thickness: int = 1, font: int = FONT) -> None:
    """``cv2.putText`` (anti-aliased), onto a picture or a layer (module docstring)."""
    if not is_layer(img):
        cv2.putText(img, message, org, font, scale, colour, thickness, cv2.LINE_AA)
        return
    (w, h), base = text_size(message, scale, thickness, font)
    pad = thickness + 2
    x0, y0 = max(org[0] - pad, 0), max(org[1] - h - pad, 0)
    x1 = min(org[0] + w + pad, img.shape[1])
    y1 = min(org[1] + base + pad, img.shape[0])
    if x1 <= x0 or y1 <= y0:
        return
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.putText(mask, message, (org[0] - x0, org[1] - y0), font, scale, 255, thickness,
                cv2.LINE_AA)
    _blend_mask(img[y0:y1, x0:x1], mask, colour)


def text(img: np.ndarray, message: str, org: tuple[int, int], *, scale: float,
         colour: BGR = (255, 255, 255), thickness: int = 1) -> None:
    """Text with a dark halo, legible over any picture."""
    x, y = org
    # Halo by shifted copies: a thicker stroke would also widen OpenCV's glyph advance.
    for dx, dy in ((-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (1, 1), (-1, 1), (1, -1)):
        put_text(img, message, (x + dx, y + dy), scale, (0, 0, 0), thickness)
    put_text(img, message, org, scale, colour, thickness)


def text_box(img: np.ndarray, rows: list[list[tuple[str, BGR | None]]], *,
             origin: tuple[int, int] = (10, 10), scale: float = 0.5) -> None:
    """A translucent dark box of text rows; a row is [(text, swatch colour or None), …]."""
    if not rows:
        return
    (_, th), base = text_size("Ag", scale)
    line_h = th + base + 6
    swatch = th + 2
    widths = []
    for row in rows:
        w = 0
        for message, colour in row:
            w += (swatch + 4 if colour is not None else 0) + text_size(
                message, scale)[0][0] + 10
        widths.append(w)
    x0, y0 = origin
    x1 = min(img.shape[1] - 1, x0 + max(widths) + 10)
    y1 = min(img.shape[0] - 1, y0 + line_h * len(rows) + 8)
    if x1 <= x0 or y1 <= y0:
        return
    roi = img[y0:y1, x0:x1]
    # darken to ~30 % (on a layer: its drawing and what shows through it alike)
    roi[:] = (roi.astype(np.uint16) * 2 // 7).astype(np.uint8)
    y = y0 + 6 + th
    for row in rows:
        x = x0 + 8
        for message, colour in row:
            if colour is not None:
                cv2.rectangle(img, (x, y - th), (x + swatch, y + 2), colour, -1)
                x += swatch + 4
            put_text(img, message, (x, y), scale, (235, 235, 235))
            x += text_size(message, scale)[0][0] + 10
        y += line_h
