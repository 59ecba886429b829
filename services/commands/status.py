"""``slamlens status``: every live service on every host linked to the router, as a table.

Each service holds a liveliness token on its status key and answers a ``get`` there with a
:class:`~slamlens.common.messages.ServiceStatus` (the protocol is in
:mod:`slamlens.common.status`). This
command asks both — which services are alive (liveliness) and what they say (a query on
``PREFIX/status/**``) — and prints one row per service: what it runs, its identity and
host, its robot and camera, what it is doing, its main rate, what it dropped or lost, the
map epoch and its version. A service that is alive but does not answer in time is listed
as such. The table refreshes every ``--interval`` until Ctrl-C; ``--once`` prints it once
and ``--json`` prints the same rows as JSON, for scripts.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

from slamlens.common.bus import Bus
from slamlens.common.cli import command_bus, keys_from, setup_logging, stop_event
from slamlens.common.config import settings_from_args
from slamlens.common.errors import MessageError
from slamlens.common.keys import Keys
from slamlens.common.messages import ServiceStatus
from slamlens.services.commands.settings import StatusSettings

COLUMNS = ("SERVICE", "NAME", "HOST", "ROBOT", "CAMERA", "STATE", "RATE", "DROPPED", "LOST",
           "EPOCH", "VERSION", "UP")


def gather(bus: Bus, keys: Keys, *, timeout_s: float) -> list[dict[str, Any]]:
    """One row per live (or answering) service, sorted by host, service and name."""
    alive = set(bus.alive(keys.any_status(), timeout=timeout_s))
    answers: dict[str, ServiceStatus] = {}
    for sample in bus.get(keys.any_status(), timeout=timeout_s):
        try:
            answers[sample.key] = ServiceStatus.from_bytes(sample.payload)
        except MessageError:
            continue  # not a status: said by the row it belongs to ("no answer")
    rows = []
    for key in alive | set(answers):
        parsed = keys.status_of(key)
        if parsed is None:
            continue
        name, service, instance = parsed
        row: dict[str, Any] = {"key": key, "alive": key in alive, "answered": key in answers,
                               "service": service, "name": name, "instance": instance}
        status = answers.get(key)
        if status is not None:
            fields = status.to_dict()
            fields.pop("schema", None)
            row.update(fields)
        rows.append(row)
    return sorted(rows, key=lambda r: (str(r.get("host", "")), r["service"], r["name"],
                                       r["instance"]))


def _duration(seconds: float) -> str:
    seconds = int(seconds)
    if seconds < 60:
        return f"{seconds}s"
    if seconds < 3600:
        return f"{seconds // 60}m{seconds % 60:02d}s"
    return f"{seconds // 3600}h{seconds // 60 % 60:02d}m"


def _rate(rates: dict[str, float]) -> str:
    if not rates:
        return "–"
    name, value = next(iter(rates.items()))
    return f"{name} {value:.1f}/s"


def cells(row: dict[str, Any]) -> list[str]:
    """The table cells of one row (see :data:`COLUMNS`)."""
    if not row["answered"]:
        return [row["service"], row["name"], "?", "", "", "no answer", "", "", "", "", "", ""]
    epoch = row.get("epoch")
    return [row["service"], row["name"], str(row["host"]), row.get("robot") or "",
            row.get("camera") or "", str(row["state"]), _rate(row.get("rates") or {}),
            str(row.get("dropped", 0)), str(row.get("lost", 0)),
            "" if epoch is None else str(epoch), str(row["version"]),
            _duration(float(row["uptime_s"]))]


def table(rows: list[dict[str, Any]]) -> str:
    """The rows as an aligned text table (a line saying so when there are none)."""
    if not rows:
        return "no slamlens service is alive on this bus"
    grid = [list(COLUMNS)] + [cells(r) for r in rows]
    widths = [max(len(line[i]) for line in grid) for i in range(len(COLUMNS))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(line, widths, strict=True)).rstrip()
                     for line in grid)


def run(command: str, args: argparse.Namespace) -> int:
    setup_logging(args, "status")
    s = settings_from_args(StatusSettings, args)
    keys = keys_from(args)
    stop = stop_event()
    bus = command_bus(args)
    try:
        if s.json:
            print(json.dumps(gather(bus, keys, timeout_s=s.timeout_s), indent=2), flush=True)
            return 0
        tty = sys.stdout.isatty() and not s.once
        while not stop.is_set():
            started = time.monotonic()
            text = table(gather(bus, keys, timeout_s=s.timeout_s))
            if tty:
                print("\x1b[H\x1b[2J" + text, flush=True)  # home and clear: a refreshing table
            else:
                print(text + ("" if s.once else "\n"), flush=True)
            if s.once:
                break
            stop.wait(max(0.0, s.interval_s - (time.monotonic() - started)))
    finally:
        bus.close()
    return 0
