"""``slamlens foxglove``: the live scene over Foxglove's WebSocket protocol (foxglove-sdk).

The same channels a recording holds (:mod:`.channels`), served by the SDK's WebSocket
server (loopback by default) to the Foxglove app: open a connection to
``ws://127.0.0.1:8765``. Inputs are the robot's ``state``, ``health`` and ``truth`` and, per
``--camera``, its ``frame`` and ``registration``, all taken latest-wins (a live picture
skips, never lags). A client that subscribes gets the newest message of the channel at
once (the scene of the current state), not only from the next state on. The scene
settings (mode, cluster threshold and count, glyph, k, scale) are also Foxglove
parameters: change them in the app's Parameters panel and the scene is drawn again.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from typing import Any

import foxglove
from foxglove.websocket import Capability

from slamlens.common.bus import Bus, Channel
from slamlens.common.drops import DropCounter
from slamlens.common.errors import ConfigError, MessageError, SlamlensError
from slamlens.common.keys import Keys
from slamlens.common.messages import SlamState
from slamlens.services.recorder.channels import FoxgloveMessage, FoxgloveTranslator
from slamlens.services.recorder.settings import FoxgloveSettings, SceneSettings

log = logging.getLogger("slamlens.foxglove")

#: scene settings offered as Foxglove parameters
PARAMETERS = ("mode", "cluster_threshold_m", "cluster_count", "glyph", "sigma_k", "scale")


class _Listener(foxglove.websocket.ServerListener):
    """SDK callbacks (on the SDK's threads): only hand work to the service's worker."""

    def __init__(self, live: FoxgloveLive) -> None:
        self.live = live

    def on_subscribe(self, client: Any, channel: Any) -> None:
        self.live.requests.put(("subscribe", channel.topic))

    def on_get_parameters(self, client: Any, param_names: list[str],
                          request_id: str | None = None) -> list[Any]:
        return self.live.parameters(param_names)

    def on_set_parameters(self, client: Any, parameters: list[Any],
                          request_id: str | None = None) -> list[Any]:
        return self.live.set_parameters(parameters)


class FoxgloveLive:
    """The bus's robot and cameras as Foxglove channels on a WebSocket server."""

    def __init__(self, bus: Bus, *, settings: FoxgloveSettings, keys: Keys) -> None:
        self.bus = bus
        self.settings = settings
        self.keys = keys
        self.translator = FoxgloveTranslator(settings.scene_settings(), prefix=keys.prefix)
        self.context = foxglove.Context()
        self._channels: dict[str, foxglove.Channel] = {}
        self._last: dict[str, FoxgloveMessage] = {}
        self._state: tuple[SlamState, int] | None = None
        self._lock = threading.Lock()
        self.requests: queue.Queue[tuple[str, Any]] = queue.Queue()
        self.bad = DropCounter(log)
        self.sent = 0
        self.subscriptions = 0
        try:
            self.server = foxglove.start_server(
                name=f"slamlens {settings.robot}", host=settings.host, port=settings.port,
                capabilities=[Capability.Parameters], server_listener=_Listener(self),
                context=self.context)
        except Exception as exc:  # the SDK raises its own error types
            raise ConfigError(f"cannot serve Foxglove on {settings.host}:{settings.port}: "
                              f"{exc}") from None
        host = f"[{settings.host}]" if ":" in settings.host else settings.host
        port = self.server.port
        self.url = f"ws://{host}:{port() if callable(port) else port}"
        inputs = [keys.state(settings.robot), keys.health(settings.robot),
                  keys.truth(settings.robot)]
        for camera in settings.camera:
            inputs += [keys.frame(camera), keys.registration(camera, settings.robot)]
        self._inputs: list[tuple[str, Channel]] = [
            (k, bus.channel(k, latest_wins=True)) for k in inputs]

    # -- parameters (SDK threads) -----------------------------------------------------
    def parameters(self, names: list[str] | None = None) -> list[Any]:
        s = self.translator.settings
        wanted = names or list(PARAMETERS)
        return [foxglove.Parameter(n, value=getattr(s, n)) for n in PARAMETERS if n in wanted]

    def set_parameters(self, parameters: list[Any]) -> list[Any]:
        changes = {p.name: p.get_value() for p in parameters if p.name in PARAMETERS}
        if changes:
            try:
                new = dataclasses.replace(self.translator.settings, **changes)
                from slamlens.common.config import settings_from_mapping

                new = settings_from_mapping(SceneSettings, dataclasses.asdict(new),
                                            source="Foxglove parameters")
            except (SlamlensError, TypeError) as exc:
                log.warning("Foxglove parameters refused: %s", exc)
            else:
                self.requests.put(("settings", new))
        return self.parameters()

    # -- output -----------------------------------------------------------------------
    def _log(self, msg: FoxgloveMessage) -> None:
        channel = self._channels.get(msg.topic)
        if channel is None:
            schema = foxglove.Schema(name=msg.schema.name, encoding=msg.schema.encoding,
                                     data=msg.schema.data)
            channel = self._channels[msg.topic] = foxglove.Channel(
                msg.topic, schema=schema, message_encoding=msg.message_encoding,
                context=self.context)
        channel.log(msg.data, log_time=msg.log_time_ns)
        self._last[msg.topic] = msg
        self.sent += 1

    def _feed(self, key: str, payload: bytes) -> None:
        now = time.time_ns()
        try:
            out = self.translator.feed(key, payload, now)
        except MessageError as exc:
            self.bad.drop(self.keys.leaf_of(key), str(exc))
            return
        if key == self.keys.state(self.settings.robot):  # (kept for a redraw)
            try:
                self._state = (SlamState.from_bytes(payload, check_symmetry=False), now)
            except MessageError:
                pass
        for msg in out:
            self._log(msg)

    def _redraw(self) -> None:
        if self._state is not None:
            state, _ = self._state
            for msg in self.translator.redraw(state.robot, state, time.time_ns()):
                self._log(msg)

    def _handle(self, request: tuple[str, Any]) -> None:
        kind, value = request
        if kind == "settings":
            self.translator.set_settings(value)
            log.info("scene settings: %s", {n: getattr(value, n) for n in PARAMETERS})
            self._redraw()
            self.server.publish_parameter_values(self.parameters())
        elif kind == "subscribe":
            self.subscriptions += 1
            last = self._last.get(value)
            if last is not None:  # the newest at once, stamped now
                self._log(dataclasses.replace(last, log_time_ns=time.time_ns()))

    def late_join(self) -> None:
        """The newest state and registrations, by ``get`` (as a viewer joining late)."""
        if self.settings.late_join_timeout_s <= 0:
            return
        for key, _ in self._inputs:
            if key.endswith("/frame"):
                continue
            for reply in self.bus.get(key, timeout=self.settings.late_join_timeout_s):
                self._feed(reply.key, reply.payload)

    def run(self, stop: threading.Event) -> None:
        """Draw the newest of each input as it comes (older ones are skipped, not queued)."""
        newest: dict[str, Any] = {}

        def pump(channel: Channel) -> None:
            while not stop.is_set():
                sample = channel.recv(timeout=0.2)
                if sample is not None:
                    with self._lock:
                        newest[sample.key] = sample
                    self.requests.put(("wake", None))

        threads = [threading.Thread(target=pump, args=(ch,), daemon=True)
                   for _, ch in self._inputs]
        for t in threads:
            t.start()
        while not stop.is_set():
            try:
                request = self.requests.get(timeout=0.2)
            except queue.Empty:
                continue
            with self._lock:
                samples, newest = list(newest.values()), {}
            for sample in samples:
                self._feed(sample.key, sample.payload)
            if request[0] != "wake":
                self._handle(request)
        for t in threads:
            t.join(timeout=0.5)

    def summary(self) -> dict[str, Any]:
        return {"url": self.url, "sent": self.sent, "scenes": self.translator.scenes,
                "subscriptions": self.subscriptions, "bad": self.bad.total}

    def close(self) -> None:
        for _, ch in self._inputs:
            ch.close()
        try:
            self.server.stop()
        except Exception:
            pass
