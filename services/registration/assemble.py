"""Building a :class:`RegistrationService` from :class:`RegistrationSettings`.

Decides the camera(s), their calibration, the frame source, the marker board and the
registrar, so ``cli.py`` stays a thin shell and tests can build the same service in-process.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np

from slamlens.common.bus import Bus
from slamlens.common.errors import ConfigError, SourceError
from slamlens.common.keys import Keys
from slamlens.services.registration.apriltag3 import AprilTagDetector, make_detector
from slamlens.services.registration.board import MarkerBoard, default_board, load_board
from slamlens.services.registration.browser import BrowserCameras, BrowserFrames
from slamlens.services.registration.calibration import (
    CameraCalibration,
    load_calibration,
    scaled_calibration,
    synthetic_calibration,
)
from slamlens.services.registration.maps import CameraSettings
from slamlens.services.registration.markers import MarkerDetector, WindowedDetector
from slamlens.services.registration.pipeline import CameraParts, CameraPipeline
from slamlens.services.registration.service import RegistrationService, TrackerPoses
from slamlens.services.registration.settings import RegistrationSettings
from slamlens.services.registration.sources import (
    DeviceOptions,
    FrameSource,
    ReconnectingSource,
    SyntheticSource,
    open_capture,
)
from slamlens.services.registration.synthetic import (
    ImagingSettings,
    SceneSettings,
    SyntheticCamera,
    WorldMarker,
    arena_centre,
    fit_hfov_deg,
    floor_texture,
    orbit_pose,
    overhead_pose,
    stereo_poses,
)
from slamlens.services.registration.tracking import Registrar, RegistrarSettings

log = logging.getLogger(__name__)

HEAD_MOUNTED_HFOV_DEG = 75.0  #: synthetic head-mounted camera when hfov = 0


def calibration_for(settings: RegistrationSettings) -> CameraCalibration:
    """The intrinsics: the calibration file, or (synthetic only) the synthetic camera's."""
    if settings.calibration:
        calib = load_calibration(settings.calibration)
        if settings.synthetic and np.any(calib.dist != 0):
            log.warning("the synthetic camera renders an ideal pinhole; the distortion in %s "
                        "is ignored when rendering", settings.calibration)
        return calib
    if not settings.synthetic:
        raise ConfigError("a real camera needs --calibration FILE.yml (see slamlens calibrate)")
    hfov = settings.hfov
    if hfov <= 0:
        hfov = (fit_hfov_deg(settings.width, settings.height, arena_xy=settings.arena,
                             height_m=settings.camera_height)
                if settings.mode == "overhead" else HEAD_MOUNTED_HFOV_DEG)
    return synthetic_calibration(settings.width, settings.height, hfov_deg=hfov)


def board_for(settings: RegistrationSettings) -> MarkerBoard:
    if settings.board:
        return load_board(settings.board)
    a = settings.arena
    return default_board(area_min_xy=a[:2], area_max_xy=a[2:], dictionary=settings.dictionary)


def synthetic_scene(settings: RegistrationSettings) -> SceneSettings:
    return SceneSettings(arena_xy=tuple(settings.arena),  # type: ignore[arg-type]
                         robot_radius_m=settings.robot_radius, dictionary=settings.dictionary,
                         marker_id=settings.marker_id, marker_size_m=settings.marker_size,
                         marker_offset_xyz=tuple(settings.marker_offset),  # type: ignore[arg-type]
                         seed=settings.seed)


def synthetic_sources(settings: RegistrationSettings, calib: CameraCalibration,
                      board: MarkerBoard | None) -> list[SyntheticSource]:
    """One synthetic source per camera name (two for stereo), sharing one scene."""
    scene = synthetic_scene(settings)
    # the floor's texture (made once, ~0.2 s of CPU) now: before the service says it is
    # ready, not in the first frame, which a stop right after "ready" would wait for
    floor_texture(scene)
    imaging = ImagingSettings(noise_sigma=settings.noise, blur_kernel=settings.blur,
                              gain=settings.gain, offset=settings.offset,
                              gradient=settings.gradient)
    centre = arena_centre(settings.arena)
    markers = () if board is None else tuple(
        WorldMarker(m.marker_id, board.corners_in_world(m.marker_id), board.dictionary)
        for m in board.markers)
    names = settings.camera_names()
    stereo = len(names) == 2

    def pose_fn(index: int) -> Callable[[float], np.ndarray] | None:
        if settings.mode == "overhead":
            return None

        def pose_at(stamp: float) -> np.ndarray:
            T = orbit_pose(stamp, centre_xy=centre, radius_m=settings.orbit_radius,
                           height_m=settings.orbit_height, period_s=settings.orbit_period)
            return stereo_poses(T, settings.stereo_baseline)[index] if stereo else T
        return pose_at

    sources = []
    for i, name in enumerate(names):
        pose_at = pose_fn(i)
        if pose_at is not None:
            T0 = pose_at(0.0)
        else:
            T0 = overhead_pose(centre_xy=centre, height_m=settings.camera_height,
                               yaw_deg=settings.camera_yaw)
            if stereo:
                T0 = stereo_poses(T0, settings.stereo_baseline)[i]
        camera = SyntheticCamera(calib.K, calib.width, calib.height, T_world_from_camera=T0,
                                 scene=scene, imaging=imaging, board=markers)
        sources.append(SyntheticSource(camera, name=f"synthetic camera {name}",
                                       pose_at=pose_at))
    return sources


def capture_factory(settings: RegistrationSettings) -> Callable[[], FrameSource]:
    """Opens the ``--source`` a real camera is read from, with its device options."""
    return open_capture(settings.source, loop=settings.loop, timeout_s=settings.stall_s,
                        options=DeviceOptions(width=settings.width, height=settings.height,
                                              fps=settings.fps, fourcc=settings.fourcc,
                                              buffer_size=settings.buffer_size))


def real_source(settings: RegistrationSettings,
                factory: Callable[[], FrameSource] | None = None) -> FrameSource:
    """The capture source, opened now if it can be, else retried in the background."""
    if factory is None:
        factory = capture_factory(settings)
    try:
        initial: FrameSource | None = factory()
    except SourceError as exc:
        log.warning("%s; will keep trying", exc)
        initial = None
    return ReconnectingSource(factory, name=f"source {settings.source}", initial=initial,
                              backoff_max_s=settings.reconnect_max_s)


def detector_for(settings: RegistrationSettings, *, moving: bool
                 ) -> MarkerDetector | AprilTagDetector | WindowedDetector:
    """One camera's detector: it looks only around the last markers between full frames,
    every ``detect_full_every``-th frame for a fixed camera, ``detect_full_every_moving``-th
    for a head-mounted one (markers come into its view all the time)."""
    detector = make_detector(settings.detector, settings.dictionary)
    full_every = settings.detect_full_every_moving if moving else settings.detect_full_every
    if full_every <= 1:
        return detector
    return WindowedDetector(detector, full_every=full_every)


def build_service(bus: Bus, keys: Keys, settings: RegistrationSettings) -> RegistrationService:
    """Everything ``slamlens registration`` runs, wired to ``bus`` (not started)."""
    # a missing path fails first, a missing calibration second, before a device is opened
    if settings.browser:
        return build_browser_service(bus, keys, settings)
    factory = None if settings.synthetic else capture_factory(settings)
    calib = calibration_for(settings)
    moving = settings.mode == "head-mounted"
    board = board_for(settings) if moving else None
    tracker = TrackerPoses() if moving and settings.camera_pose_source == "tracker" else None
    registrar_settings = registrar_settings_for(settings)
    synthetic: list[SyntheticSource] = []
    sources: list[FrameSource]
    if settings.synthetic:
        synthetic = synthetic_sources(settings, calib, board)
        sources = list(synthetic)
    else:
        sources = [real_source(settings, factory)]
    pipelines = []
    for i, (name, source) in enumerate(zip(settings.camera_names(), sources, strict=True)):
        camera = camera_settings_for(settings, name, publish_tracked=i == 0)
        parts = CameraParts(
            source=source, calib=calib,
            detector=detector_for(settings, moving=moving),
            registrar=Registrar(registrar_settings, calib),
            board=None if settings.camera_pose_source == "tracker" else board,
            tracker_pose=(None if tracker is None
                          else (lambda n=name: tracker.pose_of(n))))  # type: ignore[misc]
        pipelines.append(CameraPipeline(bus, keys, settings=camera, parts=parts))
    return RegistrationService(bus, keys, robot=settings.robot, base_camera=settings.camera,
                               pipelines=pipelines, synthetic_sources=synthetic,
                               tracker=tracker)


def registrar_settings_for(settings: RegistrationSettings) -> RegistrarSettings:
    return RegistrarSettings(
        marker_id=settings.marker_id, marker_size_m=settings.marker_size,
        marker_offset_xyz=tuple(settings.marker_offset),  # type: ignore[arg-type]
        register_frames=settings.register_frames,
        still_tolerance_m=settings.still_tolerance_m,
        still_tolerance_deg=settings.still_tolerance_deg,
        max_reprojection_error_px=settings.max_reprojection_error_px,
        moving_camera=settings.mode == "head-mounted")


def camera_settings_for(settings: RegistrationSettings, name: str, *,
                        publish_tracked: bool) -> CameraSettings:
    return CameraSettings(
        camera=name, robot=settings.robot, fps=settings.fps,
        jpeg_quality=settings.jpeg_quality, moving=settings.mode == "head-mounted",
        publish_tracked=publish_tracked,
        registration_period_s=settings.registration_period_s,
        max_reregister_move_m=settings.max_reregister_move_m,
        max_reregister_turn_deg=settings.max_reregister_turn_deg,
        origin_tolerance_m=settings.origin_tolerance_m)


def browser_calibration(settings: RegistrationSettings, camera: str, width: int,
                        height: int) -> tuple[CameraCalibration, str]:
    """A browser camera's intrinsics for its frames' size, and where they come from: its
    calibration (``--calibration FILE`` or ``FOLDER/CAMERA.yml``; scaled to frames of the
    same aspect ratio), else the default phone model (``browser_hfov``)."""
    if settings.calibration:
        given = Path(settings.calibration)
        path = given / f"{camera}.yml" if given.is_dir() else given
        if path.is_file():
            calib = load_calibration(path)
            if (calib.width, calib.height) == (width, height):
                return calib, str(path)
            if calib.width * height == calib.height * width:
                return scaled_calibration(calib, width, height), f"{path}, scaled"
            log.warning("camera %s: %s is for %dx%d frames, its frames are %dx%d: using "
                        "the default phone model", camera, path, calib.width, calib.height,
                        width, height)
    return (synthetic_calibration(width, height, hfov_deg=settings.browser_hfov),
            f"the default phone model ({settings.browser_hfov:g}° wide)")


def build_browser_service(bus: Bus, keys: Keys,
                          settings: RegistrationSettings) -> RegistrationService:
    """``--source browser``: no camera until a browser sends frames; then one pipeline
    per camera, made here (services/registration/browser.py)."""
    moving = settings.mode == "head-mounted"
    board = board_for(settings) if moving else None
    registrar_settings = registrar_settings_for(settings)

    def browser(service: RegistrationService) -> BrowserCameras:
        def make(camera: str, source: BrowserFrames, width: int, height: int
                 ) -> CameraPipeline:
            calib, origin = browser_calibration(settings, camera, width, height)
            log.info("camera %s: intrinsics from %s", camera, origin)
            parts = CameraParts(source=source, calib=calib,
                                detector=detector_for(settings, moving=moving),
                                registrar=Registrar(registrar_settings, calib), board=board)
            pipeline = CameraPipeline(bus, keys, parts=parts, settings=camera_settings_for(
                settings, camera, publish_tracked=True))
            if moving:  # a head-mounted camera starts from another's registration
                for other in service.pipelines:
                    T = other.registrar.T_anchor_from_map
                    if T is not None and other.settings.moving:
                        pipeline.inherit(T, epoch=other.epoch, camera=other.camera,
                                         reprojection_error_px=other.registrar
                                         .reprojection_error_px)
                        break
            return pipeline

        return BrowserCameras(bus, keys, base=settings.camera, make=make,
                              add=service.add_pipeline, remove=service.remove_pipeline,
                              idle_s=settings.browser_idle_s,
                              max_cameras=settings.max_browser_cameras,
                              max_pixels=settings.max_browser_frame_pixels)

    return RegistrationService(bus, keys, robot=settings.robot, base_camera=settings.camera,
                               pipelines=[], browser=browser)
