"""A state drawn once onto layers and put over every camera frame, and states copied out
of Zenoh only when the viewer decodes them (``Bus.subscribe_lazy``).

The layered picture must be the picture drawn straight onto the frame: the same pixels
where nothing was drawn or something opaque was, the same to OpenCV's rounding on
anti-aliased edges, over any frame; the camera-tracked pose is drawn per frame between the
two layers. The pipeline's state stages take the newest state only from the intake's
slot, copy out no state they skip, and decode it to the state the estimator sent."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import cv2
import numpy as np
import pytest

from slamlens.common.drops import DropCounter
from slamlens.common.keys import Keys
from slamlens.common.messages import Health, SlamState, Violation
from slamlens.services.visualiser import draw
from slamlens.services.visualiser.inputs import Wakeups
from slamlens.services.visualiser.intake import Intake
from slamlens.services.visualiser.legend import draw_legend, rejected_legend
from slamlens.services.visualiser.render import Renderer
from slamlens.services.visualiser.settings import ViewSettings
from slamlens.services.visualiser.stages import StateStages, StateWork
from slamlens.services.visualiser.store import InputStore
from slamlens.services.visualiser.takein import TakeIn
from tests.routes import put_until_seen
from tests.unit.test_render import paper_state, top_down

#: OpenCV blends anti-aliased edges in integers, a layer then the frame rounds once more
#: per step: a few pixels where several anti-aliased edges overlap differ by up to this
MAX_ROUNDING = 12


def drawn_straight(frame: np.ndarray, state: SlamState, settings: ViewSettings, *,
                   health: Health | None = None, reference: np.ndarray | None = None,
                   notes: list | None = None, earlier: tuple[SlamState, ...] = ()
                   ) -> np.ndarray:
    """The picture as drawn before layers: every step onto a copy of the frame (after
    the ``earlier`` states' poses, the path)."""
    img = frame.copy()
    renderer = Renderer()
    for s in earlier:
        renderer.track(s.robot, s.seq, s.pose[:2], s.epoch)
    drawn = renderer.draw(img, state=state, camera=top_down(), settings=settings,
                            health=health, reference_pose=reference)
    if settings.legend:
        draw_legend(drawn.canvas, health=health, glyphs_shown=drawn.glyphs_shown,
                     notes=[*rejected_legend(state, settings), *(notes or [])])
    return img


def frames() -> list[np.ndarray]:
    rng = np.random.default_rng(5)
    noise = rng.integers(0, 256, (720, 1280, 3), np.uint8)
    ramp = np.broadcast_to(np.linspace(0, 255, 1280).astype(np.uint8)[None, :, None],
                           (720, 1280, 3)).copy()
    return [noise, ramp, np.full((720, 1280, 3), 255, np.uint8)]


def assert_same_picture(layered: np.ndarray, straight: np.ndarray,
                        frame: np.ndarray) -> None:
    diff = np.abs(layered.astype(int) - straight.astype(int)).max(axis=2)
    assert diff.max() <= MAX_ROUNDING
    assert (diff > 2).mean() < 1e-3  # only where anti-aliased edges overlap
    # untouched where nothing was drawn (the corner away from the map and the legend)
    np.testing.assert_array_equal(layered[700:, 1100:], frame[700:, 1100:])
    np.testing.assert_array_equal(layered[700:, 1100:], straight[700:, 1100:])
    # and what was drawn is there: many pixels differ from the frame in both
    changed = np.abs(straight.astype(int) - frame.astype(int)).max(axis=2) > 30
    assert changed.sum() > 5000
    assert (np.abs(layered.astype(int) - frame.astype(int)).max(axis=2) > 30)[
        changed].mean() > 0.99


HEALTH = Health(robot="r1", seq=10, stamp=10.0, ok=False, suspects=np.array([12]),
                violations=(Violation(kind="pair", ids=(3, 12), step=10, value=0.01),))


@pytest.mark.parametrize("settings", [
    ViewSettings(),
    ViewSettings(mode="minmeanmax", labels=True),
    ViewSettings(mode="inter", glyph="linear", scale=2.0),
    ViewSettings(selected_feature=3, legend=True, health=True),
], ids=["all", "minmeanmax-labels", "inter", "selected-health"])
def test_a_state_put_over_frames_from_its_layers_is_the_state_drawn_on_each(settings) -> None:
    state = paper_state()
    renderer = Renderer(layers_from_n=0)  # (the paper's 15 features: drawn straight else)
    reference = np.array([0.55, 0.25, 0.7])
    notes = [[("map restarted: a note", (0, 165, 255))]]
    for frame in frames():
        before = frame.copy()
        layered = renderer.render(frame, state=state, camera=top_down(), settings=settings,
                                  health=HEALTH, reference_pose=reference, notes=notes)
        np.testing.assert_array_equal(frame, before)  # the frame is not drawn on
        assert layered.shape == frame.shape and layered.dtype == np.uint8
        assert_same_picture(layered, drawn_straight(frame, state, settings, health=HEALTH,
                                                    reference=reference, notes=notes),
                            frame)
    assert renderer.layers_built == 1  # three frames, one state: drawn once


def test_layers_are_drawn_once_per_state_and_the_tracked_pose_moves_with_each_frame() -> None:
    state = paper_state()
    renderer = Renderer(layers_from_n=0)
    settings = ViewSettings()
    frame = np.full((720, 1280, 3), 90, np.uint8)
    camera = top_down()
    rings = []
    for x in (0.0, 0.6, 1.2):  # a new tracked pose per camera frame
        reference = np.array([x, -0.8, 0.0])
        picture = renderer.render(frame, state=state, camera=camera, settings=settings,
                                  reference_pose=reference)
        uv, _ = camera.project(np.array([[x, -0.8, 0.0]]))
        u, v = (int(round(c)) for c in uv[0])
        ring = picture[v - 12:v + 13, u - 12:u + 13]
        rings.append(int((ring.min(axis=2) > 200).sum()))  # the white ring
        assert_same_picture(picture, drawn_straight(frame, state, settings,
                                                    reference=reference), frame)
    assert min(rings) > 20
    assert renderer.layers_built == 1
    # another view's settings, another camera size, another state: drawn again
    renderer.render(frame, state=state, camera=camera, settings=settings.replace(mode="inter"))
    assert renderer.layers_built == 2
    small = cv2.resize(frame, (640, 360))
    renderer.render(small, state=state, camera=camera, settings=settings)
    assert renderer.layers_built == 3
    newer = paper_state(seq=11, pose=(0.6, 0.3, 0.9))
    picture = renderer.render(frame, state=newer, camera=camera, settings=settings)
    assert renderer.layers_built == 4
    assert_same_picture(picture, drawn_straight(frame, newer, settings, earlier=(state,)),
                        frame)
    # a health message that draws the same (same verdict, same pairs): not drawn again
    h2 = Health(robot="r1", seq=11, stamp=11.0, ok=False, suspects=np.array([12]),
                violations=HEALTH.violations)
    hs = settings.replace(health=True)
    renderer.render(frame, state=newer, camera=camera, settings=hs, health=HEALTH)
    built = renderer.layers_built
    renderer.render(frame, state=newer, camera=camera, settings=hs, health=h2)
    assert renderer.layers_built == built


def test_small_maps_are_drawn_straight_and_large_ones_onto_layers() -> None:
    frame = np.full((720, 1280, 3), 90, np.uint8)
    renderer = Renderer(layers_from_n=16)
    renderer.render(frame, state=paper_state(), camera=top_down(), settings=ViewSettings())
    assert renderer.layers_built == 0  # 15 features: cheap, states come faster than frames
    renderer.layers_from_n = 15
    renderer.render(frame, state=paper_state(), camera=top_down(), settings=ViewSettings())
    assert renderer.layers_built == 1


def test_text_on_a_layer_is_the_text_drawn_on_the_picture() -> None:
    rng = np.random.default_rng(1)
    frame = rng.integers(0, 256, (120, 400, 3), np.uint8)
    straight = frame.copy()
    draw.text(straight, "seq 812 fault: pair 3-12", (20, 60), scale=0.8, colour=(0, 0, 255))
    draw.text_box(straight, [[("legend row", (0, 255, 0))], [("second", None)]],
                  origin=(200, 20), scale=0.5)
    layer = draw.new_layer(120, 400)
    draw.text(layer, "seq 812 fault: pair 3-12", (20, 60), scale=0.8, colour=(0, 0, 255))
    draw.text_box(layer, [[("legend row", (0, 255, 0))], [("second", None)]],
                  origin=(200, 20), scale=0.5)
    layered = frame.copy()
    draw.Overlay(layer).put_over(layered)
    diff = np.abs(layered.astype(int) - straight.astype(int))
    assert diff.max() <= 3
    assert (np.abs(straight.astype(int) - frame.astype(int)) > 30).sum() > 500


# -- the state stages: newest-only, lazily copied states -------------------------------
class Viewer:
    """The intake and the pipeline's state stages of a viewer of robot r1 over ``bus``
    (no camera), with ``prepare`` and ``finish`` as the stages' work."""

    def __init__(self, bus, keys: Keys, *, prepare: StateWork,
                 finish: StateWork | None = None) -> None:
        self.wakeups = wakeups = Wakeups()
        drops = DropCounter(logging.getLogger("test"))
        self.intake = Intake(bus, keys=keys, wakeups=wakeups, robots=("r1",), cameras=(),
                             late_join_timeout_s=0.0)
        self.store = InputStore(robots=("r1",), cameras=())
        self.stages = StateStages(self.intake, self.store, wakeups, fps=30.0, drops=drops,
                                  max_frame_pixels=16_777_216, prepare=prepare,
                                  finish=finish)
        self.take_in = TakeIn(self.intake, self.store, prepared=self.stages.take_prepared,
                              drops=drops, max_frame_pixels=16_777_216)

    def start(self) -> None:
        self.intake.start()
        self.stages.start()

    def stop(self) -> None:
        self.intake.stop()
        self.stages.stop()

    def taken_in(self, seq: int, timeout_s: float = 10.0) -> SlamState | None:
        """State ``seq`` as the render thread takes it in from the stages: taken in each
        time the stages hand a state on (their put wakes ``wakeups.input``) until it is
        there; None if the stages hand nothing on for ``timeout_s``."""
        wake = self.wakeups.input
        while True:
            wake.clear()
            self.take_in()
            state = self.store.snapshot().state
            if state is not None and state.seq == seq:
                return state
            if not wake.wait(timeout_s):
                return None


class CountingBus:
    """A real Zenoh bus whose lazy subscriptions count the payloads copied out."""

    def __init__(self, bus, *, arrivals: int) -> None:
        self._bus = bus
        self.copied: list[bytes] = []
        self.arrived = 0
        self.all_arrived = threading.Event()  #: set once ``arrivals`` samples were handed on
        self._arrivals = arrivals

    def __getattr__(self, name: str):
        return getattr(self._bus, name)

    def subscribe_lazy(self, key: str, callback: Callable) -> object:
        def on_sample(k: str, fetch: Callable[[], bytes]) -> None:
            def counted() -> bytes:
                data = fetch()
                self.copied.append(data)
                return data
            callback(k, counted)  # the intake stores it, then we count it
            self.arrived += 1
            if self.arrived >= self._arrivals:
                self.all_arrived.set()

        return self._bus.subscribe_lazy(key, on_sample)


def test_the_viewer_copies_out_and_decodes_only_the_newest_state(make_client) -> None:
    """While a state is being prepared five more arrive: the next one decoded is the
    newest, the four between are never copied out of Zenoh, and the decoded state is the
    one sent (every array equal to the eager decoding of the same bytes)."""
    keys = Keys()
    estimator, viewer = make_client(), CountingBus(make_client(), arrivals=6)
    publisher = estimator.publisher(keys.state("r1"), latest_wins=True)
    prepared: list[int] = []
    hold, in_prepare, second = threading.Event(), threading.Event(), threading.Event()

    def prepare(_robot: str, state: SlamState) -> None:
        prepared.append(state.seq)
        if len(prepared) == 1:
            in_prepare.set()
            assert hold.wait(10.0)
        else:
            second.set()

    pipeline = Viewer(viewer, keys, prepare=prepare)
    pipeline.start()
    try:
        assert estimator.wait_for_subscriber(keys.state("r1"), timeout=10.0)
        payloads = {seq: paper_state(seq=seq, seed=seq).to_bytes() for seq in range(1, 7)}
        # (a publisher that drops may lose a sample on a new route or under load: the
        # first is put until it is being prepared, the newest until six have arrived —
        # the sixth arrival is then always a seq 6, as only five other states exist)
        put_until_seen(lambda: publisher.put(payloads[1]), in_prepare.is_set,
                       what="the first state", timeout_s=30.0, retry_s=5.0)
        for seq in range(2, 7):
            publisher.put(payloads[seq])
        put_until_seen(lambda: publisher.put(payloads[6]), viewer.all_arrived.is_set,
                       what="the newest state", timeout_s=30.0, retry_s=2.0)
        hold.set()
        assert second.wait(10.0)
        assert prepared == [1, 6]
        assert viewer.copied == [payloads[1], payloads[6]]  # 2–5 never copied out
        state = pipeline.taken_in(6)
        assert state is not None and state.seq == 6
        eager = SlamState.from_bytes(payloads[6], check_symmetry=False)
        for name in ("pose", "landmark_ids", "landmarks", "covariance"):
            np.testing.assert_array_equal(getattr(state, name), getattr(eager, name))
        assert (state.robot, state.stamp, state.step) == (eager.robot, eager.stamp,
                                                          eager.step)
    finally:
        hold.set()
        pipeline.stop()


def test_the_next_state_is_prepared_while_the_last_is_drawn_and_it_is_the_newest(
        make_client) -> None:
    """With a second stage (``finish``, thread ``viewer-layers``) state 2 is prepared
    while state 1 is still being finished — the two stages overlap — and, while state 2
    waits for the second stage, states 3–6 arrive: the next one prepared is 6, taken
    only when it can go on, and 3–5 are never copied out of Zenoh."""
    keys = Keys()
    estimator, viewer = make_client(), CountingBus(make_client(), arrivals=6)
    publisher = estimator.publisher(keys.state("r1"), latest_wins=True)
    prepared: list[int] = []
    finished: list[int] = []
    finishing_1, release_1, done = threading.Event(), threading.Event(), threading.Event()
    overlapped: list[bool] = []

    def prepare(_robot: str, state: SlamState) -> None:
        prepared.append(state.seq)

    def finish(_robot: str, state: SlamState) -> None:
        if state.seq == 1:
            finishing_1.set()
            overlapped.append(release_1.wait(30.0))  # released once state 2 is prepared
        finished.append(state.seq)
        if state.seq == 6:
            done.set()

    pipeline = Viewer(viewer, keys, prepare=prepare, finish=finish)
    pipeline.start()
    try:
        assert estimator.wait_for_subscriber(keys.state("r1"), timeout=10.0)
        payloads = {seq: paper_state(seq=seq, seed=seq).to_bytes() for seq in range(1, 7)}
        put_until_seen(lambda: publisher.put(payloads[1]), finishing_1.is_set,
                       what="the first state", timeout_s=30.0, retry_s=5.0)
        # state 1 is held in the second stage: the first stage takes state 2 meanwhile
        put_until_seen(lambda: publisher.put(payloads[2]), lambda: 2 in prepared,
                       what="the second state", timeout_s=30.0, retry_s=5.0)
        for seq in range(3, 6):
            publisher.put(payloads[seq])
        put_until_seen(lambda: publisher.put(payloads[6]), viewer.all_arrived.is_set,
                       what="the newest state", timeout_s=30.0, retry_s=2.0)
        assert prepared == [1, 2]  # state 2 waits for the second stage: nothing taken
        release_1.set()
        assert done.wait(10.0)
        assert overlapped == [True]
        assert prepared == [1, 2, 6] and finished == [1, 2, 6]
        assert viewer.copied == [payloads[1], payloads[2], payloads[6]]  # 3–5 never
        state = pipeline.taken_in(6)
        assert state is not None and state.seq == 6
    finally:
        release_1.set()
        pipeline.stop()
