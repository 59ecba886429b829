"""Pure parts of the viewer service: intake, clients and views, eyes, the tracked-pose match,
map bounds, parsing, video (the plots' series: test_viewer_series.py)."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from slamlens.common.errors import ConfigError, SlamlensError
from slamlens.common.messages import Registration, SlamState, Truth
from slamlens.services.visualiser.camera_model import CameraModel
from slamlens.services.visualiser.clients import ClientRegistry, RenderBudget, TooManyViews
from slamlens.services.visualiser.compose import camera_views
from slamlens.services.visualiser.inputs import (
    CameraInputs,
    Inputs,
    Queue,
    RateMeter,
    RobotInputs,
    is_new_map,
)
from slamlens.services.visualiser.recording import (
    Recorder,
    RecordingRefused,
    encode_png,
    recording_name,
)
from slamlens.services.visualiser.settings import ViewSettings
from slamlens.services.visualiser.tracked import TrackedMatch
from slamlens.services.visualiser.views import (
    DEFAULT_BOUNDS,
    CameraView,
    Eye,
    EyeChooser,
    Rendered,
    grow_bounds,
    project_features,
)
from slamlens.services.visualiser.web import BadRequest, parse_http, parse_pairs
from tests.unit.viewer_states import random_state


# -- intake -------------------------------------------------------------------------------
def test_queue_keeps_order_and_drops_the_oldest_when_full() -> None:
    q = Queue("health", lambda: None, maxlen=3)
    for k in range(5):
        q.offer(bytes([k]))
    assert [r.payload for r in q.drain()] == [b"\x02", b"\x03", b"\x04"]
    assert q.drain() == []
    assert q.received_count == 5


def test_rate_meter_counts_intervals_in_its_window() -> None:
    meter = RateMeter(window_s=2.0)
    for k in range(21):
        meter.tick(100.0 + k * 0.05)  # 20 Hz for one second
    assert meter.rate(101.0) == pytest.approx(20.0)
    assert meter.rate(104.0) == 0.0  # nothing in the last two seconds


# -- clients and views --------------------------------------------------------------------
def no_recorder(*args: object) -> Recorder:
    raise AssertionError("no recording in this test")


def test_clients_share_a_view_per_distinct_settings_and_keep_the_newest_256() -> None:
    new_views: list[int] = []
    clients = ClientRegistry(ViewSettings(), ttl_s=60.0, on_new_view=lambda: new_views.append(1),
                             new_recorder=no_recorder)
    assert clients.settings_for(None) == ViewSettings() and clients.client_count == 0
    inter = clients.update_settings("a", {"mode": "inter", "labels": True})
    assert (inter.mode, inter.labels) == ("inter", True)
    assert clients.settings_for("a") is inter
    assert clients.update_settings("b", {"mode": "inter", "labels": "on"}) == inter
    assert len(clients.looked_at()) == 1 and len(new_views) == 1  # one view for both tabs
    with pytest.raises(ConfigError, match="mode"):
        clients.update_settings("a", {"mode": "some"})
    assert clients.settings_for("a") is inter  # a rejected change leaves the settings
    for k in range(ClientRegistry.MAX_CLIENTS):
        clients.settings_for(f"tab{k}")
    assert clients.client_count == ClientRegistry.MAX_CLIENTS
    assert clients.settings_for("a") == ViewSettings()  # the oldest tab was forgotten


def test_a_view_is_active_for_its_ttl_and_current_only_for_its_inputs() -> None:
    clients = ClientRegistry(ViewSettings(), ttl_s=0.2, on_new_view=lambda: None,
                             new_recorder=no_recorder)
    settings = ViewSettings(mode="minmeanmax")
    assert clients.active() == [] and clients.latest(settings) is None
    clients.touch(settings)
    (view,) = clients.active()
    assert view.settings == settings and not clients.is_current(settings, (1,))
    picture = Rendered(version=1, seq=4, stamp=0.4, image=np.zeros((2, 2, 3), np.uint8),
                       jpeg=b"jpeg", rendered_at=0.0)
    clients.publish(view, picture, inputs=(1,))
    assert clients.latest(settings) is picture
    assert clients.is_current(settings, (1,)) and not clients.is_current(settings, (2,))
    assert clients.looked_at(now=view.touched + 0.1) == [view]
    assert clients.looked_at(now=view.touched + 0.3) == []  # nobody looked for a ttl


# -- eyes ---------------------------------------------------------------------------------
def test_eyes_follow_the_view_choice_and_the_map_bounds_restart() -> None:
    map_eyes = EyeChooser("map", map_width=640, map_height=360, stereo_baseline_m=0.1)
    (eye,) = map_eyes.choose([], [])
    assert eye.name == "map" and map_eyes.bounds is None  # before any state: default floor
    assert eye.camera is not None and (eye.camera.width, eye.camera.height) == (640, 360)
    default = CameraModel.top_down(bounds_xy=DEFAULT_BOUNDS, width=640, height=360)
    np.testing.assert_array_equal(eye.camera.T_camera_from_map, default.T_camera_from_map)
    wide = random_state(2, landmarks=[[0.1, 0.2], [5.2, 0.4]])
    narrow = random_state(2, landmarks=[[0.1, 0.2], [2.2, 0.4]])
    map_eyes.choose([wide], [])
    assert map_eyes.bounds == grow_bounds(None, wide)
    map_eyes.choose([narrow], [])
    assert map_eyes.bounds == grow_bounds(None, wide)  # grows only …
    map_eyes.restart()
    map_eyes.choose([narrow], [])
    assert map_eyes.bounds == grow_bounds(None, narrow) != grow_bounds(None, wide)  # … a new run
    # several robots: the bounds hold every map
    map_eyes.restart()
    far = random_state(2, landmarks=[[-4.0, -3.0], [-3.5, -3.0]])
    map_eyes.choose([narrow, far], [])
    bounds = map_eyes.bounds
    assert bounds is not None and bounds[0] <= -4.0 and bounds[2] >= 2.2
    stereo = EyeChooser("stereo", map_width=640, map_height=360, stereo_baseline_m=0.1)
    assert [e.name for e in stereo.choose([], [])] == ["map-left", "map-right"]
    frame = np.zeros((360, 640, 3), np.uint8)
    camera = EyeChooser("camera", map_width=640, map_height=360, stereo_baseline_m=0.1)
    note = "waiting for the registration of camera top for robot r7"
    (waiting,) = camera.choose([], [CameraView("top", frame, {}, {"r7": note})])
    assert waiting.camera is None and waiting.image is frame and waiting.note == note
    assert waiting.model_for("r7") == (None, note)
    assert camera.current == (waiting,)


def registration_for(robot: str, *, epoch: int | None = None) -> Registration:
    K = np.array([[500.0, 0, 320], [0, 500.0, 180], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3], T[2, 3] = np.diag([1.0, -1.0, -1.0]), 3.0
    return Registration(camera="top", robot=robot, stamp=0.0, K=K, dist=np.zeros(5),
                        width=640, height=360, T_camera_from_map=T,
                        reprojection_error_px=0.2, epoch=epoch)


def robot_inputs(name: str, state: SlamState | None, *, epoch_started: float = -np.inf
                 ) -> RobotInputs:
    return RobotInputs(name, 0, state, 0.0, None, epoch_started, None, 0, RateMeter())


def test_a_registration_places_only_its_own_map() -> None:
    """A registration with another epoch, or without one and received before the state
    that began the current map, is stale: never drawn with the new map."""
    old_map = dataclasses.replace(random_state(2), epoch=111)
    new_map = dataclasses.replace(random_state(2), epoch=222)
    r = robot_inputs("r", new_map, epoch_started=50.0)
    assert r.registration_usable(registration_for("r", epoch=222), received=10.0)
    assert not r.registration_usable(registration_for("r", epoch=111), received=60.0)
    assert not r.registration_usable(registration_for("r"), received=49.0)  # before the map
    assert r.registration_usable(registration_for("r"), received=51.0)
    first = robot_inputs("r", old_map)  # the first map the viewer sees: any epoch-less one
    assert first.registration_usable(registration_for("r"), received=-1e9)
    assert is_new_map(old_map, new_map) and not is_new_map(new_map, new_map)
    resumed = dataclasses.replace(new_map, seq=new_map.seq - 1)  # same epoch, seq back
    assert not is_new_map(new_map, resumed)
    unknown = dataclasses.replace(random_state(2, seq=5), epoch=0)
    assert is_new_map(unknown, dataclasses.replace(unknown, seq=4))  # epoch 0: seq back

    # a camera that places one robot's map and not the other's (stale): per-robot models
    inputs = Inputs(robots=(robot_inputs("a", new_map, epoch_started=50.0),
                            robot_inputs("b", new_map, epoch_started=50.0)),
                    cameras=(CameraInputs("top", None, None, None, {
                        "a": (registration_for("a", epoch=222), 10.0),
                        "b": (registration_for("b", epoch=111), 60.0)}, RateMeter()),),
                    versions=())
    (view,) = camera_views(inputs)
    assert list(view.registrations) == ["a"]
    assert "new map of robot b" in view.waiting["b"]
    chooser = EyeChooser("camera", map_width=640, map_height=360, stereo_baseline_m=0.1)
    (eye,) = chooser.choose([new_map], [view])
    assert eye.model_for("a")[0] is not None
    model, why = eye.model_for("b")
    assert model is None and "register the new map of robot b" in why


# -- the tracked pose ---------------------------------------------------------------------
def test_the_tracked_pose_is_matched_with_the_estimate_nearest_its_stamp() -> None:
    match = TrackedMatch(match_s=0.06)
    tracked = Truth(robot="r", stamp=1.03, pose=np.array([1.0, 2.0, 0.1]),
                    landmark_ids=np.zeros(0, np.int64), landmarks=np.zeros((0, 2)))
    assert match.reference() == (None, None)
    match.set_tracked(tracked)
    assert match.reference() == (None, None)  # no estimate yet
    for k in range(20):
        match.add_estimate(0.1 * k, np.array([0.1 * k, 0.0, 0.0]))
    pose, estimate = match.reference()
    assert pose is not None and estimate is not None
    np.testing.assert_array_equal(pose, tracked.pose)
    np.testing.assert_allclose(estimate, [1.0, 0.0, 0.0])  # stamp 1.0 is nearest 1.03
    match.set_tracked(Truth(robot="r", stamp=5.0, pose=np.zeros(3),
                            landmark_ids=np.zeros(0, np.int64), landmarks=np.zeros((0, 2))))
    assert match.reference() == (None, None)  # 3.1 s from the newest estimate: no match


# -- map bounds ---------------------------------------------------------------------------
def test_map_bounds_snap_grow_and_hold_still() -> None:
    first = grow_bounds(None, random_state(3, landmarks=[[0.1, 0.2], [2.3, 0.4], [1.0, 2.7]]))
    assert first == (0.0, 0.0, 2.5, 3.0)
    # a small move inside the bounds changes nothing
    assert grow_bounds(first, random_state(3, landmarks=[[0.2, 0.3], [2.2, 0.4],
                                                          [1.0, 2.6]])) == first
    # a new landmark outside grows them, to the grid
    grown = grow_bounds(first, random_state(3, landmarks=[[0.1, 0.2], [3.2, 0.4],
                                                          [1.0, 2.7]]))
    assert grown == (0.0, 0.0, 3.5, 3.0)
    # a lone robot still gets a floor of at least 2 m
    lone = grow_bounds(None, random_state(0))
    assert lone[2] - lone[0] >= 2.0 and lone[3] - lone[1] >= 2.0


def test_map_bounds_recover_from_one_wild_estimate() -> None:
    normal = [[0.1, 0.2], [2.3, 0.4], [1.0, 2.7]]
    wild = grow_bounds(None, random_state(3, landmarks=[[0.1, 0.2], [2.3, 0.4], [900, 800]]))
    assert wild[2] >= 900
    assert grow_bounds(wild, random_state(3, landmarks=normal)) == (0.0, 0.0, 2.5, 3.0)
    huge = grow_bounds(None, random_state(1, landmarks=[[1e308, -1e308]]))
    assert all(np.isfinite(huge))


# -- parsing ------------------------------------------------------------------------------
def test_parse_pairs_and_http_address() -> None:
    assert parse_pairs("1-2, 3-4,") == [(1, 2), (3, 4)]
    assert parse_pairs("") == []
    for bad in ("1-", "a-b", "1:2", "-1-2"):
        with pytest.raises(BadRequest):
            parse_pairs(bad)
    with pytest.raises(SlamlensError, match="at most 32 pairs"):  # the CLI's one-line errors
        parse_pairs(",".join(f"{k}-{k + 1}" for k in range(33)))
    assert parse_http("127.0.0.1:8080") == ("127.0.0.1", 8080)
    assert parse_http("[::1]:0") == ("::1", 0)
    for bad in ("8080", "host:", ":80", "host:99999", "host:http"):
        with pytest.raises(ConfigError):
            parse_http(bad)


# -- feature picking ----------------------------------------------------------------------
def test_feature_pixels_in_a_stereo_picture_are_offset_into_the_right_half() -> None:
    top = CameraModel.top_down(bounds_xy=(0, 0, 3, 3), width=640, height=360)
    left, right = top.stereo_pair(0.1)
    xy = np.array([[1.5, 1.5], [50.0, 1.5]])  # the second is far outside the picture
    single = project_features((Eye("map", top, None, ""),), xy)
    assert single[0] == pytest.approx([320, 180], abs=1e-6) and single[1] is None
    pair = project_features((Eye("l", left, None, ""), Eye("r", right, None, "")), xy)
    uv, _ = left.project(np.array([[1.5, 1.5, 0.0]]))
    assert pair[0] == pytest.approx(uv[0])  # seen by the left eye first
    picture = np.zeros((360, 500, 3), np.uint8)  # an unregistered left camera's picture
    pair = project_features((Eye("l", None, picture, "not registered"),
                             Eye("r", right, None, "")), xy)
    uv, _ = right.project(np.array([[1.5, 1.5, 0.0]]))
    assert pair[0] == pytest.approx([uv[0, 0] + 500, uv[0, 1]])  # after the left picture


# -- recording ----------------------------------------------------------------------------
@pytest.mark.parametrize("codec", ["mp4v", "MJPG"])
def test_recorder_writes_real_time_video(tmp_path: Path, codec: str) -> None:
    frame = np.zeros((120, 160, 3), np.uint8)
    frame[:, :80] = (0, 0, 255)
    sizes = iter([(120, 160)] * 3 + [(240, 320)] * 1000)  # the view changes size midway

    def source() -> np.ndarray:
        h, w = next(sizes)
        return cv2.resize(frame, (w, h))

    name = recording_name("robot1", "tab/1", codec)
    assert "/" not in name and name.endswith(".mp4" if codec == "mp4v" else ".avi")
    recorder = Recorder(directory=tmp_path, name=name, fps=25.0, codec=codec, source=source,
                        settings=lambda: None)
    started = time.monotonic()
    recorder.start()
    deadline = started + 30.0
    while recorder.frames < 8 and time.monotonic() < deadline:  # some after the size change
        time.sleep(0.02)
    recorder.stop()
    elapsed = time.monotonic() - started
    info = recorder.info()
    assert not info["recording"] and info["error"] == ""
    # real time: never more than 25 frames a second (fewer on a busy machine)
    assert 8 <= info["frames"] <= 25 * elapsed + 2, (info["frames"], elapsed)
    capture = cv2.VideoCapture(str(tmp_path / name))
    read = 0
    while True:
        ok, image = capture.read()
        if not ok:
            break
        assert image.shape == (120, 160, 3)  # later frames scaled to the first size
        assert image[60, 20, 2] > 200 and image[60, 140, 2] < 60
        read += 1
    capture.release()
    assert read == info["frames"]


def test_a_recording_is_refused_without_disk_space_and_stops_itself_at_its_limits(
        tmp_path: Path) -> None:
    # noise: ~100 kB a frame in MJPG, so the file grows on disk (the writer buffers)
    picture = np.random.default_rng(1).integers(0, 255, (240, 320, 3), dtype=np.uint8)

    def recorder(name: str, free: list[int], **limits: float) -> Recorder:
        space = iter(free)
        return Recorder(directory=tmp_path, name=name, fps=20.0, codec="MJPG",
                        source=lambda: picture, settings=lambda: None,
                        free=lambda _dir: next(space, free[-1]), **limits)

    def stopped_by_itself(r: Recorder) -> dict:
        deadline = time.monotonic() + 20
        while r.running and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not r.running
        return r.info()

    short = recorder("a.avi", [10 ** 12], min_free_bytes=10 ** 13)
    with pytest.raises(RecordingRefused, match="min_free_disk_mb 10000000"):
        short.start()
    assert not (tmp_path / "a.avi").exists()

    timed = recorder("b.avi", [10 ** 12], max_seconds=0.5)
    timed.start()
    info = stopped_by_itself(timed)
    assert "max_recording_s 0.5" in info["limit"] and info["frames"] >= 1
    assert cv2.VideoCapture(str(tmp_path / "b.avi")).read()[0]  # a file a player reads

    sized = recorder("c.avi", [10 ** 12], max_bytes=200_000)
    sized.start()
    assert "max_recording_mb" in stopped_by_itself(sized)["limit"]

    filling = recorder("d.avi", [10 ** 12, 10 ** 5], min_free_bytes=10 ** 6)  # the disk fills
    filling.start()
    info = stopped_by_itself(filling)
    assert "0 MB free on the disk" in info["limit"] and not info["recording"]


def test_render_budget_holds_other_views_to_their_share() -> None:
    budget = RenderBudget(0.25, bank_s=0.02)
    budget.refill(100.0)
    assert budget.allows and budget.wait_s() == 0.0
    budget.spend(0.03)  # one slow render of another view: 10 ms over
    assert not budget.allows and budget.wait_s() == pytest.approx(0.04)  # 10 ms at 25 %
    budget.refill(100.03)
    assert not budget.allows  # 7.5 ms of the 10 ms back
    budget.refill(100.05)
    assert budget.allows
    budget.refill(200.0)  # a long pause banks at most bank_s
    budget.spend(0.02)
    assert not budget.allows
    # over a long run, others get share × elapsed time whatever they ask
    budget, spent, now = RenderBudget(0.3, bank_s=0.02), 0.0, 0.0
    while now < 10.0:
        budget.refill(now)
        if budget.allows:
            budget.spend(0.015)
            spent += 0.015
        now += 0.001
    assert spent == pytest.approx(0.3 * 10.0, abs=0.05)


def test_the_default_view_renders_first_then_the_one_drawn_longest_ago() -> None:
    clients = ClientRegistry(ViewSettings(), ttl_s=60.0, on_new_view=lambda: None,
                             new_recorder=no_recorder, max_views=3)
    others = [ViewSettings(scale=s) for s in (2.0, 3.0, 4.0)]
    for settings in others:
        clients.touch(settings)
    clients.touch(ViewSettings())
    views = {v.settings: v for v in clients.active()}
    for settings, drawn in zip(others, (5.0, 1.0, 3.0), strict=True):
        views[settings].drawn_at = drawn
    views[ViewSettings()].drawn_at = 9.0
    order = [v.settings for v in clients.render_order(list(views.values()))]
    assert order == [ViewSettings(), others[1], others[2], others[0]]


def test_views_are_capped_and_a_client_leaving_its_streamed_view_makes_room() -> None:
    clients = ClientRegistry(ViewSettings(), ttl_s=60.0, on_new_view=lambda: None,
                             new_recorder=no_recorder, max_views=2)
    a = clients.update_settings("a", {"scale": 2})
    clients.watch(a, "a")
    b = clients.update_settings("b", {"scale": 3})
    clients.watch(b, "b")
    with pytest.raises(TooManyViews, match="max_views 2"):
        clients.update_settings("c", {"scale": 4})
    assert clients.settings_for("c") == ViewSettings()  # unchanged
    clients.watch(ViewSettings(), None)  # the default view never counts
    moved = clients.update_settings("a", {"scale": 5})  # a's stream follows a: room
    assert moved.scale == 5 and clients.memory()["evicted"] == 1
    assert {v.settings for v in clients.active()} == {b, moved, ViewSettings()}
    clients.unwatch(b, "b")
    assert clients.update_settings("c", {"scale": 4}).scale == 4  # b is idle now: evicted
    assert clients.memory() | {"picture_bytes": 0} == {
        "kept": 3, "streamed": 1, "max": 2, "evicted": 2, "refused": 1, "picture_bytes": 0}


def test_png_snapshot_round_trips() -> None:
    image = np.random.default_rng(0).integers(0, 255, (30, 40, 3), dtype=np.uint8)
    data = encode_png(image)
    assert data[:4] == b"\x89PNG"
    assert np.array_equal(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR), image)


# -- configuration ------------------------------------------------------------------------
def test_viewer_config_from_toml_and_flags(tmp_path: Path) -> None:
    from slamlens.common.config import load_settings
    from slamlens.services.visualiser.settings import ViewerConfig

    path = tmp_path / "viewer.toml"
    path.write_text('robot = "r2"\ncamera = "head"\nview = "stereo"\nfps = 15\n')
    config = load_settings(ViewerConfig, path, {"fps": 20.0, "camera": None})
    assert (config.robot, config.camera, config.view, config.fps) == ("r2", "head", "stereo",
                                                                      20.0)
    assert config.cameras == ("head-left", "head-right")
    assert load_settings(ViewerConfig, None, {}).resolved_view == "map"
    assert load_settings(ViewerConfig, None, {"camera": "top"}).cameras == ("top",)
    path.write_text('robots = "r2"\n')
    with pytest.raises(ConfigError, match="robots"):
        load_settings(ViewerConfig, path, {})
    for bad in ({"view": "camera"}, {"jpeg_quality": 101}, {"fps": 0}, {"view": "sideways"},
                {"camera": "a/b"}):
        with pytest.raises(ConfigError):
            load_settings(ViewerConfig, None, bad)


def test_a_registration_no_camera_has_is_a_bad_message_not_a_failed_render() -> None:
    """Well-formed registrations the viewer cannot draw through are refused at decoding
    (counted, one line each), so the picture never fails; a good one afterwards is used."""
    import logging

    from slamlens.common.drops import DropCounter
    from slamlens.common.inprocess_bus import InProcessBus
    from slamlens.common.keys import Keys
    from slamlens.services.visualiser.inputs import Wakeups
    from slamlens.services.visualiser.intake import Intake
    from slamlens.services.visualiser.store import InputStore
    from slamlens.services.visualiser.takein import TakeIn

    keys, bus = Keys(), InProcessBus()
    drops = DropCounter(logging.getLogger("test"))
    intake = Intake(bus, keys=keys, wakeups=Wakeups(), robots=("r1",), cameras=("cam",),
                    late_join_timeout_s=0.0)
    store = InputStore(robots=("r1",), cameras=("cam",))
    ingest = TakeIn(intake, store, prepared=lambda _robot: None, drops=drops,
                    max_frame_pixels=4096 * 4096)
    intake.start()
    try:
        good = Registration(camera="cam", robot="r1", stamp=0.0,
                            K=np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]),
                            dist=np.zeros(5), width=640, height=480,
                            T_camera_from_map=np.eye(4), reprojection_error_px=0.2)
        bad = [dataclasses.replace(good, K=np.zeros((3, 3))),
               dataclasses.replace(good, K=np.diag([500.0, 500.0, 2.0])),
               dataclasses.replace(good, dist=np.zeros(3)),
               dataclasses.replace(good, width=100_000, height=100_000),
               dataclasses.replace(good, width=0)]
        for n, registration in enumerate(bad, start=1):
            bus.put(keys.registration("cam", "r1"), registration.to_bytes())
            ingest()
            assert drops.counts == {"registration cam": n}
            assert store.snapshot().cameras[0].registration is None
        bus.put(keys.registration("cam", "r1"), good.to_bytes())
        ingest()
        assert store.snapshot().cameras[0].registration is not None
        assert drops.total == len(bad)
    finally:
        intake.stop()
