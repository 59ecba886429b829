"""Commands of the SLAM side: ``sim``, ``estimator``, ``replay``, ``serial``, ``summary``,
``tune``.

Each command: its settings (:mod:`slamlens.services.slam.settings`) from ``--config FILE`` with the
flags over it, a bus from the common flags, the service's ``run`` until SIGINT/SIGTERM (or
the end of the data), and a clean close of the Zenoh session. The flags themselves are
built from the settings by ``services/commands/cli.py``.
"""

from __future__ import annotations

import argparse
import heapq
import itertools
import json
import logging
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from slamlens.common.cli import command_bus, keys_from, one_blas_thread, setup_logging, stop_event
from slamlens.common.config import settings_from_args
from slamlens.common.errors import ConfigError
from slamlens.common.progress import count_bar, enabled, time_bar
from slamlens.common.status import Report, announce, counts_of
from slamlens.services.slam.settings import (
    INVARIANT,
    LINEARISATIONS,
    EstimatorSettings,
    ReplaySettings,
    SerialSettings,
    SimSettings,
    SummarySettings,
    TuneSettings,
)

log = logging.getLogger("slamlens")


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, command)
    return {"sim": _run_sim, "estimator": _run_estimator, "replay": _run_replay,
            "serial": _run_serial, "tune": _run_tune,
            "summary": _run_summary}[command](args)


def _estimator_ready(out: Any, stop: threading.Event, s: SimSettings | ReplaySettings) -> bool:
    """Wait (if configured) for the robot's estimator; False if stopped while waiting."""
    if not s.wait_for_estimator or out.wait_for_estimator(stop, timeout_s=s.wait_timeout_s):
        return True
    if stop.is_set():
        return False
    robots = ", ".join(out.robots)
    raise ConfigError(f"no estimator for robot {robots} appeared within "
                      f"{s.wait_timeout_s:g} s (use --no-wait to publish anyway)")


def _driver_status(out: Any, state: dict[str, str]) -> Any:
    """The status provider of a driver: what it published, and whether it waits."""
    def status() -> Report:
        counts = out.counts
        inputs = counts.get("Odometry", 0) + counts.get("Observations", 0)
        return Report(state=state["now"], counts={"inputs": float(inputs),
                                                  **{k: float(v) for k, v in counts.items()}})
    return status


def _run_sim(args: argparse.Namespace) -> int:
    from slamlens.services.slam.drivers import Fleet, play
    from slamlens.services.slam.sim import Simulator, staggered
    from slamlens.services.slam.world import load_world

    s = settings_from_args(SimSettings, args)
    world = load_world(s.scenario)
    sims = []
    for k, robot in enumerate(s.robots()):
        mine, origin = staggered(world, k)
        sims.append(Simulator(mine, robot=robot, seed=s.seed + k, anonymous=s.anonymous,
                              loops=s.loops or None, truth_origin=origin,
                              marker_id=s.marker_id_of(k)))
    stop = stop_event()
    bus = command_bus(args)
    try:
        out = Fleet(bus, keys=keys_from(args), robots=s.robots())
        state = {"now": "waiting for an estimator"}
        announce(bus, args, "sim", _driver_status(out, state), robot=",".join(s.robots()))
        print("sim ready", flush=True)
        if not _estimator_ready(out, stop, s):
            _finish("sim", out, stop, 0.0)  # stopped while it waited
            return 0
        who = f"{len(sims)} robots ({s.robot})" if len(sims) > 1 else s.robot
        log.info("simulating %s with %s, seed %d, %.0f s of robot time at %s", world.name,
                 who, s.seed, sims[0].duration_s,
                 f"{s.rate:g}× real time" if s.rate else "full speed")
        streams = [iter(sim.events()) for sim in sims]
        firsts = [next(events) for events in streams]  # the Truth at t = 0: the start poses
        if s.hold_s:
            state["now"] = "holding at the start pose"
            log.info("standing at the start pose for %.1f s", s.hold_s)
            hold_until = time.monotonic() + s.hold_s
            while time.monotonic() < hold_until and not stop.is_set():
                for first in firsts:
                    out.publish(first)
                stop.wait(0.1)
        if s.rate == 0 and s.wait_for_estimator:
            out.pace_on_estimator()
        state["now"] = "driving"
        events = heapq.merge(*(itertools.chain([first], rest)
                               for first, rest in zip(firsts, streams, strict=True)),
                             key=lambda m: m.stamp)  # type: ignore[attr-defined]
        bar = time_bar(sims[0].duration_s, desc=f"sim {s.robot}", mode=s.progress)
        try:
            wall = play(events, out, stop, rate=s.rate,
                        progress_every_s=_log_every(10.0 if s.rate and s.rate <= 5 else 0.0,
                                                    s.progress), bar=bar)
        finally:
            bar.close()
        state["now"] = "done"
        _finish("sim", out, stop, wall)
    finally:
        bus.close()
    return 0


def _log_every(every_s: float, mode: str) -> float:
    """Data seconds between progress log lines: none while a bar shows the progress."""
    return 0.0 if enabled(mode) else every_s


def _finish(name: str, out: Any, stop: threading.Event, wall: float) -> None:
    """The driver's final line: what it published, and whether the estimator applied it."""
    applied = ""
    if out.pacer is not None and not stop.is_set():
        applied = (", all applied by the estimator" if out.pacer.drain(stop)
                   else ", NOT all applied: the estimator applied nothing for 10 s")
    verb = "stopped" if stop.is_set() else "done"
    log.info("%s in %.2f s wall: %s", verb, wall, out.counts)
    print(f"{name} {verb}: {json.dumps(out.counts)} in {wall:.2f} s{applied}", flush=True)


def _run_estimator(args: argparse.Namespace) -> int:
    one_blas_thread()
    from slamlens.common.state_header import INPUT_COUNTS
    from slamlens.services.slam.estimator_service import EstimatorService

    settings = settings_from_args(EstimatorSettings, args)
    stop = stop_event()
    bus = command_bus(args)
    try:
        service = EstimatorService(bus, keys=keys_from(args), settings=settings)

        def status() -> Report:
            summary = service.summary()
            refused_by = summary["refused_by"]
            assert isinstance(refused_by, dict)
            state = "resumed" if service.resumed else "running"
            if service.waiting_for_sources:
                state = service.waiting_for_sources
            if refused_by:  # refusals by reason, visible in `slamlens status`
                state += "; refused " + ", ".join(f"{k} {v}" for k, v in refused_by.items())
            return Report(state=state,
                          counts=counts_of(summary, "states", "odometry",
                                           "observation_batches", "landmarks",
                                           "refused", "gated", *INPUT_COUNTS),
                          dropped=int(summary["dropped"]),  # type: ignore[call-overload]
                          lost=int(summary["lost"]),  # type: ignore[call-overload]
                          epoch=service.epoch)

        announce(bus, args, "estimator", status, robot=settings.robot)
        fault = "" if settings.fault == "none" else (
            f", planted fault {settings.fault} on {list(settings.faulty_features)}")
        log.info("estimator for %s ready%s", settings.robot, fault)
        print("estimator ready", flush=True)
        service.run(stop)
        print(f"estimator stopped: {json.dumps(service.summary())}", flush=True)
    finally:
        bus.close()
    return 0


def _replay_robots(s: ReplaySettings) -> list[tuple[int, str]]:
    """(dataset robot number, name) of each robot to replay."""
    from slamlens.services.slam.mrclam import available_robots

    if not s.robots:
        return [(s.robot_index, s.robot)]
    numbers = available_robots(s.path) if s.robots == "all" else \
        [int(k) for k in s.robots.split(",") if k.strip()]
    if not numbers:
        raise ConfigError(f"--robots {s.robots}: no Robot{{K}}_Odometry.dat in {s.path}")
    return [(k, f"robot{k}") for k in numbers]


def _replay_runs(s: ReplaySettings) -> list[Any]:
    """The dataset's runs to replay, one per robot (MRCLAM or Victoria Park)."""
    if s.format == "victoria-park":
        from slamlens.services.slam.victoria_park import load_victoria_park

        if s.robots:
            raise ConfigError("--robots is for MRCLAM; Victoria Park is one robot (--robot R)")
        return [load_victoria_park(s.path, robot=s.robot, step_s=s.step_s)]
    from slamlens.services.slam.mrclam import load_mrclam

    return [load_mrclam(s.path, robot=k, robot_name=name) for k, name in _replay_robots(s)]


def _run_replay(args: argparse.Namespace) -> int:
    from slamlens.services.slam.drivers import Fleet, play

    s = settings_from_args(ReplaySettings, args)
    runs = _replay_runs(s)
    names = [run_.robot for run_ in runs]
    stop = stop_event()
    bus = command_bus(args)
    try:
        out = Fleet(bus, keys=keys_from(args), robots=names)
        state = {"now": "waiting for an estimator"}
        announce(bus, args, "replay", _driver_status(out, state), robot=",".join(names))
        print("replay ready", flush=True)
        if not _estimator_ready(out, stop, s):
            _finish("replay", out, stop, 0.0)  # stopped while it waited
            return 0
        if len(runs) > 1:
            log.info("replaying %d robots of %s: %s", len(runs), s.path, ", ".join(names))
        end = (s.start_s + s.duration_s) if s.duration_s else None
        events = heapq.merge(*(run_.events(start=s.start_s or None, end=end) for run_ in runs),
                             key=lambda m: m.stamp)  # type: ignore[attr-defined]
        if s.rate == 0 and s.wait_for_estimator:
            out.pace_on_estimator()
        state["now"] = "replaying"
        duration = max(run_.duration_s for run_ in runs)
        total = (min(end, duration) if end is not None else duration) - s.start_s
        bar = time_bar(total, desc=f"replay {s.robot}", mode=s.progress)
        try:
            wall = play(events, out, stop, rate=s.rate, bar=bar,
                        progress_every_s=_log_every(30.0, s.progress))
        finally:
            bar.close()
        state["now"] = "done"
        _finish("replay", out, stop, wall)
    finally:
        bus.close()
    return 0


def _run_serial(args: argparse.Namespace) -> int:
    from slamlens.services.slam.drivers import RobotPublisher
    from slamlens.services.slam.serial_link import SerialLink

    s = settings_from_args(SerialSettings, args)
    stop = stop_event()
    bus = command_bus(args)
    link = SerialLink(s.port, baudrate=s.baudrate, robot=s.robot)
    try:
        out = RobotPublisher(bus, keys=keys_from(args), robot=s.robot)
        announce(bus, args, "serial", _driver_status(out, {"now": "running"}), robot=s.robot)
        # Opening flushes the port's input (pyserial resets the buffer): open before saying
        # ready, so every byte the robot sends after "serial ready" reaches the parser.
        opened = link.open()
        print("serial ready" + ("" if opened else f" (port {s.port} not open yet; retrying)"),
              flush=True)
        for message in link.messages(stop):
            out.publish(message)
        print(f"serial stopped: published {json.dumps(out.counts)}, parser {link.stats}",
              flush=True)
    finally:
        link.close()
        bus.close()
    return 0


def _run_summary(args: argparse.Namespace) -> int:
    one_blas_thread()
    from slamlens.services.slam.summary_service import SummaryService

    settings = settings_from_args(SummarySettings, args)
    stop = stop_event()
    bus = command_bus(args)
    try:
        service = SummaryService(bus, keys=keys_from(args), robot=settings.robot,
                                 settings=settings)

        def status() -> Report:
            s = service.summary()
            return Report(counts=counts_of(s, "answered", "made", "shared", "refused",
                                           "received", "decoded"),
                          dropped=int(s["dropped"]))  # type: ignore[call-overload]

        announce(bus, args, "summary", status, robot=settings.robot)
        print("summary ready", flush=True)
        service.run(stop)
        print(f"summary stopped: {json.dumps(service.summary())}", flush=True)
    finally:
        bus.close()
    return 0


def _linearisations(s: TuneSettings) -> list[str]:
    """The linearisations ``slamlens tune`` fits for: the one named, or all of them — but
    the invariant EKF, which has no iterated update, with ``--update-iterations`` > 1."""
    out = [lin for lin in LINEARISATIONS if s.linearisation in (lin, "all")
           and not (lin == INVARIANT and s.update_iterations > 1)]
    if not out:
        raise ConfigError("the invariant EKF has no iterated update: leave out "
                          "--update-iterations or choose another --linearisation")
    return out


def _scales(s: TuneSettings) -> list[str]:
    """What the NEES scale multiplies, as ``slamlens tune`` tries it: the rule named, or
    both (``--scale choose``)."""
    return ["motion", "all"] if s.scale == "choose" else [s.scale]


def _run_tune(args: argparse.Namespace) -> int:
    from slamlens.services.slam import crossval, scoring, tuning
    from slamlens.services.slam.mrclam import load_mrclam

    s = settings_from_args(TuneSettings, args)
    runs = [load_mrclam(s.path, robot=k, robot_name=f"robot{k}", truth_folder=s.truth or None)
            for k in s.robot_index]
    events = sum(scoring.event_count(run) for run in runs)
    log.info("fitting noise to %s, robots %s (%d events per estimator pass)", s.path,
             list(s.robot_index), events)
    bars: list[Any] = []

    def bar(desc: str, total: int) -> Any:
        for old in bars:
            old.close()
        bars.append(count_bar(total, desc=desc, mode=s.progress))
        return bars[-1].update

    def fold_progress(what: str, number: int, scale: float, total: int) -> Any:
        step = "scoring the robot left out" if number == 0 else f"pass {number}"
        return bar(f"tune ({what}) {step} (σ × {scale:.3f})", total)

    candidates = [(lin, scale) for lin in _linearisations(s) for scale in _scales(s)]
    notes: list[str] = []
    cv: crossval.CrossValidation | None = None
    pool = ProcessPoolExecutor(s.jobs) if s.jobs > 1 and len(runs) > 1 else None
    try:
        if s.cross_validate and len(runs) >= 2:
            results = [crossval.cross_validate(
                runs, crossval.Candidate(lin, s.motion_model, s.update_iterations, scale),
                gate_chi2=s.gate_chi2, progress=fold_progress, executor=pool)
                for lin, scale in candidates]
            cv = crossval.choose(results)
            notes = crossval.report(results, cv)
            for line in notes:
                print(line, file=sys.stderr, flush=True)
            candidates = [(cv.candidate.linearisation, cv.candidate.scale)]

        def passes(lin: str, scale: str) -> Any:
            return lambda n, c: bar(f"tune ({lin}, {scale} σ) pass {n} (σ × {c:.3f})", events)

        fits = [tuning.tune(runs, motion_model=s.motion_model, gate_chi2=s.gate_chi2,
                            base=EstimatorSettings(linearisation=lin,
                                                   update_iterations=s.update_iterations),
                            scaled=scale, progress=passes(lin, scale), executor=pool)
                for lin, scale in candidates]
    finally:
        for old in bars:
            old.close()
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    result = min(fits, key=tuning.in_sample_rank)
    for line in tuning.camera_lines(result.fit.cameras):
        print(line, file=sys.stderr, flush=True)
    if len(fits) > 1:  # no robot left out to judge by: the fit's own figures decide
        notes = [f"chosen by the fit itself (no robot left out): {r.linearisation}, "
                 f"{r.scaled} σ scaled, pooled NEES {r.pooled_nees:.2f}, "
                 f"{'in' if r.passes() else 'NOT in'} its band" for r in fits]
    robots = ",".join(str(k) for k in s.robot_index)
    header = [f"slamlens estimator settings fitted by: slamlens tune {s.path} --robot-index "
              f"{robots} --motion-model {s.motion_model} --gate-chi2 {s.gate_chi2:g} "
              f"--linearisation {s.linearisation} --scale {s.scale}"
              + (f" --update-iterations {s.update_iterations}" if s.update_iterations > 1
                 else "")
              + ("" if s.cross_validate else " --no-cross-validate"),
              "use: slamlens estimator --config THIS_FILE --robot R (docs/estimator.md)"]
    text = tuning.profile_toml(result, header=header, notes=notes)
    if s.folds and cv is not None:
        _write_folds(Path(s.folds), cv, header)
    if s.output:
        Path(s.output).write_text(text)
        log.info("wrote %s", s.output)
    else:
        print(text, end="", flush=True)
    return _tune_done(result, cv)


def _write_folds(folder: Path, cv: Any, header: list[str]) -> None:
    """Each leave-one-robot-out profile as DIR/without-robotK.toml (``tune --folds``)."""
    from slamlens.services.slam import tuning

    folder.mkdir(parents=True, exist_ok=True)
    for fold in cv.folds:
        path = folder / f"without-{fold.held_out}.toml"
        e = fold.test
        path.write_text(tuning.profile_toml(fold.result, header=[
            *header, f"this is the fold with {fold.held_out} left out: fitted on the others; "
                     f"on {fold.held_out}: pose NEES {e.nees_mean:.2f}, landmark RMSE after "
                     f"a rigid fit {e.landmark_rmse_rigid:.3f} m"]))
        log.info("wrote %s", path)


def _tune_done(result: Any, cv: Any) -> int:
    """The final line and the exit status: 0 when every robot left out meets the targets
    (or, with no robot left out, the fit's own NEES check passes)."""
    if cv is not None:
        ok = cv.meeting == len(cv.folds)
        verdict = ("every robot left out meets the targets" if ok else
                   f"{len(cv.folds) - cv.meeting} robot(s) left out do NOT meet the targets")
    else:
        ok = result.passes()
        verdict = "NEES in its band" if ok else "NEES NOT in its band"
    held = [] if cv is None else [{**e.summary(), "left_out": True} for e in cv.held_out]
    print(f"tune done: {json.dumps([e.summary() for e in result.after] + held)}; "
          f"linearisation {result.linearisation}; scale {result.scale:.3f} after "
          f"{result.passes_run} passes; {verdict}", flush=True)
    return 0 if ok else 1
