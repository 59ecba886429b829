"""Zenoh's own log, read back into the router's log: refused messages and links made visible.

Zenoh (Rust) writes its log to the process's standard output, and reports an access-control
refusal only at trace level, next to a line for every message it allows. The router
therefore points file descriptor 1 at a pipe (Python's own ``sys.stdout`` keeps the real
standard output) and a reader thread turns Zenoh's lines into the router's log:

* a message the access control refused: one warning naming the identity, the message kind
  and the key the first time, then a count every :data:`SUMMARY_EVERY_S` seconds;
* a TLS connection refused (a certificate of another authority, a plain TCP client on a TLS
  port): one warning with Zenoh's reason;
* a client whose certificate names no identity the router knows;
* any other Zenoh warning or error, without its Rust source location (with ``RUST_LOG``
  set, every line Zenoh writes at the levels it names).

Zenoh writes every decision, allowed ones included, so the reader is built to cost little:
chunks holding only allowed decisions are skipped unparsed, and it reads in naps of 20 ms
rather than waking for every line (the pipe holds 1 MiB, thousands of lines; Zenoh would
wait only if more piled up within one nap). Log records go through a bounded queue to their
own thread, so a slow log never stalls the reader; what does not fit is counted.
"""

from __future__ import annotations

import fcntl
import io
import logging
import os
import re
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field

log = logging.getLogger("slamlens.router")

SUMMARY_EVERY_S = 10.0
#: Zenoh's warnings, plus its access-control decisions when access control is on
BASE_DIRECTIVES = "warn"
ACL_DIRECTIVES = "zenoh::net::routing::interceptor=trace"
_PIPE_BYTES = 1 << 20  # room for bursts of trace lines while the reader is descheduled
_QUEUE = 1000  # log records waiting for the router's log; more are counted and dropped
_CHUNK = 1 << 16  # bytes read from the pipe at a time
#: a chunk without any of these is only "authorized" decisions: skipped without parsing.
#: "unauthorized" keeps every refused decision, however far from its "Msg intercepted!"
_INTERESTING = (b"unauthorized", b"intercepted", b"CertCommonName", b"did not match",
                b"WARN", b"ERROR")
_NAP_S = 0.02  # the pipe holds _PIPE_BYTES: ~5000 lines, far more than 20 ms of routing

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
# time, level, [thread name], ThreadId(n), [spans{…}:], target: message
_LINE = re.compile(r"^\S+Z\s+(?P<level>TRACE|DEBUG|INFO|WARN|ERROR)\s+(?:\S+\s+)?"
                   r"ThreadId\((?P<thread>\d+)\)\s+(?:.*?[\s:])?"
                   r"(?P<target>zenoh\w*(?:::\w+)*):\s(?P<text>.*)$")
_DECISION = re.compile(r"(?:Using cached result: )?(?P<zid>[0-9a-f]+)(?: on (?P<subject>\S+))? is "
                       r"(?P<verdict>authorized|unauthorized) to (?P<what>.+?) on (?P<key>\S+)$")
_NAME = re.compile(r"CertCommonName\(([^)]*)\)")
_RUST_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")
_HINT = re.compile(r"\s*Hint: increase the system open file limit\.?")


@dataclass
class DenialCounts:
    """How often each (identity, message kind, key) was refused; what is yet to be said."""

    total: dict[tuple[str, str, str], int] = field(default_factory=dict)
    unreported: dict[tuple[str, str, str], int] = field(default_factory=dict)

    def add(self, what: tuple[str, str, str]) -> bool:
        """Count one refusal; True if it is the first of its kind (log it now)."""
        first = what not in self.total
        self.total[what] = self.total.get(what, 0) + 1
        if not first:
            self.unreported[what] = self.unreported.get(what, 0) + 1
        return first

    def take_unreported(self) -> dict[tuple[str, str, str], int]:
        out, self.unreported = self.unreported, {}
        return out


class ZenohLogReader:
    """Parses Zenoh's log lines (see module docstring); feed it with :meth:`line`."""

    def __init__(self, emit: logging.Logger = log, *, verbose: bool = False) -> None:
        self.verbose = verbose  # RUST_LOG asked for Zenoh's own lines: pass them on
        self.denials = DenialCounts()
        self._emit = emit
        self._last_decision: dict[str, re.Match[str] | None] = {}
        self._names: dict[str, str] = {}  # zid → certificate name (cached decisions omit it)
        self._partial = b""  # an incomplete last line, until its end arrives
        self._records: deque[tuple[int, str]] = deque()
        self._cond = threading.Condition()
        self.dropped_records = 0

    # -- parsing (the reader thread; never blocks) ---------------------------------------
    def feed(self, chunk: bytes, *, final: bool = False) -> None:
        """Take the next bytes of Zenoh's log. Most chunks hold nothing but allowed
        decisions and are skipped unparsed (every message routed writes such lines); the
        decision behind a drop is an unauthorized one, and a chunk holding one is parsed,
        so the drop finds it however many other lines came between (a thread descheduled
        between the two, a reader behind)."""
        data = self._partial + chunk
        cut = len(data) if final else data.rfind(b"\n") + 1
        complete, self._partial = data[:cut], data[cut:]
        if not complete:
            return
        if not self.verbose and not any(m in complete for m in _INTERESTING):
            return
        for raw in complete.decode("utf-8", errors="replace").splitlines():
            self.line(raw)

    def line(self, raw: str) -> None:
        text = _ANSI.sub("", raw).rstrip("\n")
        m = _LINE.match(text)
        if m is None:
            if text:
                self._record(logging.INFO, f"zenoh: {text}")
            return
        level, thread, target, body = m["level"], m["thread"], m["target"], m["text"]
        if target.endswith("access_control"):
            decision = _DECISION.search(body)
            if decision is not None:
                self._last_decision[thread] = decision
                names = _NAME.findall(decision["subject"] or "")
                if names:
                    self._names[decision["zid"]] = names[0]
            elif "did not match any configured ACL subject" in body:
                zid = body.split(" ", 1)[0]
                self._record(logging.WARNING, f"a client ({zid}) presented no identity this "
                             "router knows: everything it sends is refused")
            elif level in ("WARN", "ERROR"):
                self._record(logging.WARNING, f"zenoh: {_clean(body)}")
            return
        if body == "Msg intercepted!":
            self._refused(self._last_decision.pop(thread, None))
            return
        if level in ("TRACE", "DEBUG", "INFO"):
            if self.verbose:
                self._record(logging.INFO, f"zenoh {level.lower()} {target}: {_clean(body)}")
            return
        if target.startswith("zenoh_link_tls") and ("alert" in body or "corrupt" in body
                                                    or "certificate" in body.lower()):
            self._record(logging.WARNING, f"refused a TLS connection: {_clean(body)}")
            return
        self._record(logging.WARNING if level == "WARN" else logging.ERROR,
                     f"zenoh: {_clean(body)}")

    def _refused(self, decision: re.Match[str] | None) -> None:
        if decision is None or decision["verdict"] != "unauthorized":
            what = ("a client of no known identity", "send messages", "any key")
        else:
            name = self._names.get(decision["zid"], f"zenoh id {decision['zid']}")
            what = (name, decision["what"], decision["key"])
        with self._cond:
            first = self.denials.add(what)
        if first:
            name, kind, key = what
            self._record(logging.WARNING, f"refused: {name} may not {kind} on {key} "
                         "(dropped; repeats are counted)")

    def _record(self, level: int, message: str) -> None:
        with self._cond:
            if len(self._records) >= _QUEUE:
                self.dropped_records += 1
                return
            self._records.append((level, message))
            self._cond.notify()

    # -- logging (its own thread, so a slow log never stalls the reader) -----------------
    def emit_pending(self, timeout: float) -> None:
        with self._cond:
            self._cond.wait_for(lambda: bool(self._records), timeout)
            records, self._records = list(self._records), deque()
        for level, message in records:
            self._emit.log(level, "%s", message)

    def summarise(self) -> None:
        with self._cond:
            unreported = self.denials.take_unreported()
            totals = dict(self.denials.total)
        for (name, kind, key), n in sorted(unreported.items()):
            total = totals[(name, kind, key)]
            self._emit.warning("refused %d more: %s may not %s on %s (%d in all)",
                               n, name, kind, key, total)

    def refused_total(self) -> int:
        with self._cond:
            return sum(self.denials.total.values())


def _clean(text: str) -> str:
    return " ".join(_HINT.sub("", _RUST_LOCATION.sub("", text)).split())


class ZenohLog:
    """Route Zenoh's log through a :class:`ZenohLogReader` (call :meth:`start` before the
    first Zenoh session opens; the log can be initialised once per process)."""

    def __init__(self, *, access_control: bool) -> None:
        self.reader = ZenohLogReader(verbose="RUST_LOG" in os.environ)
        self._directives = BASE_DIRECTIVES + (f",{ACL_DIRECTIVES}" if access_control else "")
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def start(self) -> None:
        import zenoh

        sys.stdout.flush()
        read_fd, write_fd = os.pipe()
        try:
            fcntl.fcntl(write_fd, fcntl.F_SETPIPE_SZ, _PIPE_BYTES)
        except (OSError, AttributeError):  # not Linux, or above the limit: default size
            pass
        real_stdout = os.dup(1)
        os.dup2(write_fd, 1)
        os.close(write_fd)
        sys.stdout = io.TextIOWrapper(os.fdopen(real_stdout, "wb", buffering=0),
                                      line_buffering=True)
        self._threads = [
            threading.Thread(target=self._read, args=(read_fd,), name="zenoh-log", daemon=True),
            threading.Thread(target=self._log, name="zenoh-log-out", daemon=True),
        ]
        for t in self._threads:
            t.start()
        zenoh.init_log_from_env_or(self._directives)

    def _read(self, fd: int) -> None:
        while chunk := os.read(fd, _CHUNK):
            try:
                self.reader.feed(chunk)
            except Exception:  # a line we cannot parse must never stop the reader
                log.debug("unparsed zenoh log: %r", chunk[:200])
            if len(chunk) < _CHUNK:
                # drained: let lines gather in the pipe rather than wake for each one (a
                # wake-up per routed message cost the router ~20 % latency on two cores)
                time.sleep(_NAP_S)
        self.reader.feed(b"", final=True)

    def _log(self) -> None:
        last = time.monotonic()
        while not self._stop.is_set():
            self.reader.emit_pending(timeout=0.5)
            if time.monotonic() - last >= SUMMARY_EVERY_S:
                last = time.monotonic()
                self.reader.summarise()

    def stop(self) -> None:
        """Say what is still unsaid (the reader keeps running until the process exits)."""
        self._stop.set()
        self.reader.emit_pending(timeout=0.0)
        self.reader.summarise()
        if self.reader.dropped_records:
            log.warning("zenoh log: %d lines dropped (the router's log could not keep up)",
                        self.reader.dropped_records)
