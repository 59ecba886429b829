"""The viewer's live pictures over HTTP: the websocket the page uses and the MJPEG stream.

* ``GET /ws?client=ID``: per frame a JSON header then the JPEG, one frame per ``next`` the
  page sends back (flow control: a slow tab gets fewer frames, never a growing backlog);
* ``GET /stream.mjpg?client=ID``: the same as ``multipart/x-mixed-replace`` MJPEG (for
  ``<img>``, VLC, ffmpeg); every part carries ``X-State-Seq`` and ``X-State-Stamp``.

Each stream watches its client's view while it lasts (:class:`_Watch`: the view is kept
and rendered) and follows the client to new settings.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

from aiohttp import WSMsgType, web

from slamlens.common.drops import DropCounter
from slamlens.services.visualiser.api import ViewerApi
from slamlens.services.visualiser.clients import TooManyViews
from slamlens.services.visualiser.settings import ViewSettings

BOUNDARY = "slamlensframe"
MAX_WS_MESSAGE = 1024  # the page only ever sends "next"


class _Watch:
    """The view one stream shows, watched while the stream lasts (so it is kept), and
    followed when the client changes its settings."""

    def __init__(self, api: ViewerApi, client: str | None) -> None:
        self._api, self._client = api, client
        self.settings: ViewSettings | None = None

    def current(self) -> ViewSettings:
        """The client's settings now (TooManyViews if the first has no room)."""
        settings = self._api.settings_for(self._client)
        if settings == self.settings:
            self._api.touch(settings)
            return settings
        try:
            self._api.watch(settings, self._client)
        except TooManyViews:
            if self.settings is None:
                raise
            return self.settings  # no room for the new settings: keep showing the old
        if self.settings is not None:
            self._api.unwatch(self.settings, self._client)
        self.settings = settings
        return settings

    def close(self) -> None:
        if self.settings is not None:
            self._api.unwatch(self.settings, self._client)
            self.settings = None



class Streams:
    """The stream handlers of a viewer's web server."""

    def __init__(self, api: ViewerApi, *, refusals: DropCounter,
                 client: Callable[[web.Request], str | None],
                 next_frames: Callable[[float], Awaitable[None]],
                 closing: Callable[[], bool]) -> None:
        self._api = api
        self.refusals = refusals
        self._client = client
        self._next_frames = next_frames
        self._closing = closing

    async def mjpeg(self, request: web.Request) -> web.StreamResponse:
        watch = _Watch(self._api, self._client(request))
        watch.current()  # no room for its view: 503 before the stream starts
        response = web.StreamResponse(headers={
            "Content-Type": f"multipart/x-mixed-replace; boundary={BOUNDARY}",
            "Cache-Control": "no-cache, no-store, must-revalidate", "Pragma": "no-cache"})
        last = None
        try:
            await response.prepare(request)
            while not self._closing():
                transport = request.transport
                if transport is None or transport.is_closing():
                    break  # the client went away while no picture was written
                rendered = self._api.latest(watch.current())
                if rendered is None or rendered is last:
                    await self._next_frames(1.0)
                    continue
                last = rendered
                head = (f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\n"
                        f"Content-Length: {len(rendered.jpeg)}\r\n"
                        f"X-State-Seq: {'' if rendered.seq is None else rendered.seq}\r\n"
                        f"X-State-Stamp: {'' if rendered.stamp is None else rendered.stamp!r}"
                        f"\r\nX-Frame-Version: {rendered.version}\r\n\r\n")
                await response.write(head.encode() + rendered.jpeg + b"\r\n")
        except (ConnectionResetError, asyncio.CancelledError):
            pass  # the viewer went away
        finally:
            watch.close()
        return response

    async def websocket(self, request: web.Request) -> web.StreamResponse:
        watch = _Watch(self._api, self._client(request))
        watch.current()  # no room for its view: 503 instead of the upgrade
        ws = web.WebSocketResponse(heartbeat=20.0, max_msg_size=MAX_WS_MESSAGE,
                                   compress=False)
        try:
            await ws.prepare(request)
        except BaseException:
            watch.close()
            raise
        wanted = asyncio.Event()
        wanted.set()

        async def read() -> None:
            async for msg in ws:
                if msg.type == WSMsgType.TEXT and msg.data == "next":
                    wanted.set()
                elif msg.type == WSMsgType.ERROR:  # e.g. a message over MAX_WS_MESSAGE
                    self.refusals.drop("web websocket", f"closed the websocket of "
                                       f"{request.remote}: {ws.exception()}")
                    break

        reader = asyncio.create_task(read())
        last = None
        try:
            while not self._closing() and not ws.closed and not reader.done():
                rendered = self._api.latest(watch.current())
                if not wanted.is_set():  # the page has not drawn the previous frame yet
                    try:
                        await asyncio.wait_for(wanted.wait(), 1.0)
                    except TimeoutError:
                        pass
                    continue
                if rendered is None or rendered is last:
                    await self._next_frames(1.0)
                    continue
                last = rendered
                wanted.clear()
                height, width = rendered.image.shape[:2]
                await ws.send_json({"seq": rendered.seq, "stamp": rendered.stamp,
                                    "version": rendered.version, "width": width,
                                    "height": height})
                await ws.send_bytes(rendered.jpeg)
        except (ConnectionResetError, asyncio.CancelledError):
            pass
        finally:
            watch.close()
            reader.cancel()
            await ws.close()
        return ws
