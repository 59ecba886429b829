"""The synthetic camera: a virtual pinhole view of the arena rendered from ground truth.

It is the reference for registration accuracy: the camera's intrinsics ``K`` and pose
``T_world_from_camera`` are known exactly, so whatever the registration recovers from its
pictures can be compared with the truth. With the simulator, world = map (the map frame is
the robot's start pose), so the true ``T_camera_from_map`` is ``inv(T_world_from_camera)``.

What is drawn (z up, metres, world frame):

* a procedural floor (tiles, grout, blotches and grain; deterministic for a seed),
* the landmarks as shaded coloured posts,
* the robot at its true pose: a grey cylinder with a yellow heading wedge and its fiducial
  marker flat on top (docs/protocol.md: marker x = robot forward, marker y = robot left, face up),
  with a white quiet zone,
* optionally fixed world markers (the head-mounted camera's board).

Markers are warped with ``cv2.warpPerspective`` into a small supersampled patch and area-
averaged down, so their edges sit where the projection puts them (sub-pixel exact).
The floor, posts and board form a cached static layer for a fixed camera; each frame only
copies it, draws the robot, and applies lighting, blur and noise. The renderer is a pure
pinhole: it ignores distortion (the synthetic calibration has none).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from slamlens.common.geometry import T_from_pose2, invert_T, make_T, rot_z, transform_points

#: BGR colours of the scene
FLOOR_TONES = ((178, 186, 196), (152, 162, 174))
GROUT_BGR = (110, 116, 122)
CONCRETE_BGR = (120, 124, 128)
WALL_BGR = (200, 196, 190)
ROBOT_SIDE_BGR = (60, 60, 64)
ROBOT_TOP_BGR = (92, 92, 98)
HEADING_BGR = (0, 210, 240)
POST_BGR = ((40, 110, 230), (200, 120, 30), (60, 170, 60), (160, 60, 170), (30, 180, 200))
LIGHT_DIR = np.array([0.35, -0.45, 0.82]) / np.linalg.norm([0.35, -0.45, 0.82])
Pose2 = Sequence[float] | np.ndarray  #: planar pose (x m, y m, θ rad)
QUIET_ZONE_MODULES = 1.5  #: white border around every marker, in marker modules
NEAR_M = 0.05  #: faces with a vertex closer than this to the camera are not drawn


# ---------------------------------------------------------------------------------------
# Settings
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SceneSettings:
    """What the arena looks like. Lengths in metres, world (= map) frame."""

    arena_xy: tuple[float, float, float, float] = (-1.0, -1.0, 2.0, 2.0)  #: xmin, ymin, xmax, ymax
    robot_radius_m: float = 0.25  #: body radius (a Pioneer-sized disc)
    landmark_radius_m: float = 0.04
    landmark_height_m: float = 0.25
    dictionary: str = "apriltag_36h11"  #: the robot marker's dictionary
    marker_id: int = 0
    marker_size_m: float = 0.2  #: side of the marker's black square
    marker_offset_xyz: tuple[float, float, float] = (0.0, 0.0, 0.2)  #: marker centre, robot frame
    floor_tile_m: float = 0.3
    floor_margin_m: float = 2.0  #: textured floor beyond the arena; concrete further out
    texture_m_per_px: float = 0.004
    seed: int = 0  #: floor texture and sensor noise


@dataclass(frozen=True)
class ImagingSettings:
    """Optics and sensor effects applied after drawing (order: lighting, blur, noise)."""

    noise_sigma: float = 0.0  #: Gaussian sensor noise, grey levels
    blur_kernel: int = 0  #: Gaussian blur kernel size in pixels (odd; 0 or 1 = none)
    gain: float = 1.0  #: brightness factor
    offset: float = 0.0  #: brightness offset, grey levels (rounded to an integer)
    gradient: float = 0.0  #: relative brightness change from the left to the right edge


@dataclass(frozen=True)
class WorldMarker:
    """A fixed marker in the world (head-mounted board), corners TL, TR, BR, BL (OpenCV)."""

    marker_id: int
    corners_world: np.ndarray  #: (4, 3) metres
    dictionary: str = "apriltag_36h11"


# ---------------------------------------------------------------------------------------
# Camera poses
# ---------------------------------------------------------------------------------------


def overhead_pose(*, centre_xy: Sequence[float], height_m: float,
                  yaw_deg: float = 0.0) -> np.ndarray:
    """T_world_from_camera looking straight down from ``height_m`` above ``centre_xy``.

    With ``yaw_deg`` = 0, image right = world +x and image up = world +y (the picture reads
    like a map); a yaw turns the camera about the vertical, as a real mount would be.
    """
    R = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # columns: x_c, y_c, z_c
    return make_T(rot_z(math.radians(yaw_deg)) @ R,
                  np.array([centre_xy[0], centre_xy[1], height_m]))


def look_at(eye: Sequence[float], target: Sequence[float]) -> np.ndarray:
    """T_world_from_camera of an upright camera at ``eye`` looking at ``target`` (z up)."""
    eye_w, target_w = np.asarray(eye, float), np.asarray(target, float)
    z_c = target_w - eye_w
    z_c /= np.linalg.norm(z_c)
    x_c = np.cross(z_c, [0.0, 0.0, 1.0])
    if np.linalg.norm(x_c) < 1e-9:  # looking straight down or up: pick world +x as right
        x_c = np.array([1.0, 0.0, 0.0])
    x_c /= np.linalg.norm(x_c)
    y_c = np.cross(z_c, x_c)
    return make_T(np.column_stack([x_c, y_c, z_c]), eye_w)


def orbit_pose(t_s: float, *, centre_xy: Sequence[float], radius_m: float = 3.0,
               height_m: float = 2.5, period_s: float = 60.0) -> np.ndarray:
    """A head-mounted camera walking slowly around the arena, looking at its centre.

    Starts on the −y side (looking towards +y) and goes anticlockwise once per ``period_s``.
    """
    phi = -math.pi / 2 + 2.0 * math.pi * t_s / period_s
    eye = (centre_xy[0] + radius_m * math.cos(phi), centre_xy[1] + radius_m * math.sin(phi),
           height_m)
    return look_at(eye, (centre_xy[0], centre_xy[1], 0.0))


def stereo_poses(T_world_from_camera: np.ndarray, baseline_m: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(left, right) camera poses ``baseline_m`` apart along the camera's x axis."""
    half = baseline_m / 2.0
    return (T_world_from_camera @ make_T(np.eye(3), np.array([-half, 0.0, 0.0])),
            T_world_from_camera @ make_T(np.eye(3), np.array([half, 0.0, 0.0])))


def fit_hfov_deg(width: int, height: int, *, arena_xy: Sequence[float], height_m: float,
                 margin_m: float = 0.2) -> float:
    """Horizontal field of view that fits ``arena_xy`` (+ margin) into an overhead view."""
    half_x = (arena_xy[2] - arena_xy[0]) / 2.0 + margin_m
    half_y = (arena_xy[3] - arena_xy[1]) / 2.0 + margin_m
    f_px = min(width / 2.0 * height_m / half_x, height / 2.0 * height_m / half_y)
    return math.degrees(2.0 * math.atan(width / 2.0 / f_px))


def arena_centre(arena_xy: Sequence[float]) -> tuple[float, float]:
    return ((arena_xy[0] + arena_xy[2]) / 2.0, (arena_xy[1] + arena_xy[3]) / 2.0)


def robot_marker_corners_world(pose: Pose2, *, size_m: float,
                               offset_xyz: Sequence[float], scale: float = 1.0) -> np.ndarray:
    """World corners (TL, TR, BR, BL as OpenCV orders them) of the robot's marker.

    Marker frame (OpenCV): x right of the marker image, y up the image, z out of the face;
    docs/protocol.md aligns it with the robot: image right = robot forward, image up = robot left.
    ``scale`` > 1 gives the outer corners of a border around the marker.
    """
    h = size_m * scale / 2.0
    corners_marker = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    T_world_from_marker = T_from_pose2(np.asarray(pose, float)) @ make_T(
        np.eye(3), np.asarray(offset_xyz, float))
    return transform_points(T_world_from_marker, corners_marker)


# ---------------------------------------------------------------------------------------
# Pure drawing helpers
# ---------------------------------------------------------------------------------------


def _project(K: np.ndarray, T_camera_from_world: np.ndarray, points_world: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection: (uv (N,2) px, depth (N,) m)."""
    p = transform_points(T_camera_from_world, points_world)
    z = p[:, 2]
    safe = np.where(z > 1e-9, z, 1e-9)
    uv = np.column_stack([K[0, 0] * p[:, 0] / safe + K[0, 1] * p[:, 1] / safe + K[0, 2],
                          K[1, 1] * p[:, 1] / safe + K[1, 2]])
    return uv, z


@lru_cache(maxsize=16)
def _marker_bgra(dictionary: str, marker_id: int, module_px: int = 16) -> np.ndarray:
    """The marker image with its white quiet zone, BGRA, opaque; read-only."""
    from slamlens.services.registration.markers import get_dictionary

    d = get_dictionary(dictionary)  # a built-in name or a custom FILE.yml
    bits = d.markerSize + 2  # data bits plus the black border
    side = bits * module_px
    marker = cv2.aruco.generateImageMarker(d, marker_id, side, borderBits=1)
    pad = int(round(QUIET_ZONE_MODULES * module_px))
    full = cv2.copyMakeBorder(marker, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=255)
    bgra = cv2.cvtColor(full, cv2.COLOR_GRAY2BGRA)
    bgra.setflags(write=False)
    return bgra


def quiet_zone_scale(dictionary: str) -> float:
    """Outer size of marker + white border relative to the black square."""
    from slamlens.services.registration.markers import get_dictionary

    bits = get_dictionary(dictionary).markerSize + 2
    return 1.0 + 2.0 * QUIET_ZONE_MODULES / bits


def warp_quad(image: np.ndarray, src_bgra: np.ndarray, quad_px: np.ndarray) -> None:
    """Composite ``src_bgra`` onto ``image`` (in place) so its outer edges land on ``quad_px``.

    ``quad_px`` holds the image positions (pixel-centre coordinates, as cv2.projectPoints
    gives them) of the source's outer corners TL, TR, BR, BL. The source's outer edges are
    at −0.5 and size−0.5 in its own pixel-centre coordinates. Rendered supersampled in a
    patch around the quad and area-averaged down: anti-aliased and unbiased.
    """
    h_img, w_img = image.shape[:2]
    x0 = max(int(math.floor(quad_px[:, 0].min())) - 1, 0)
    y0 = max(int(math.floor(quad_px[:, 1].min())) - 1, 0)
    x1 = min(int(math.ceil(quad_px[:, 0].max())) + 2, w_img)
    y1 = min(int(math.ceil(quad_px[:, 1].max())) + 2, h_img)
    if x1 <= x0 or y1 <= y0:
        return
    size = max(x1 - x0, y1 - y0)
    ss = 4 if size < 200 else (2 if size < 500 else 1)  # bounded patch cost for near markers
    sh, sw = src_bgra.shape[:2]
    src_pts = np.array([[-0.5, -0.5], [sw - 0.5, -0.5], [sw - 0.5, sh - 0.5], [-0.5, sh - 0.5]],
                       np.float64)
    # full-res pixel x ↦ supersampled patch pixel j: j = ss·(x − x0 + 0.5) − 0.5
    dst_pts = ss * (quad_px - np.array([x0, y0]) + 0.5) - 0.5
    H = cv2.getPerspectiveTransform(src_pts.astype(np.float32), dst_pts.astype(np.float32))
    big = cv2.warpPerspective(src_bgra, H, ((x1 - x0) * ss, (y1 - y0) * ss),
                              flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                              borderValue=(0, 0, 0, 0))
    small = cv2.resize(big, (x1 - x0, y1 - y0), interpolation=cv2.INTER_AREA) \
        if ss > 1 else big
    # premultiplied: transparent samples are black, so the area average is colour·coverage
    alpha = small[:, :, 3:4].astype(np.float32) / 255.0
    roi = image[y0:y1, x0:x1]
    roi[:] = np.clip(small[:, :, :3].astype(np.float32) + roi.astype(np.float32)
                     * (1.0 - alpha) + 0.5, 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class _Face:
    points_world: np.ndarray  #: (k, 3) convex polygon
    normal_world: np.ndarray  #: (3,) outward
    bgr: tuple[int, int, int]


def _cylinder_faces(centre_xy: Sequence[float] | np.ndarray, radius: float, z0: float, z1: float,
                    side_bgr: tuple[int, int, int], top_bgr: tuple[int, int, int],
                    n: int = 20) -> list[_Face]:
    a = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    ring = np.column_stack([centre_xy[0] + radius * np.cos(a),
                            centre_xy[1] + radius * np.sin(a)])
    faces = []
    for k in range(n):
        p, q = ring[k], ring[(k + 1) % n]
        mid = (a[k] + math.pi / n)
        faces.append(_Face(np.array([[p[0], p[1], z0], [q[0], q[1], z0],
                                     [q[0], q[1], z1], [p[0], p[1], z1]]),
                           np.array([math.cos(mid), math.sin(mid), 0.0]), side_bgr))
    faces.append(_Face(np.column_stack([ring, np.full(n, z1)]), np.array([0.0, 0.0, 1.0]),
                       top_bgr))
    return faces


def _shade(bgr: tuple[int, int, int], normal: np.ndarray) -> tuple[int, int, int]:
    k = 0.45 + 0.55 * max(0.0, float(normal @ LIGHT_DIR))  # ambient + Lambert
    return tuple(int(min(255, c * k * 1.25)) for c in bgr)  # type: ignore[return-value]


def _draw_faces(image: np.ndarray, faces: Sequence[_Face], *, K: np.ndarray,
                T_camera_from_world: np.ndarray, camera_centre: np.ndarray) -> None:
    """Back-face culled, depth-sorted (far first) flat-shaded polygons."""
    if not faces:
        return
    # one projection for every vertex of every face: the per-face work is just fillPoly
    counts = [len(f.points_world) for f in faces]
    uv, z = _project(K, T_camera_from_world, np.vstack([f.points_world for f in faces]))
    bounds = np.cumsum([0, *counts])
    items = []
    for k, face in enumerate(faces):
        centroid = face.points_world.mean(axis=0)
        if face.normal_world @ (camera_centre - centroid) <= 0:
            continue
        a, b = bounds[k], bounds[k + 1]
        if np.any(z[a:b] < NEAR_M):
            continue
        items.append((float(np.linalg.norm(centroid - camera_centre)), uv[a:b], face))
    items.sort(key=lambda it: -it[0])
    for _, face_uv, face in items:
        pts = np.round(face_uv * 16.0).astype(np.int32)  # 4 fractional bits (shift=4)
        cv2.fillPoly(image, [pts], _shade(face.bgr, face.normal_world), cv2.LINE_AA, shift=4)


def _clip_half_plane(polygon: np.ndarray, line: np.ndarray) -> np.ndarray:
    """The part of a convex polygon (k, 2) where line · (u, v, 1) ≤ 0 (Sutherland–Hodgman)."""
    out = []
    values = polygon @ line[:2] + line[2]
    for k in range(len(polygon)):
        p, q = polygon[k], polygon[(k + 1) % len(polygon)]
        vp, vq = values[k], values[(k + 1) % len(polygon)]
        if vp <= 0:
            out.append(p)
        if (vp <= 0) != (vq <= 0):
            out.append(p + (q - p) * vp / (vp - vq))
    return np.array(out).reshape(-1, 2)


def floor_texture(scene: SceneSettings) -> tuple[np.ndarray, np.ndarray]:
    """(texture BGR, A_world_from_texture 3x3): tiles, grout, blotches, grain; seeded."""
    return _floor_texture(scene.arena_xy, scene.floor_margin_m, scene.texture_m_per_px,
                          scene.floor_tile_m, scene.seed)


@lru_cache(maxsize=4)
def _floor_texture(arena_xy: tuple[float, float, float, float], margin: float, res: float,
                   tile: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng([seed, 7])
    x0, y0 = arena_xy[0] - margin, arena_xy[1] - margin
    w = int(math.ceil((arena_xy[2] + margin - x0) / res))
    h = int(math.ceil((arena_xy[3] + margin - y0) / res))
    xs = x0 + (np.arange(w) + 0.5) * res
    ys = y0 + (np.arange(h) + 0.5) * res
    ti = np.floor(xs / tile).astype(np.int64)
    tj = np.floor(ys / tile).astype(np.int64)
    parity = (tj[:, None] + ti[None, :]) & 1
    tones = np.array(FLOOR_TONES, np.float32)
    tex = tones[parity]  # (h, w, 3)
    # per-tile brightness jitter, hashed from the tile index so it is seed-stable
    jitter = rng.normal(0.0, 5.0, (64, 64)).astype(np.float32)
    tex += jitter[tj[:, None] % 64, ti[None, :] % 64][:, :, None]
    # low-frequency blotches and fine grain so the floor does not look like a test card
    blotch = cv2.resize(rng.normal(0.0, 7.0, (h // 64 + 2, w // 64 + 2)).astype(np.float32),
                        (w, h), interpolation=cv2.INTER_CUBIC)
    tex += blotch[:, :, None]
    tex += rng.normal(0.0, 4.0, (h, w, 1)).astype(np.float32)
    gx = np.abs(xs / tile - np.round(xs / tile)) * tile < 0.003
    gy = np.abs(ys / tile - np.round(ys / tile)) * tile < 0.003
    grout = gy[:, None] | gx[None, :]
    tex[grout] = np.array(GROUT_BGR, np.float32)
    texture = np.clip(tex, 0, 255).astype(np.uint8)
    texture.setflags(write=False)
    A = np.array([[res, 0.0, x0 + 0.5 * res], [0.0, res, y0 + 0.5 * res], [0.0, 0.0, 1.0]])
    return texture, A


# ---------------------------------------------------------------------------------------
# The camera
# ---------------------------------------------------------------------------------------


class SyntheticCamera:
    """Renders BGR frames of the arena seen from a known pinhole camera.

    ``render`` is deterministic: the same inputs, seed and ``frame_index`` give the same
    pixels. The static layer (floor, board, posts) is cached per camera pose and landmark
    set, so a fixed camera only redraws the robot each frame.
    """

    def __init__(self, K: np.ndarray, width: int, height: int, *,
                 T_world_from_camera: np.ndarray, scene: SceneSettings = SceneSettings(),
                 imaging: ImagingSettings = ImagingSettings(),
                 board: Sequence[WorldMarker] = ()) -> None:
        self.K = np.array(K, dtype=float)
        self.width, self.height = int(width), int(height)
        self.T_world_from_camera = np.array(T_world_from_camera, dtype=float)
        self.scene = scene
        self.imaging = imaging
        self.board = tuple(board)
        self._static_key: tuple[bytes, bytes] | None = None
        self._static: np.ndarray | None = None
        self._posts: list[tuple[float, tuple[int, int, int, int], list[_Face]]] = []
        self._post_faces_key = b""
        self._post_faces: list[list[_Face]] = []
        self._light = self._lighting_map()
        self._offset = None if imaging.offset == 0.0 else np.full(
            (self.height, self.width, 3), round(imaging.offset), np.int16)
        self._noise = self._noise_bank()

    # -- effects ------------------------------------------------------------------
    def _lighting_map(self) -> np.ndarray | None:
        im = self.imaging
        if im.gain == 1.0 and im.gradient == 0.0:
            return None
        ramp = im.gain * (1.0 + im.gradient * (np.linspace(0.0, 1.0, self.width) - 0.5))
        row = np.repeat(ramp.astype(np.float32)[:, None], 3, axis=1)
        return np.ascontiguousarray(np.broadcast_to(row, (self.height, self.width, 3)))

    _NOISE_PAD = 61

    def _noise_bank(self) -> np.ndarray | None:
        # One seeded noise field larger than the image; each frame takes a window at a
        # seeded offset: per-frame noise without drawing 2.7 M normals per frame.
        if self.imaging.noise_sigma <= 0:
            return None
        rng = np.random.default_rng([self.scene.seed, 11])
        pad = self._NOISE_PAD
        field = rng.normal(0.0, self.imaging.noise_sigma,
                           (self.height + pad, self.width + pad, 3))
        return np.round(field).astype(np.int16)

    def _apply_imaging(self, image: np.ndarray, frame_index: int) -> np.ndarray:
        im = self.imaging
        if self._light is not None:
            image = cv2.multiply(image, self._light, dtype=cv2.CV_8U)
        if self._offset is not None:
            image = cv2.add(image, self._offset, dtype=cv2.CV_8U)
        if im.blur_kernel > 1:
            k = im.blur_kernel | 1  # Gaussian kernels must be odd
            image = cv2.GaussianBlur(image, (k, k), 0)
        if self._noise is not None:
            rng = np.random.default_rng([self.scene.seed, 13, frame_index])
            dy, dx = (int(v) for v in rng.integers(0, self._NOISE_PAD, 2))
            window = self._noise[dy:dy + self.height, dx:dx + self.width]
            image = cv2.add(image, window, dtype=cv2.CV_8U)
        return image

    # -- static layer -------------------------------------------------------------
    def _camera(self, T_world_from_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return invert_T(T_world_from_camera), T_world_from_camera[:3, 3].copy()

    def _render_floor(self, T_camera_from_world: np.ndarray) -> np.ndarray:
        texture, A = floor_texture(self.scene)
        # floor plane z = 0: image ~ K [r1 r2 t] (x, y, 1)
        H_image_from_floor = self.K @ T_camera_from_world[:3, [0, 1, 3]]
        H = H_image_from_floor @ A
        image = cv2.warpPerspective(texture, H, (self.width, self.height),
                                    flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                                    borderValue=CONCRETE_BGR)
        # pixels whose ray never meets the floor (above the horizon) show the wall: the
        # half-plane of the image where the floor's inverse homography has w ≤ 0
        row = np.linalg.inv(H_image_from_floor)[2]
        frame = np.array([[-1.0, -1.0], [self.width, -1.0], [self.width, self.height],
                          [-1.0, self.height]])
        sky = _clip_half_plane(frame, row / np.abs(row).max())
        if len(sky) >= 3:
            cv2.fillPoly(image, [np.round(sky * 16.0).astype(np.int32)], WALL_BGR,
                         cv2.LINE_AA, shift=4)
        return image

    def _build_static(self, T_world_from_camera: np.ndarray, landmarks_xy: np.ndarray) -> None:
        T_cw, centre = self._camera(T_world_from_camera)
        image = self._render_floor(T_cw)
        for marker in self.board:
            self._draw_marker(image, marker.dictionary, marker.marker_id,
                              np.asarray(marker.corners_world, float), T_cw)
        s = self.scene
        if self._post_faces_key != landmarks_xy.tobytes():  # a moving camera keeps the posts
            self._post_faces_key = landmarks_xy.tobytes()
            self._post_faces = [
                _cylinder_faces((x, y), s.landmark_radius_m, 0.0, s.landmark_height_m,
                                POST_BGR[k % len(POST_BGR)], POST_BGR[k % len(POST_BGR)], n=12)
                for k, (x, y) in enumerate(landmarks_xy)]
        all_faces: list[_Face] = []
        self._posts = []
        for (x, y), faces in zip(landmarks_xy, self._post_faces, strict=True):
            all_faces += faces
            top = np.array([[x, y, s.landmark_height_m]])
            pts = np.vstack([f.points_world for f in faces])
            uv, z = _project(self.K, T_cw, pts)
            if np.all(z > NEAR_M):
                bbox = (int(uv[:, 0].min()) - 1, int(uv[:, 1].min()) - 1,
                        int(uv[:, 0].max()) + 2, int(uv[:, 1].max()) + 2)
                self._posts.append((float(np.linalg.norm(top[0] - centre)), bbox, faces))
        _draw_faces(image, all_faces, K=self.K, T_camera_from_world=T_cw, camera_centre=centre)
        image.setflags(write=False)
        self._static = image

    def _draw_marker(self, image: np.ndarray, dictionary: str, marker_id: int,
                     corners_world: np.ndarray, T_camera_from_world: np.ndarray) -> None:
        centre = corners_world.mean(axis=0)
        outer = centre + (corners_world - centre) * quiet_zone_scale(dictionary)
        uv, z = _project(self.K, T_camera_from_world, outer)
        if np.any(z < NEAR_M):
            return
        warp_quad(image, _marker_bgra(dictionary, marker_id), uv)

    # -- robot --------------------------------------------------------------------
    def _draw_robot(self, image: np.ndarray, pose: np.ndarray, T_cw: np.ndarray,
                    centre: np.ndarray) -> None:
        s = self.scene
        top_z = max(s.marker_offset_xyz[2], 0.02)
        faces = _cylinder_faces(pose[:2], s.robot_radius_m, 0.0, top_z, ROBOT_SIDE_BGR,
                                ROBOT_TOP_BGR, n=28)
        # heading wedge at the front rim, clear of the marker's quiet zone
        c, si = math.cos(pose[2]), math.sin(pose[2])
        r = s.robot_radius_m
        wedge_robot = np.array([[0.93 * r, 0.0], [0.7 * r, 0.12 * r], [0.7 * r, -0.12 * r]])
        wedge = np.column_stack([pose[0] + c * wedge_robot[:, 0] - si * wedge_robot[:, 1],
                                 pose[1] + si * wedge_robot[:, 0] + c * wedge_robot[:, 1],
                                 np.full(3, top_z + 1e-4)])
        faces.append(_Face(wedge, np.array([0.0, 0.0, 1.0]), HEADING_BGR))
        _draw_faces(image, faces, K=self.K, T_camera_from_world=T_cw, camera_centre=centre)
        corners = robot_marker_corners_world(pose, size_m=s.marker_size_m,
                                             offset_xyz=s.marker_offset_xyz)
        self._draw_marker(image, s.dictionary, s.marker_id, corners, T_cw)
        # posts nearer to the camera than the robot's top, overlapping it, go back on top
        uv, _ = _project(self.K, T_cw, np.vstack([f.points_world for f in faces]))
        rx0, ry0 = uv.min(axis=0)
        rx1, ry1 = uv.max(axis=0)
        robot_dist = float(np.linalg.norm(np.array([pose[0], pose[1], top_z]) - centre))
        for dist, (x0, y0, x1, y1), post_faces in self._posts:
            if dist < robot_dist and x0 < rx1 and rx0 < x1 and y0 < ry1 and ry0 < y1:
                _draw_faces(image, post_faces, K=self.K, T_camera_from_world=T_cw,
                            camera_centre=centre)

    # -- public -------------------------------------------------------------------
    def render(self, *, robot_pose: Pose2 | None,
               landmarks_xy: np.ndarray | None = None,
               T_world_from_camera: np.ndarray | None = None,
               frame_index: int = 0) -> np.ndarray:
        """A BGR uint8 frame of the arena with the robot at ``robot_pose`` (x, y, θ).

        ``T_world_from_camera`` overrides the camera's pose for this frame (a moving
        camera); ``frame_index`` selects the sensor noise of this frame.
        """
        T_wc = self.T_world_from_camera if T_world_from_camera is None else np.asarray(
            T_world_from_camera, float)
        lms = np.zeros((0, 2)) if landmarks_xy is None else np.asarray(
            landmarks_xy, float).reshape(-1, 2)
        key = (T_wc.tobytes(), lms.tobytes())
        if key != self._static_key or self._static is None:
            self._build_static(T_wc, lms)
            self._static_key = key
        assert self._static is not None
        image = self._static.copy()
        if robot_pose is not None:
            T_cw, centre = self._camera(T_wc)
            self._draw_robot(image, np.asarray(robot_pose, float), T_cw, centre)
        return self._apply_imaging(image, frame_index)

    def true_T_camera_from_world(self, T_world_from_camera: np.ndarray | None = None
                                 ) -> np.ndarray:
        """The exact extrinsics (world = map with the simulator: the registration's truth)."""
        return invert_T(self.T_world_from_camera if T_world_from_camera is None
                        else T_world_from_camera)

    def project(self, points_world: np.ndarray, *, T_world_from_camera: np.ndarray | None = None
                ) -> np.ndarray:
        """Exact pixel positions (pixel-centre coordinates) of world points."""
        uv, _ = _project(self.K, self.true_T_camera_from_world(T_world_from_camera),
                         np.asarray(points_world, float))
        return uv
