"""The ``/ar`` page's HTTP side: the page, its websocket and its settings (aiohttp).

* ``GET /ar`` the page (``static/ar.html``, ``ar.js``): the device's rear camera, the
  overlay of the chosen robot on it;
* ``GET /ar/ws?client=ID&camera=C[&robot=R]`` the page's camera: it sends a text message
  ``{"tag": T}`` (anything JSON, echoed back) then the frame as one binary message (a
  JPEG); each frame is answered by a JSON header (``seq``, ``tag``, ``overlay``, ``note``,
  ``state_seq``, ``status``, ``server_ms``) then the picture (JPEG), in order. A refused
  frame is answered ``{"refused": reason}`` and counted; a camera refused (a name that
  is not this viewer's, taken, too many) answers 409 before the upgrade;
* ``GET/POST /api/ar/settings?client=ID`` the page's view settings (as ``/api/settings``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from aiohttp import WSMsgType, web

from slamlens.common.drops import DropCounter
from slamlens.services.visualiser.ar import ArHub, ArRefused, ArResult, ArSession

log = logging.getLogger("slamlens.viewer.web")

STATIC_DIR = Path(__file__).resolve().parent / "static"
NO_STORE = {"Cache-Control": "no-store"}
OUTBOX = 4  #: answers waiting to be sent to one page (it keeps two frames in flight)
MAX_TEXT = 1024  #: a text message is a frame's tag


def _json(data: Any, status: int = 200) -> web.Response:
    return web.json_response(data, status=status, headers=NO_STORE,
                             dumps=lambda d: json.dumps(d, allow_nan=False))


class ArRoutes:
    """The routes of the AR page, over an :class:`~slamlens.services.visualiser.ar.ArHub`."""

    def __init__(self, hub: ArHub, *, refusals: DropCounter,
                 client: Callable[[web.Request], str | None],
                 closing: Callable[[], bool]) -> None:
        self.hub = hub
        self.refusals = refusals
        self._client = client
        self._closing = closing

    def add_to(self, router: web.UrlDispatcher) -> None:
        router.add_get("/ar", self.page)
        router.add_get("/ar/ws", self.websocket)
        router.add_get("/api/ar/settings", self.get_settings)
        router.add_post("/api/ar/settings", self.post_settings)

    def _required_client(self, request: web.Request) -> str:
        client = self._client(request)
        if client is None:
            raise web.HTTPBadRequest(reason="the query parameter 'client' is required")
        return client

    async def page(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC_DIR / "ar.html", headers=NO_STORE)

    async def get_settings(self, request: web.Request) -> web.StreamResponse:
        client = self._required_client(request)
        return _json({"client": client, "settings": self.hub.settings_for(client).to_dict(),
                      "defaults": self.hub.default_settings.to_dict(),
                      "camera": self.hub.base_camera, "robots": list(self.hub.api.robot_names())})

    async def post_settings(self, request: web.Request) -> web.StreamResponse:
        client = self._required_client(request)
        try:
            changes = await request.json()
        except (ValueError, UnicodeDecodeError, RecursionError):
            raise web.HTTPBadRequest(reason="the body must be a JSON object of settings") \
                from None
        if not isinstance(changes, dict):
            raise web.HTTPBadRequest(reason="the body must be a JSON object of settings")
        for key, value in changes.items():
            if isinstance(value, list) and all(isinstance(v, int) and not isinstance(v, bool)
                                               for v in value):
                changes[key] = ",".join(str(v) for v in value)  # colours
            elif value is not None and not isinstance(value, (str, int, float, bool)):
                raise web.HTTPBadRequest(reason=f"setting {str(key)[:40]!r}: expected a "
                                         "string, number, boolean or a list of integers")
        settings = self.hub.update_settings(client, changes)  # ConfigError: 400
        return _json({"client": client, "settings": settings.to_dict()})

    async def websocket(self, request: web.Request) -> web.StreamResponse:
        client = self._required_client(request)
        loop = asyncio.get_running_loop()
        outbox: asyncio.Queue[ArResult] = asyncio.Queue(maxsize=OUTBOX)

        def put(result: ArResult) -> None:
            if outbox.full():  # the page stopped reading: its oldest answer goes
                outbox.get_nowait()
            outbox.put_nowait(result)

        def deliver(result: ArResult) -> None:  # on the session's thread
            with contextlib.suppress(RuntimeError):  # the loop closed meanwhile
                loop.call_soon_threadsafe(put, result)

        try:
            session = self.hub.open(client=client, camera=request.query.get("camera", ""),
                                    robot=request.query.get("robot") or None, deliver=deliver)
        except ArRefused as exc:
            self.refusals.drop(f"web {exc.kind}", f"409 {request.path} from {request.remote}: "
                               f"{exc}")
            return _json({"error": str(exc)}, status=409)
        ws = web.WebSocketResponse(heartbeat=20.0, compress=False,
                                   max_msg_size=self.hub.limits.max_frame_bytes + MAX_TEXT)
        sender: asyncio.Task[None] | None = None
        try:
            await ws.prepare(request)
            sender = asyncio.create_task(self._send(ws, outbox))
            await self._read(ws, session, request)
        except (ConnectionResetError, asyncio.CancelledError):
            pass
        finally:
            if sender is not None:
                sender.cancel()
            await loop.run_in_executor(None, self.hub.close, session)
            await ws.close()
        return ws

    async def _send(self, ws: web.WebSocketResponse, outbox: asyncio.Queue[ArResult]) -> None:
        while not ws.closed:
            result = await outbox.get()
            await ws.send_json(result.header)
            await ws.send_bytes(result.jpeg)

    async def _read(self, ws: web.WebSocketResponse, session: ArSession,
                    request: web.Request) -> None:
        tag: Any = None
        async for msg in ws:
            if self._closing():
                break
            if msg.type == WSMsgType.BINARY:
                try:
                    session.offer_frame(msg.data, tag)
                except ArRefused as exc:
                    self.hub.refusals.drop(exc.kind, f"camera {session.camera} from "
                                           f"{request.remote}: {exc}")
                    await ws.send_json({"refused": str(exc), "tag": tag})
                tag = None
            elif msg.type == WSMsgType.TEXT:
                try:
                    tag = json.loads(msg.data).get("tag") if len(msg.data) <= MAX_TEXT else None
                except (ValueError, AttributeError, RecursionError):
                    self.hub.refusals.drop("ar frame", f"camera {session.camera}: a text "
                                           "message that is not {\"tag\": …}")
                    tag = None
            elif msg.type == WSMsgType.ERROR:  # e.g. a message over max_msg_size
                self.refusals.drop("web websocket", f"closed the AR websocket of "
                                   f"{request.remote}: {ws.exception()}")
                break
