"""The in-process profiles of ``bench_large.py --profile`` and ``--profile-viewer``, at
n = 1000 on the ``large`` world (docs/large_maps.md):

* :func:`profile_estimator` — cProfile of ``EstimatorService.apply`` with a real Zenoh
  session (shared memory on), grouped by what the time is; the publish path as it was
  before the large-map work timed on the same states;
* :func:`profile_viewer` — the viewer's state → picture path, thread CPU ms per picture,
  with the baselines of before the viewer work measured in the same run.
"""

from __future__ import annotations

import os
import statistics
import time
from collections.abc import Callable
from typing import Any

import msgpack

from slamlens.common.keys import Keys
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus

KEYS = Keys()
ROBOT = "robot1"

#: where the estimator service's time goes: a group's name and the functions it sums
ESTIMATOR_GROUPS = {
    "EKF update (downdate, gains)": ("downdate_lower", "robot_columns", "_check_update",
                                     "mahalanobis", "initialise"),
    "EKF predict": ("predict",),
    "materialise P after an update (symmetric)": ("symmetric",),
    "materialise P after a predict (copy + robot rows)": ("symmetric_after_predict",),
    "patch P in place after a predict (robot rows)": ("robot_rows_into",),
    "finite checks on construction (sums)": ("reduce",),
    "shared-memory copy (ShmPool.wrap)": ("wrap",),
    "encode (wire_parts, msgpack of the small fields)": ("wire_parts", "_wire_dict",
                                                        "encode_array", "pack"),
    "Zenoh put": ("put",),
}

#: where the viewer's time goes per new state: a group's name and the function it is
VIEWER_GROUPS = {
    "overview kernel (group_min_mean_max)": "group_min_mean_max",
    "clusters (cluster_labels + tracker)": "cluster_ids",
    "glyphs and cones (_draw_objects)": "_draw_objects",
    "floor layer (outlines, lines, path)": "_draw_floor_layer",
    "legend": "draw_legend",
    "layers put over the frame (Overlay.put_over)": "put_over",
    "JPEG (imencode)": "imencode",
}


def fill_to_1000(est, events) -> None:
    """Feed ``events`` (an iterator: what is left goes on from there) straight into the
    filter ``est`` until its map has 1000 landmarks."""
    from slamlens.common.messages import Observations, Odometry

    for m in events:
        if isinstance(m, (Odometry, Observations)):
            est.apply(m)
        if est.n >= 1000:
            break


def _large_inputs(service, events: int) -> list:
    """The service's filter filled to n = 1000 with the first loop (unpublished), and the
    next ``events`` + 20 inputs of the simulator as the service takes them."""
    from slamlens.common.messages import Observations, Odometry
    from slamlens.services.slam.input_order import Input
    from slamlens.services.slam.sim import Simulator
    from slamlens.services.slam.world import load_world

    stream = Simulator(load_world("large"), loops=2, seed=0).events()
    fill_to_1000(service.estimator, stream)
    return [Input("odometry" if isinstance(m, Odometry) else "observations", m)
            for m in stream if isinstance(m, (Odometry, Observations))][:events + 20]


def _grouped(stats: dict, groups: dict[str, tuple[str, ...]]) -> dict[str, float]:
    """cProfile's own time (tottime) summed per group of function names."""
    spent = {name: 0.0 for name in groups}
    for (_file, _line, func), (_cc, _nc, tottime, _ct, _callers) in stats.items():
        for name, funcs in groups.items():
            if func in funcs or any(func.startswith(f"<method '{f}'") for f in funcs):
                spent[name] += tottime
    return spent


def _publish_paths(est, bus) -> None:
    """An update state through the publish path of before the large-map work (msgpack.packb
    of a freshly materialised state) and through today's, on the same states; and the
    materialisation alone into one buffer."""
    from slamlens.common.messages import SlamState
    from slamlens.services.slam import ekf

    est.to_state(seq=1, stamp=0.0, step="update")  # warm: today's path's buffers exist
    old, new = [], []
    for _ in range(7):
        t = time.perf_counter()
        cov = ekf.symmetric(est.store.L, 3 + 2 * est.n)
        cov.flags.writeable = False
        old_state = SlamState(robot=ROBOT, seq=1, stamp=0.0, step="update", pose=est.pose,
                              landmark_ids=est.landmark_ids, landmarks=est.landmarks,
                              covariance=cov)
        d = old_state.to_dict()
        d["covariance"] = {"dtype": "<f8", "shape": [cov.size], "data": cov.tobytes()}
        bus.shm.wrap(msgpack.packb(d, use_bin_type=True))
        old.append(time.perf_counter() - t)
        est.published.dirty = True  # as after an update: the whole matrix, no predict shortcut
        t = time.perf_counter()
        state = est.to_state(seq=1, stamp=0.0, step="update")
        bus.shm.wrap(state.wire_parts())
        new.append(time.perf_counter() - t)
        del state
    alone = []
    N = 3 + 2 * est.n
    out = est.published.buffers.array((N, N), "<f8")
    for _ in range(7):
        t = time.perf_counter()
        ekf.symmetric(est.store.L, N, out=out)
        alone.append(time.perf_counter() - t)
    print(f"  ekf.symmetric alone at N = {N}, into one buffer: "
          f"{statistics.median(alone) * 1e3:.1f} ms (median of 7)")
    o, w = statistics.median(old) * 1e3, statistics.median(new) * 1e3
    print(f"  publish path of an update state (materialise + encode + shm): before {o:.1f} ms, "
          f"now {w:.1f} ms (ratio {o / w:.1f}×; median of 7)")


def profile_estimator(events: int = 300) -> None:
    """cProfile of ``EstimatorService.apply`` at n = 1000, grouped by what the time is."""
    import cProfile
    import pstats

    from slamlens.services.slam.estimator_service import EstimatorService
    from slamlens.services.slam.settings import EstimatorSettings

    endpoint = free_tcp_endpoint()
    router = open_bus(BusSettings(listen=(endpoint,), mode="router"))
    bus, sub = (open_bus(BusSettings(connect=(endpoint,))) for _ in range(2))
    received = [0]
    sub.session.declare_subscriber(  # a same-host consumer: the payload stays in shm
        KEYS.state(ROBOT), lambda _s: received.__setitem__(0, received[0] + 1))
    service = EstimatorService(bus, keys=KEYS, settings=EstimatorSettings(robot=ROBOT))
    est = service.estimator
    items = _large_inputs(service, events)
    for item in items[:20]:  # warm: the shared-memory pool is made on first use
        service.apply(item)
    reused_before = est.published.buffers.reused
    profiler = cProfile.Profile()
    t0 = time.perf_counter()
    profiler.enable()
    for item in items[20:]:
        service.apply(item)
    profiler.disable()
    wall = time.perf_counter() - t0
    spent = _grouped(pstats.Stats(profiler).stats, ESTIMATOR_GROUPS)  # type: ignore[attr-defined]
    n = len(items) - 20
    print(f"PROFILE estimator service at n = {est.n}: {n} events in {wall:.2f} s = "
          f"{n / wall:.0f} states/s (under cProfile), load {os.getloadavg()[0]:.2f}; "
          f"{received[0]} received by a same-host subscriber, shm {bus.shm.shared} / plain "
          f"{bus.shm.plain}; predict states patched in place {est.predicts_in_place}, "
          f"covariance buffers reused {est.published.buffers.reused - reused_before} of {n}")
    for name, t in sorted(spent.items(), key=lambda kv: -kv[1]):
        print(f"  {name:52s} {t / n * 1e3:6.2f} ms per state ({t / wall:5.1%})")
    _publish_paths(est, bus)
    for b in (bus, sub, router):
        b.close()


class ViewerProfile:
    """A real state of the ``large`` world at n = 1000 (and ``repeats`` + 1 copies of it
    under new seqs), camera frames to draw it on, and the thread CPU time of each step."""

    def __init__(self, repeats: int) -> None:
        import dataclasses

        import numpy as np

        from slamlens.common.messages import SlamState
        from slamlens.services.slam.estimator import Estimator
        from slamlens.services.slam.settings import EstimatorSettings
        from slamlens.services.slam.sim import Simulator
        from slamlens.services.slam.world import load_world
        from slamlens.services.visualiser.camera_model import CameraModel

        est = Estimator(EstimatorSettings(robot=ROBOT))
        fill_to_1000(est, Simulator(load_world("large"), loops=2, seed=0).events())
        self.repeats = repeats
        self.payload = est.to_state(seq=1, stamp=0.0, step="update").to_bytes()
        self.state0 = SlamState.from_bytes(self.payload, check_symmetry=False)
        self.states = [dataclasses.replace(self.state0, seq=2 + k) for k in range(repeats + 1)]
        self.camera = CameraModel.top_down(bounds_xy=(-1.5, -1.5, 39.5, 24.5), width=1280,
                                           height=720)
        self.frames = [np.full((720, 1280, 3), 60 + k, np.uint8) for k in range(repeats + 1)]

    def cpu_ms(self, f: Callable[[int], Any], k_from: int = 1) -> float:
        """Median thread CPU ms of ``f(k)`` over k = ``k_from`` … ``repeats``."""
        spent = []
        for k in range(self.repeats + 1):
            t = time.thread_time()
            f(k)
            spent.append((time.thread_time() - t) * 1e3)
        return statistics.median(spent[k_from:])

    def picture(self, renderer, state, k: int, settings) -> None:
        """One picture as the viewer sends it: rendered over frame ``k``, JPEG-encoded."""
        import cv2

        cv2.imencode(".jpg", renderer.render(self.frames[k], state=state, camera=self.camera,
                                             settings=settings))


def _viewer_decode(vp: ViewerProfile) -> None:
    from slamlens.common.messages import SlamState

    in_place = vp.cpu_ms(lambda k: SlamState.from_bytes(vp.payload, check_symmetry=False))
    # baseline in the same run: msgpack's own decode (it copies the covariance), as before
    copied = vp.cpu_ms(lambda k: SlamState.from_dict(msgpack.unpackb(
        vp.payload, raw=False, strict_map_key=False), check_symmetry=False))
    print(f"  decode a state (SlamState.from_bytes, {len(vp.payload) / 2 ** 20:.1f} MiB): "
          f"{in_place:.1f} ms, its arrays in place; msgpack.unpackb + from_dict {copied:.1f} "
          f"ms (ratio {in_place / copied:.2f})")


def _viewer_modes(vp: ViewerProfile) -> None:
    from slamlens.services.visualiser.render import Renderer
    from slamlens.services.visualiser.settings import ViewSettings

    for mode in ("all", "minmeanmax"):
        settings = ViewSettings(mode=mode)
        r = Renderer()
        new = vp.cpu_ms(lambda k, r=r, s=settings: vp.picture(r, vp.states[k], k, s))
        same = vp.cpu_ms(lambda k, r=r, s=settings: vp.picture(r, vp.states[-1], k, s))
        fresh = vp.cpu_ms(lambda k, s=settings: vp.picture(Renderer(), vp.states[-1], k, s))
        print(f"  mode {mode:10s}: new state {new:5.1f} ms; camera frame, same state "
              f"{same:5.1f} ms (scene reused) vs {fresh:5.1f} ms recomputed "
              f"(ratio {fresh / same:.1f}×)")


def _viewer_layers(vp: ViewerProfile) -> None:
    """A state drawn onto layers once, put over every camera frame; baseline in the same
    run: every step drawn straight onto each frame (as before the layers)."""
    from slamlens.services.visualiser.legend import draw_legend, rejected_legend
    from slamlens.services.visualiser.render import Renderer
    from slamlens.services.visualiser.settings import ViewSettings

    settings, state = ViewSettings(), vp.states[-1]
    r = Renderer()
    r.scene(state, settings)
    layers = vp.cpu_ms(lambda k: (r.layer_cache.clear(), r.layers(state, vp.camera, settings)))
    over = vp.cpu_ms(lambda k: r.render(vp.frames[k], state=state, camera=vp.camera,
                                        settings=settings))

    def straight(k: int) -> None:
        drawn = r.draw(vp.frames[k].copy(), state=state, camera=vp.camera, settings=settings)
        draw_legend(drawn.canvas, health=None, glyphs_shown=drawn.glyphs_shown,
                    notes=rejected_legend(state, settings))

    direct = vp.cpu_ms(straight)
    copy = vp.cpu_ms(lambda k: bytearray(vp.payload))
    print(f"  a state onto its layers (once per state, viewer-layers) {layers:5.1f} ms; a "
          f"camera frame: layers put over it {over:5.2f} ms vs drawn straight {direct:5.1f} "
          f"ms (ratio {direct / over:.0f}×)")
    print(f"  a {len(vp.payload) / 2 ** 20:.1f} MiB payload copied (each state the viewer "
          f"skipped, before subscribe_lazy): {copy:.1f} ms")


def _viewer_sample(vp: ViewerProfile) -> None:
    from slamlens.common.geometry import all_relative_covariances, pd_size_m
    from slamlens.services.visualiser.series import SeriesStore

    store = SeriesStore(min_interval_s=0.0)
    sample = vp.cpu_ms(lambda k: SeriesStore(min_interval_s=0.0).add_state(vp.states[k],
                                                                            now=0.0))
    old = vp.cpu_ms(lambda k: pd_size_m(all_relative_covariances(vp.states[k].covariance,
                                                                 vp.states[k].n)[2]))
    store.add_state(vp.states[0], now=0.0)
    print(f"  plot sample: {sample:.1f} ms (every pair's size, {store.interval_s:.2f} s "
          f"apart at most: ≤ 1/20 of the time) vs before {old:.1f} ms every 0.2 s "
          f"(ratio {old / sample:.1f}×)")


def _viewer_groups(vp: ViewerProfile) -> None:
    import cProfile
    import pstats

    from slamlens.services.visualiser.render import Renderer
    from slamlens.services.visualiser.settings import ViewSettings

    settings, r = ViewSettings(), Renderer()
    profiler = cProfile.Profile(time.thread_time)
    profiler.enable()
    for k in range(vp.repeats):
        vp.picture(r, vp.states[k], k, settings)
    profiler.disable()
    stats = pstats.Stats(profiler).stats  # type: ignore[attr-defined]
    for name, func in VIEWER_GROUPS.items():
        total = sum(v[3] for (_f, _l, fn), v in stats.items()
                    if fn == func or (fn.startswith("<") and func in fn))
        print(f"  {name:40s} {total / vp.repeats * 1e3:6.1f} ms per new state")


def profile_viewer(repeats: int = 9) -> None:
    """The viewer's state → picture path in this process at n = 1000 (a real state of the
    ``large`` world): thread CPU ms per picture of a new state and per camera frame of the
    same state, the plot sample, decoding; baselines in the same run: the scene computed
    for every picture (a fresh ``Renderer`` each time, as before the viewer work)
    and the plot sample as before (every pair's P_d gathered, then its size)."""
    vp = ViewerProfile(repeats)
    print(f"PROFILE viewer at n = {vp.state0.n} (thread CPU ms, median of {repeats}), load "
          f"{os.getloadavg()[0]:.2f}:")
    _viewer_decode(vp)
    _viewer_modes(vp)
    _viewer_layers(vp)
    _viewer_sample(vp)
    _viewer_groups(vp)
