"""The web viewer: an aiohttp app around a viewer's :class:`ViewerApi`, on its own thread.

Endpoints (every ``client`` is a browser tab's random id; without one, the default settings):

* ``GET /`` the page; ``GET /static/…`` its script and style (no build step, no CDN);
* ``GET /ws?client=ID`` the live view over a websocket: a JSON header then the JPEG, one
  frame per ``next`` the page sends back (flow control: a slow tab gets fewer frames,
  never a growing backlog);
* ``GET /stream.mjpg?client=ID`` the same as ``multipart/x-mixed-replace`` MJPEG (for
  ``<img>``, VLC, ffmpeg); every part carries ``X-State-Seq`` and ``X-State-Stamp``;
* ``GET /snapshot.png[?client=ID][&download=1]`` the current picture as PNG (docs/cli.md);
* ``GET/POST /api/settings?client=ID``, ``GET /api/status``, ``GET /api/features``,
  ``GET /api/health``, ``GET /api/series[?pairs=1-2,3-4]``,
  ``POST /api/record/start|stop?client=ID``, ``GET /recordings/NAME``,
  ``POST /api/reregister[?robot=R]`` (asks the camera(s) to register the robot again);
* ``GET /ar``, ``/ar/ws``, ``/api/ar/settings`` the AR page: a browser's own camera with the
  overlay (:mod:`~slamlens.services.visualiser.ar_web`).

With ``ssl_context`` it serves HTTPS (a phone's browser opens its camera only for a secure
page; docs/viewer.md, "AR on a phone").

User input never causes a 500: bad values answer 400 with ``{"error": "..."}``, a body
over ``MAX_BODY_BYTES`` 413, a view or recording beyond the viewer's limits 503; each
refusal is one log line. Before any of it, :class:`~slamlens.services.visualiser.web_access.
AccessGuard` checks Host, Origin and the access token (403 / 401).
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
import ssl
import threading
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from aiohttp import web

from slamlens.common.drops import DropCounter
from slamlens.common.errors import ConfigError, SlamlensError
from slamlens.services.visualiser.api import ViewerApi
from slamlens.services.visualiser.ar import ArHub
from slamlens.services.visualiser.ar_web import ArRoutes
from slamlens.services.visualiser.camera_sources import SourceWatch
from slamlens.services.visualiser.clients import TooManyViews
from slamlens.services.visualiser.recording import NAME_PATTERN, RecordingRefused, encode_png
from slamlens.services.visualiser.service import ViewerService
from slamlens.services.visualiser.settings import ViewSettings
from slamlens.services.visualiser.web_access import AccessGuard, QuietServerLog
from slamlens.services.visualiser.web_streams import Streams

log = logging.getLogger("slamlens.viewer.web")

STATIC_DIR = Path(__file__).resolve().parent / "static"
CLIENT_PATTERN = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
SNAPSHOT_WAIT_S = 3.0  # how long a snapshot waits for a picture of the newest inputs
NO_STORE = {"Cache-Control": "no-store"}
MAX_BODY_BYTES = 64 * 1024  # a settings change is a few hundred bytes
UNAVAILABLE = (TooManyViews, RecordingRefused)  # answered 503: the viewer is at a limit

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


class BadRequest(SlamlensError):
    """User input the viewer cannot use (answered with HTTP 400 and the reason)."""


def parse_http(address: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:PORT`` for IPv6) → (host, port); ConfigError if malformed."""
    host, sep, port = address.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(f"--http {address!r}: expected HOST:PORT, e.g. 127.0.0.1:8080")
    return host.strip("[]"), int(port)


def parse_pairs(text: str) -> list[tuple[int, int]]:
    """``"1-2,3-4"`` → [(1, 2), (3, 4)] (BadRequest naming the bad item)."""
    pairs = []
    for item in (t.strip() for t in text.split(",")):
        if not item:
            continue
        a, sep, b = item.partition("-")
        if not sep or not a.strip().isdigit() or not b.strip().isdigit():
            raise BadRequest(f"pairs: {item!r} is not of the form ID-ID (e.g. 3-7)")
        pairs.append((int(a), int(b)))
    if len(pairs) > 32:
        raise BadRequest(f"pairs: at most 32 pairs, got {len(pairs)}")
    return pairs


def _json(data: Any, status: int = 200) -> web.Response:
    return web.json_response(data, status=status, headers=NO_STORE,
                             dumps=lambda d: json.dumps(d, allow_nan=False))


def _errors(refusals: DropCounter) -> Callable[..., Awaitable[web.StreamResponse]]:
    """The middleware that turns refused requests into JSON errors, one log line each."""

    @web.middleware
    async def errors(request: web.Request, handler: Handler) -> web.StreamResponse:
        try:
            return await handler(request)
        except SlamlensError as exc:  # BadRequest, ConfigError (a bad setting), limits …
            status = 503 if isinstance(exc, UNAVAILABLE) else 400
            kind, reason = ("limit" if status == 503 else "request"), str(exc)
        except web.HTTPException as exc:
            if exc.status < 400:
                raise
            status, kind, reason = exc.status, "request", exc.reason
        refusals.drop(f"web {kind}", f"{status} {request.method} {request.path} from "
                      f"{request.remote}: {reason}")
        return _json({"error": reason}, status=status)

    return errors


class WebServer:
    """Serves a :class:`ViewerService` (through its :class:`ViewerApi`) over HTTP on a
    background thread. With a ``token`` every request must carry it; Host and Origin are
    always checked (:class:`~slamlens.services.visualiser.web_access.AccessGuard`)."""

    def __init__(self, service: ViewerService, *, host: str = "127.0.0.1",
                 port: int = 8080, token: str | None = None,
                 allowed_hosts: tuple[str, ...] = (),
                 allowed_origins: tuple[str, ...] = (), ar: ArHub | None = None,
                 ssl_context: ssl.SSLContext | None = None,
                 sources: SourceWatch | None = None) -> None:
        self.api: ViewerApi = service.api
        self.host = host
        self.port = port
        self.ar = ar
        self.ssl_context = ssl_context
        self.sources = sources
        self.refusals = DropCounter(log)  #: refused requests, by kind ("web host", …)
        self.guard = AccessGuard(token=token, bound_host=host, allowed_hosts=allowed_hosts,
                                 allowed_origins=allowed_origins, refusals=self.refusals,
                                 https=ssl_context is not None)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._runner: web.AppRunner | None = None
        self._thread: threading.Thread | None = None
        self._frames = asyncio.Event()  # replaced by a fresh one on each new picture
        self._closing = False

    # -- life cycle ---------------------------------------------------------------
    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        scheme = "https" if self.ssl_context is not None else "http"
        return f"{scheme}://{host}:{self.port}"

    @property
    def url_with_token(self) -> str:
        """The URL to open in a browser (with ``?token=`` when the viewer has one)."""
        token = self.guard.token
        return self.url + (f"/?token={token}" if token else "")

    def start(self) -> str:
        """Bind and serve; returns the URL (``port=0`` picks a free port)."""
        ready = threading.Event()
        errors: list[BaseException] = []

        def run() -> None:
            loop = asyncio.new_event_loop()
            self._loop = loop
            asyncio.set_event_loop(loop)
            try:
                loop.run_until_complete(self._serve())
            except BaseException as exc:  # reported to start()'s caller
                errors.append(exc)
                if self._runner is not None:
                    loop.run_until_complete(self._runner.cleanup())
                loop.close()
                ready.set()
                return
            ready.set()
            loop.run_forever()
            loop.run_until_complete(self._shutdown())
            loop.close()

        self._thread = threading.Thread(target=run, name="viewer-web", daemon=True)
        self._thread.start()
        ready.wait()
        if errors:
            exc = errors[0]
            raise ConfigError(f"cannot serve the viewer on {self.host}:{self.port}: {exc}")
        self.api.add_listener(self._on_frames_threadsafe)
        return self.url

    async def _serve(self) -> None:
        self._frames = asyncio.Event()
        app = self.make_app()
        # streams end on their own at shutdown (they watch _closing): wait 2 s at most
        self._runner = web.AppRunner(app, access_log=None, shutdown_timeout=2.0,
                                     logger=QuietServerLog(log, self.refusals))
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.host, self.port, ssl_context=self.ssl_context)
        await site.start()
        server = getattr(site, "_server", None)
        if server is not None and server.sockets:
            self.port = server.sockets[0].getsockname()[1]
        self.guard.port = self.port

    async def _shutdown(self) -> None:
        self._closing = True
        self._frames.set()
        if self._runner is not None:
            await self._runner.cleanup()

    def stop(self) -> None:
        loop, thread = self._loop, self._thread
        if loop is None or thread is None or not thread.is_alive():
            return
        self._closing = True
        loop.call_soon_threadsafe(self._frames.set)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout=10.0)

    def _on_frames_threadsafe(self) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._on_frames)
            except RuntimeError:  # the loop closed meanwhile
                pass

    def _on_frames(self) -> None:
        event, self._frames = self._frames, asyncio.Event()
        event.set()

    async def _next_frames(self, timeout: float) -> None:
        """Wait until the service produced new pictures (or ``timeout``)."""
        try:
            await asyncio.wait_for(self._frames.wait(), timeout)
        except TimeoutError:
            pass

    # -- the app ------------------------------------------------------------------
    def make_app(self) -> web.Application:
        app = web.Application(middlewares=[self.guard.middleware, _errors(self.refusals)],
                              client_max_size=MAX_BODY_BYTES)
        r = app.router
        r.add_get("/", self.index)
        r.add_static("/static", STATIC_DIR)
        streams = Streams(self.api, refusals=self.refusals, client=self._client,
                          next_frames=self._next_frames, closing=lambda: self._closing)
        r.add_get("/ws", streams.websocket)
        r.add_get("/stream.mjpg", streams.mjpeg)
        r.add_get("/snapshot.png", self.snapshot)
        r.add_get("/api/settings", self.get_settings)
        r.add_post("/api/settings", self.post_settings)
        r.add_get("/api/status", self.status)
        r.add_get("/api/features", self.features)
        r.add_get("/api/health", self.health)
        r.add_get("/api/series", self.series)
        r.add_post("/api/reregister", self.reregister)
        r.add_post("/api/record/start", self.record_start)
        r.add_post("/api/record/stop", self.record_stop)
        r.add_get("/recordings/{name}", self.recording)
        if self.ar is not None:
            ArRoutes(self.ar, refusals=self.refusals, client=self._client,
                     closing=lambda: self._closing).add_to(r)
        return app

    # -- helpers --------------------------------------------------------------------
    @staticmethod
    def _client(request: web.Request, *, required: bool = False) -> str | None:
        client = request.query.get("client")
        if client is None or client == "":
            if required:
                raise BadRequest("the query parameter 'client' is required (a tab's id)")
            return None
        if not CLIENT_PATTERN.match(client):
            raise BadRequest("client: expected 1-64 letters, digits, '-' or '_'")
        return client

    def _settings(self, request: web.Request) -> ViewSettings:
        return self.api.settings_for(self._client(request))

    # -- pages and pictures -----------------------------------------------------------
    async def index(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC_DIR / "index.html", headers=NO_STORE)

    async def snapshot(self, request: web.Request) -> web.StreamResponse:
        settings = self._settings(request)
        self.api.touch(settings)
        loop = asyncio.get_running_loop()
        deadline = loop.time() + SNAPSHOT_WAIT_S
        while not self.api.fresh(settings) and loop.time() < deadline:
            await self._next_frames(max(0.0, min(0.5, deadline - loop.time())))
            self.api.touch(settings)
        rendered = self.api.latest(settings)
        if rendered is None:
            return _json({"error": "no picture yet: the viewer is still starting"}, status=503)
        png = await loop.run_in_executor(None, encode_png, rendered.image)
        name = f"slamlens-{self.api.robot}-{rendered.seq or 0}.png"
        disposition = "attachment" if request.query.get("download") else "inline"
        return web.Response(body=png, content_type="image/png", headers={
            **NO_STORE, "X-State-Seq": "" if rendered.seq is None else str(rendered.seq),
            "Content-Disposition": f'{disposition}; filename="{name}"'})

    # -- JSON API -------------------------------------------------------------------
    async def get_settings(self, request: web.Request) -> web.StreamResponse:
        client = self._client(request)
        return _json({"client": client, "settings": self.api.settings_for(client).to_dict(),
                      "defaults": self.api.default_settings.to_dict()})

    async def post_settings(self, request: web.Request) -> web.StreamResponse:
        client = self._client(request, required=True)
        assert client is not None
        if request.can_read_body:
            try:  # the body's size is bounded by the app (client_max_size: 413 beyond)
                changes = await request.json()
            except (ValueError, UnicodeDecodeError):  # JSONDecodeError is a ValueError
                raise BadRequest("the body must be a JSON object of settings") from None
            except RecursionError:  # nested deeper than the JSON parser will go
                raise BadRequest("the body must be a JSON object of settings (not nested "
                                 "this deep)") from None
        else:
            changes = {k: v for k, v in request.query.items()
                       if k not in ("client", "token")}
        if not isinstance(changes, dict):
            raise BadRequest("the body must be a JSON object of settings")
        if changes.get("reset"):
            changes = {k: v for k, v in self.api.default_settings.to_dict().items()}
        for key, value in changes.items():
            if isinstance(value, list) and all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
                changes[key] = ",".join(str(v) for v in value)  # colours
            elif value is not None and not isinstance(value, (str, int, float, bool)):
                raise BadRequest(f"setting {str(key)[:40]!r}: expected a string, number, "
                                 "boolean or a list of numbers")
        settings = self.api.update_settings(client, changes)
        return _json({"client": client, "settings": settings.to_dict()})

    async def status(self, request: web.Request) -> web.StreamResponse:
        ar = None if self.ar is None else self.ar.status()
        sources = {} if self.sources is None else self.sources.notes()
        return _json({**self.api.status(), "refused": dict(self.refusals.counts), "ar": ar,
                      "sources": sources})

    async def features(self, request: web.Request) -> web.StreamResponse:
        return _json(self.api.features(self._settings(request)))

    async def health(self, request: web.Request) -> web.StreamResponse:
        return _json(self.api.health(request.query.get("robot")))

    async def series(self, request: web.Request) -> web.StreamResponse:
        pairs = parse_pairs(request.query.get("pairs", ""))
        settings = self._settings(request)
        loop = asyncio.get_running_loop()
        data = await loop.run_in_executor(None, self.api.series, settings, pairs,
                                          request.query.get("robot"))
        return _json(data)

    async def reregister(self, request: web.Request) -> web.StreamResponse:
        """Ask the camera(s) to register a robot again (a query to the registration
        service: docs/protocol.md); answers what the service(s) said."""
        robot = request.query.get("robot")
        data = await asyncio.get_running_loop().run_in_executor(
            None, self.api.reregister, robot)
        return _json(data)

    async def record_start(self, request: web.Request) -> web.StreamResponse:
        client = self._client(request, required=True)
        assert client is not None
        info = await asyncio.get_running_loop().run_in_executor(
            None, self.api.record_start, client)
        return _json({**info, "url": f"/recordings/{info['file']}"})

    async def record_stop(self, request: web.Request) -> web.StreamResponse:
        client = self._client(request, required=True)
        assert client is not None
        info = await asyncio.get_running_loop().run_in_executor(
            None, self.api.record_stop, client)
        if info is None:
            return _json({"error": f"client {client} is not recording"}, status=404)
        return _json({**info, "url": f"/recordings/{info['file']}"})

    async def recording(self, request: web.Request) -> web.StreamResponse:
        name = request.match_info["name"]
        if not NAME_PATTERN.match(name):
            raise BadRequest("recording: not a recording file name")
        path = self.api.recording_path(name)
        if not path.is_file():
            return _json({"error": f"no recording named {name}"}, status=404)
        return web.FileResponse(path, headers={
            "Content-Disposition": f'attachment; filename="{name}"'})
