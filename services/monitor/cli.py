"""Command ``monitor`` (docs/monitor.md): its settings from ``--config FILE`` with the flags
over it, a bus from the common flags, the service until SIGINT/SIGTERM, the verdict in words
and a final line saying what it checked, a clean close of the Zenoh session."""

from __future__ import annotations

import argparse
import json
from typing import Any

from slamlens.common.cli import (
    command_bus,
    keys_from,
    one_blas_thread,
    setup_logging,
    stop_event,
)
from slamlens.common.config import settings_from_args
from slamlens.common.status import Report, announce
from slamlens.services.monitor.settings import MonitorSettings


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, command)
    one_blas_thread()
    from slamlens.services.monitor.service import MonitorService

    settings = settings_from_args(MonitorSettings, args)
    robot = settings.robot
    stop = stop_event()
    bus = command_bus(args)
    try:
        service = MonitorService(bus, keys=keys_from(args), robot=robot, settings=settings)

        def status() -> Report:
            summary = service.summary()
            return Report(state=str(summary["verdict"]) if service.checked else
                          "no verdict yet",
                          counts={"checked": float(service.checked),
                                  "violations": float(service.violations),
                                  "behind": float(service.behind)},
                          dropped=int(summary["dropped"]),  # type: ignore[call-overload]
                          lost=int(summary["lost"]),  # type: ignore[call-overload]
                          epoch=service.epoch)

        announce(bus, args, "monitor", status, robot=robot)
        print("monitor ready", flush=True)
        service.run(stop)
        print(f"monitor verdict: {verdict_sentence(service.summary())}", flush=True)
        print(f"monitor stopped: {json.dumps(service.summary())}", flush=True)
    finally:
        bus.close()
    return 0


def verdict_sentence(summary: dict[str, Any]) -> str:
    """The monitor's verdict in words, for its last lines (docs/monitor.md)."""
    by = summary.get("states_by_verdict", {})
    checked = int(summary.get("checked", 0))
    parts = [f"{summary.get('verdict_words')} at the end"]
    if checked:
        parts.append(f"{by.get('fault', 0)} of {checked} states under an estimator fault, "
                     f"{by.get('tuning', 0)} under inconsistent tuning or model mismatch")
        conservative = int(summary.get("states_ok_with_timid_nis", 0))
        if conservative:
            parts.append(f"{conservative} ok with a NIS window below its band standing (S "
                         "conservative: the pose NEES in its band)")
    if not summary.get("estimator_fault_seen"):
        parts.append("no estimator fault seen")
    return "; ".join(parts)
