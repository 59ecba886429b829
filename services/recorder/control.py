"""The player's control page and API on loopback: pause, resume, seek, rate (aiohttp).

* ``GET /`` a small page: play/pause, a position slider (seek), the rate;
* ``GET /api/status`` position, duration, rate, paused, published (JSON);
* ``POST /api/pause``, ``POST /api/resume``, ``POST /api/seek?t=SECONDS`` (from the start
  of the recording), ``POST /api/rate?value=R``: each answers the new status; a bad value
  answers 400 with ``{"error": …}``.
"""

from __future__ import annotations

import asyncio
import json
import logging
import threading
from typing import Any

from aiohttp import web

from slamlens.common.errors import ConfigError
from slamlens.services.recorder.play import Player

log = logging.getLogger("slamlens.play")

PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>slamlens play</title>
<style>body{font:14px sans-serif;margin:2em;max-width:48em}input[type=range]{width:100%}
button{font-size:1.1em;margin-right:.5em}</style></head>
<body><h1>slamlens play</h1><p id="file"></p>
<p><button id="toggle">pause</button> rate <input id="rate" type="number" min="0"
 step="0.5" style="width:5em"> <span id="pos"></span></p>
<input id="seek" type="range" min="0" max="1" step="0.01" value="0">
<script>
const $ = (id) => document.getElementById(id);
let status = null, dragging = false;
async function call(path) {
  const r = await fetch(path, {method: path.startsWith("/api/status") ? "GET" : "POST"});
  status = await r.json(); show();
}
function show() {
  if (!status || status.error) return;
  $("file").textContent = status.file + (status.inputs_only ? " (inputs only)" : "");
  $("toggle").textContent = status.paused ? "play" : "pause";
  const d = status.duration_s;
  $("pos").textContent = status.position_s.toFixed(1) + " s"
    + (d ? " / " + d.toFixed(1) + " s" : "") + " · " + status.published + " published"
    + (status.finished ? " · finished" : "");
  if (d) { $("seek").max = d; if (!dragging) $("seek").value = status.position_s; }
  if (document.activeElement !== $("rate")) $("rate").value = status.rate;
}
$("toggle").onclick = () => call(status && status.paused ? "/api/resume" : "/api/pause");
$("seek").onpointerdown = () => { dragging = true; };
$("seek").onchange = () => { dragging = false; call("/api/seek?t=" + $("seek").value); };
$("rate").onchange = () => call("/api/rate?value=" + $("rate").value);
setInterval(() => call("/api/status"), 500); call("/api/status");
</script></body></html>
"""


def _number(request: web.Request, name: str) -> float:
    raw = request.query.get(name, "")
    try:
        value = float(raw)
    except ValueError:
        raise ConfigError(f"query {name}={raw!r}: expected a number") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise ConfigError(f"query {name}={raw!r}: expected a finite number")
    return value


class ControlServer:
    """The control page of one :class:`Player`, served on its own thread."""

    def __init__(self, player: Player, *, host: str, port: int) -> None:
        self.player = player
        self.host, self.port = host, port
        self.url = ""
        self._loop: asyncio.AbstractEventLoop | None = None
        self._runner: web.AppRunner | None = None
        self._thread = threading.Thread(target=self._serve, daemon=True, name="play control")
        self._ready = threading.Event()
        self._error: BaseException | None = None

    def _app(self) -> web.Application:
        app = web.Application()
        p = self.player

        def answer(fn: Any) -> Any:
            async def handler(request: web.Request) -> web.Response:
                try:
                    fn(request)
                except ConfigError as exc:
                    return web.json_response({"error": str(exc)}, status=400)
                return web.json_response(p.status(), dumps=json.dumps)
            return handler

        async def page(request: web.Request) -> web.Response:
            return web.Response(text=PAGE, content_type="text/html")

        app.router.add_get("/", page)
        app.router.add_get("/api/status", answer(lambda r: None))
        app.router.add_post("/api/pause", answer(lambda r: p.pause()))
        app.router.add_post("/api/resume", answer(lambda r: p.resume()))
        app.router.add_post("/api/seek", answer(lambda r: p.seek(_number(r, "t"))))
        app.router.add_post("/api/rate", answer(lambda r: p.set_rate(_number(r, "value"))))
        return app

    def _serve(self) -> None:
        loop = self._loop = asyncio.new_event_loop()
        try:
            self._runner = web.AppRunner(self._app(), access_log=None)
            loop.run_until_complete(self._runner.setup())
            site = web.TCPSite(self._runner, self.host, self.port)
            loop.run_until_complete(site.start())
            server = getattr(site, "_server", None)
            sockets = getattr(server, "sockets", None) or []
            port = sockets[0].getsockname()[1] if sockets else self.port
            host = f"[{self.host}]" if ":" in self.host else self.host
            self.url = f"http://{host}:{port}/"
        except OSError as exc:
            self._error = exc
            self._ready.set()
            return
        self._ready.set()
        loop.run_forever()
        loop.run_until_complete(self._runner.cleanup())
        loop.close()

    def start(self) -> str:
        self._thread.start()
        self._ready.wait(10.0)
        if self._error is not None:
            raise ConfigError(f"--control {self.host}:{self.port}: cannot listen "
                              f"({self._error})")
        return self.url

    def stop(self) -> None:
        if self._loop is not None and self._loop.is_running():
            self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=1.5)
