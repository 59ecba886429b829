"""Command ``rerun`` (docs/rerun.md): its settings from ``--config FILE`` with the flags
over it, the Rerun SDK (an optional extra: a clear line if it is missing), a bus from the
common flags, the sink until SIGINT/SIGTERM, a final line saying what it did, a clean close
of the recording and of the Zenoh session."""

from __future__ import annotations

import argparse
import json
import logging
from typing import TYPE_CHECKING

from slamlens.common.cli import command_bus, keys_from, setup_logging, stop_event
from slamlens.common.config import settings_from_args
from slamlens.common.errors import ConfigError
from slamlens.common.status import Provider, Report, announce
from slamlens.services.rerun.settings import RerunSettings

if TYPE_CHECKING:
    from slamlens.services.rerun.sink import RerunSink

log = logging.getLogger("slamlens")

INSTALL_HINT = ("slamlens rerun needs the Rerun SDK, which the base install leaves out: "
                "pip install 'slamlens[rerun]' (or pip install rerun-sdk)")


def _status(sink: RerunSink) -> Provider:
    """What ``slamlens status`` shows of the sink: states drawn, the newest seq, drops."""
    def report() -> Report:
        t = sink.translator
        return Report(state="drawing" if t.drawn else "waiting for states",
                      counts={"states": t.drawn, "seq": t.seq, "images": t.images,
                              "cameras": t.cameras, "logged": sink.logged,
                              "superseded": sink.superseded},
                      dropped=sink.bad.total, rated=("states",))
    return report


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, command)
    settings = settings_from_args(RerunSettings, args)
    try:
        import rerun  # noqa: F401
    except ImportError:
        raise ConfigError(INSTALL_HINT) from None
    from slamlens.services.rerun.sink import RerunSink

    stop = stop_event(grace_s=None) if settings.save else stop_event()  # a file is finished
    bus = command_bus(args)
    sink = None
    try:
        sink = RerunSink(bus, settings=settings, keys=keys_from(args))
        announce(bus, args, "rerun", _status(sink), robot=settings.robot,
                 camera=",".join(settings.camera))
        sink.late_join()
        print(f"rerun ready: {sink.where}", flush=True)
        sink.run(stop)
        sink.finish()
        print(f"rerun stopped: {json.dumps(sink.summary())}", flush=True)
    finally:
        if sink is not None:
            sink.close()  # (a viewer that never answered: Rerun waits up to 5 s for it)
        bus.close()
    return 0
