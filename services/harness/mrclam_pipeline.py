"""UTIAS MRCLAM through the real processes, for tests and benchmarks.

``run_pipeline`` starts a router, ``slamlens estimator --config deploy/mrclam.toml``,
``slamlens monitor`` and ``slamlens replay --rate 0`` as separate processes on a free
loopback port, receives every state (a recovering subscriber) and every Health, scores the
states against the dataset's ground truth (:class:`slamlens.services.slam.tuning.Scorer`, truth
interpolated at each state's stamp) and returns the figures with the services' final lines.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slamlens.common.config import load_settings
from slamlens.common.keys import Keys
from slamlens.common.messages import Health, SlamState
from slamlens.common.session import BusSettings, free_tcp_endpoint, open_bus
from slamlens.services.harness.procs import REPO, spawn, stop
from slamlens.services.monitor.settings import MonitorSettings
from slamlens.services.monitor.stats import WindowTest
from slamlens.services.slam.mrclam import load_mrclam
from slamlens.services.slam.scoring import Evaluation, Scorer, TruthTrack, dead_reckoning_track
from slamlens.services.slam.settings import EstimatorSettings

DATA = REPO.parent / "shared" / "data" / "mrclam6"
PROFILE = REPO / "deploy" / "mrclam.toml"
#: the truth "covers" a state when it has samples ≤ 0.5 s apart over the 3 s before it: time
#: for the monitor's pose NEES window to judge again after a gap (docs/monitor.md)
TRUTH_SPAN_S = 3.0

def _monitor_nis_band() -> tuple[int, float, float]:
    s = MonitorSettings()
    test = WindowTest(dof=2, window=s.nis_window, alpha=s.significance, band="white")
    return test.window, test.lo, test.hi


#: the monitor's NIS windows and their textbook band, for white innovations (the sensor
#: model experiments of docs/consistency.md count windows outside it; the monitor's own band
#: counts the innovations' measured dependence, docs/monitor.md)
NIS_WINDOW, NIS_LO, NIS_HI = _monitor_nis_band()


#: the fold profiles of the shipped profile's tune run, and those of OC's (the linearisation
#: shipped before: the experiments of docs/consistency.md were measured with them)
FOLDS = REPO / "benchmarks" / "profiles"
OC_FOLDS = FOLDS / "oc"


def left_out_profile(robot: int, folds: Path = FOLDS) -> EstimatorSettings:
    """The profile fitted on the other four robots (``folds``/without-robotK.toml)."""
    return load_settings(EstimatorSettings, folds / f"without-robot{robot}.toml")


def nis_windows_out(nis: np.ndarray) -> tuple[float, float]:
    """Shares of the monitor's tumbling NIS windows over ``nis`` below and above their band."""
    means = nis[:nis.size // NIS_WINDOW * NIS_WINDOW].reshape(-1, NIS_WINDOW).mean(axis=1)
    return float(np.mean(means < NIS_LO)), float(np.mean(means > NIS_HI))


@dataclass
class PipelineResult:
    evaluation: Evaluation
    states: int  #: states of inputs received (the init state, published at start-up, not counted)
    last_seq: int
    verdicts: dict[str, int]  #: Health verdicts received, by verdict
    #: "tuning" Healths by the kinds standing (e.g. "nees", "nis", "nees+nis")
    tuning_kinds: dict[str, int] = field(default_factory=dict)
    #: "tuning" Healths with no NEES standing where the truth covers the last TRUTH_SPAN_S
    tuning_without_nees_with_truth: int = 0
    fault_healths: list[dict] = field(default_factory=list)  #: a few "fault" ones, if any
    estimator: dict = field(default_factory=dict)  #: its final line
    monitor: dict = field(default_factory=dict)  #: its final line
    replay_line: str = ""
    monitor_log: str = ""  #: its stderr
    monitor_out: str = ""  #: its stdout (the verdict in words, the final line)
    wall_s: float = 0.0


class _Collector:
    """Receives every state and Health of one robot; scores states as they come."""

    def __init__(self, endpoint: str, robot: str, truth: TruthTrack,
                 dead: TruthTrack) -> None:
        self.bus = open_bus(BusSettings(connect=(endpoint,)))
        keys = Keys()
        self.scorer = Scorer(truth, robot=robot, dead_reckoning=dead)
        self.states = self.bus.channel(keys.state(robot), recover=True)
        self.healths = self.bus.channel(keys.health(robot), recover=True)
        self.count = 0
        self.last: SlamState | None = None
        self.verdicts: dict[str, int] = {}
        self.tuning_kinds: dict[str, int] = {}
        self.truth = truth
        self.tuning_without_nees_with_truth = 0
        self.faults: list[dict] = []
        self.healths_of_inputs = 0
        self.errors: list[str] = []
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._read_states, daemon=True),
                         threading.Thread(target=self._read_healths, daemon=True)]
        for t in self._threads:
            t.start()

    def _read_states(self) -> None:
        while not self._stop.is_set():
            sample = self.states.recv(timeout=0.2)
            if sample is None:
                continue
            try:
                state = SlamState.from_bytes(sample.payload)
            except Exception as exc:  # noqa: BLE001 - a test must see it, not die silently
                self.errors.append(repr(exc))
                continue
            self.last = state
            if state.step != "init":
                self.count += 1
                self.scorer.add_state(state)

    def _read_healths(self) -> None:
        while not self._stop.is_set():
            sample = self.healths.recv(timeout=0.2)
            if sample is None:
                continue
            health = Health.from_bytes(sample.payload)
            self.verdicts[health.verdict] = self.verdicts.get(health.verdict, 0) + 1
            if health.verdict == "tuning":
                kinds = "+".join(sorted({v.kind for v in health.standing}))
                self.tuning_kinds[kinds] = self.tuning_kinds.get(kinds, 0) + 1
                if "nees" not in kinds.split("+") and self.truth.covers(
                        health.stamp, before_s=TRUTH_SPAN_S):
                    self.tuning_without_nees_with_truth += 1
            self.healths_of_inputs += health.seq > 0
            if health.verdict == "fault" and len(self.faults) < 5:
                self.faults.append({"seq": health.seq, "standing": [
                    v.to_dict() for v in health.standing[:5]]})

    def settle(self, seq: int, timeout_s: float = 120.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.last is not None and self.last.seq >= seq and self.states.backlog == 0:
                return True
            time.sleep(0.05)
        return False

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(5)
        self.bus.close()


def _final(out: str, name: str) -> dict:
    for line in reversed(out.splitlines()):
        if line.startswith(f"{name} stopped: "):
            return json.loads(line.split(": ", 1)[1])
    raise AssertionError(f"no final line from {name}:\n{out[-2000:]}")


def run_pipeline(robot_index: int, *, profile: Path = PROFILE, data: Path = DATA,
                 timeout_s: float = 900.0) -> PipelineResult:
    robot = f"robot{robot_index}"
    run = load_mrclam(data, robot_index, robot_name=robot)
    truth = TruthTrack.from_mrclam(run)
    endpoint = free_tcp_endpoint()
    env = {"OPENBLAS_NUM_THREADS": "1"}
    router = spawn("router", "--listen", endpoint)
    procs = [router]
    collector = None
    try:
        router.wait_for_line("router ready", timeout=30)
        est = spawn("estimator", "--config", str(profile), "--robot", robot, "--connect",
                    endpoint, env=env)
        procs.append(est)
        mon = spawn("monitor", "--robot", robot, "--connect", endpoint, env=env)
        procs.append(mon)
        est.wait_for_line("estimator ready", timeout=60)
        mon.wait_for_line("monitor ready", timeout=60)
        collector = _Collector(endpoint, robot, truth, dead_reckoning_track(run))
        started = time.monotonic()
        replay = spawn("replay", str(data), "--robot", robot, "--robot-index",
                       str(robot_index), "--rate", "0", "--connect", endpoint)
        procs.append(replay)
        replay_line = replay.wait_for_line("replay done", timeout=timeout_s)
        replay.wait(30)
        counts = json.loads(replay_line.split("replay done: ", 1)[1].split(" in ")[0])
        inputs = counts["Odometry"] + counts["Observations"]
        # every state received before the estimator stops: its cache is what a gap the
        # collector's recovery finds late is filled from (it goes with the process)
        assert collector.settle(inputs), (
            f"received up to seq {collector.last.seq if collector.last else None} of "
            f"{inputs}; queue dropped {collector.states.dropped}, lost {collector.states.lost}")
        est_out, _ = stop(est)
        estimator = _final(est_out, "estimator")
        # the monitor has checked everything when it has seen the last state
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and collector.healths_of_inputs < collector.count:
            time.sleep(0.1)
        wall = time.monotonic() - started
        mon_out, mon_err = stop(mon)
        monitor = _final(mon_out, "monitor")
        last = collector.last
        assert last is not None
        assert (collector.states.dropped, collector.states.lost) == (0, 0), (
            "states the collector's queue dropped / its recovery could not get back")
        evaluation = collector.scorer.finish(last.landmark_ids, last.landmarks,
                                             dict(last.diagnostics or {}))
        return PipelineResult(
            evaluation=evaluation, states=collector.count, last_seq=last.seq,
            verdicts=dict(collector.verdicts), tuning_kinds=dict(collector.tuning_kinds),
            tuning_without_nees_with_truth=collector.tuning_without_nees_with_truth,
            fault_healths=collector.faults,
            estimator=estimator, monitor=monitor, replay_line=replay_line.strip(),
            monitor_log=mon_err, monitor_out=mon_out, wall_s=wall)
    finally:
        if collector is not None:
            collector.close()
        for p in reversed(procs):
            if p.poll() is None:
                stop(p)
