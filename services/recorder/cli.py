"""Commands ``record``, ``play`` and ``foxglove`` (docs/recording.md).

Each: its settings (:mod:`slamlens.services.recorder.settings`) from ``--config FILE`` with the
flags
over it, a bus from the common flags, the service until SIGINT/SIGTERM (or the end of the
recording), a final line saying what it did, and a clean close of the Zenoh session.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
from pathlib import Path

from slamlens.common.cli import command_bus, keys_from, setup_logging, stop_event
from slamlens.common.config import settings_from_args
from slamlens.common.errors import ConfigError
from slamlens.services.recorder.settings import FoxgloveSettings, PlaySettings, RecordSettings

log = logging.getLogger("slamlens")


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, command)
    return {"record": _run_record, "play": _run_play,
            "foxglove": _run_foxglove}[command](args)


def _run_record(args: argparse.Namespace) -> int:
    from slamlens.services.recorder.record import Recorder

    settings = settings_from_args(RecordSettings, args)
    if settings.layout:
        _write_layout(settings.layout, settings.robot[0], settings.camera)
    if settings.nice and hasattr(os, "nice"):
        os.nice(settings.nice)  # a background consumer: the live services go first
    stop = stop_event(grace_s=None)  # the file is finished however long that takes
    bus = command_bus(args)
    try:
        recorder = Recorder(bus, settings=settings, prefix=keys_from(args).prefix)
        log.info("recording %s into %s", ", ".join(recorder.expressions), recorder.path)
        print(f"record ready: {recorder.path}", flush=True)
        recorder.run(stop)
        print(f"record stopped: {json.dumps(recorder.summary())}", flush=True)
    finally:
        bus.close()
    return 0


def _write_layout(path: str, robot: str, cameras: tuple[str, ...]) -> None:
    """The Foxglove layout of these channels, as a file."""
    from slamlens.services.recorder.foxglove_layout import layout

    try:
        Path(path).write_text(json.dumps(layout(robot, cameras), indent=2,
                                         ensure_ascii=False) + "\n", encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot write the layout {path}: {exc}") from None
    print(f"Foxglove layout written: {path}", flush=True)


def _parse_address(address: str) -> tuple[str, int]:
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(f"--control {address!r}: expected HOST:PORT, e.g. 127.0.0.1:8090")
    return host.strip("[]"), int(port)


def _run_play(args: argparse.Namespace) -> int:
    from slamlens.services.recorder.play import Player
    from slamlens.services.recorder.reading import Recording

    settings = settings_from_args(PlaySettings, args)
    recording = Recording(settings.path)  # a bad file is one line before any bus
    stop = stop_event()
    bus = command_bus(args)
    control = None
    player = None
    try:
        player = Player(bus, settings=settings, keys=keys_from(args), recording=recording)
        player.check_estimators(stop)
        if settings.control:
            from slamlens.services.recorder.control import ControlServer

            host, port = _parse_address(settings.control)
            control = ControlServer(player, host=host, port=port)
            print(f"play control {control.start()}", flush=True)
        rec = player.recording
        span = "" if rec.end_ns is None or rec.start_ns is None else \
            f", {(rec.end_ns - rec.start_ns) / 1e9:.1f} s"
        log.info("playing %s (%s keys%s) at %s", rec.path, len(player.topics), span,
                 f"{settings.rate:g}× the recorded timing" if settings.rate else "full speed")
        print(f"play ready: {len(player.topics)} keys", flush=True)
        wall = player.run(stop)
        applied = ""
        if settings.inputs_only and settings.rate == 0 and not stop.is_set():
            applied = (", all applied by the estimator" if player.drain(stop)
                       else ", NOT all applied: the estimator applied nothing for 10 s")
        verb = "done" if player.finished else "stopped"
        print(f"play {verb}: {json.dumps(player.summary())} in {wall:.2f} s{applied}",
              flush=True)
    finally:
        if control is not None:
            control.stop()
        if player is not None:
            player.close()
        bus.close()
    return 0


def _run_foxglove(args: argparse.Namespace) -> int:
    from slamlens.services.recorder.live import FoxgloveLive

    settings = settings_from_args(FoxgloveSettings, args)
    if settings.layout:
        _write_layout(settings.layout, settings.robot, settings.camera)
    stop = stop_event()
    bus = command_bus(args)
    live = None
    try:
        live = FoxgloveLive(bus, settings=settings, keys=keys_from(args))
        live.late_join()
        print(f"foxglove ready {live.url}", flush=True)
        live.run(stop)
        print(f"foxglove stopped: {json.dumps(live.summary())}", flush=True)
    finally:
        if live is not None:
            live.close()
        bus.close()
    return 0
