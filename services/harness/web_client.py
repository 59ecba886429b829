"""Real HTTP and websocket clients for the viewer's web tests (urllib, aiohttp).

Also runnable as a program inside a network namespace:
``python -m slamlens.services.harness.web_client``
reads a JSON list of requests on stdin and prints a JSON list of answers, so a test can
probe a viewer bound to an address only that namespace reaches.
"""

from __future__ import annotations

import asyncio
import json
import sys
import urllib.error
import urllib.request
from typing import Any

import aiohttp

# every kind of route of the viewer: the page, its files, the JSON API (GET and POST),
# pictures, recordings, and a route that does not exist: (method, path, JSON body)
ROUTES: list[tuple[str, str, dict | None]] = [
    ("GET", "/", None), ("GET", "/static/app.js", None), ("GET", "/api/status", None),
    ("GET", "/api/settings?client=tab1", None), ("POST", "/api/settings?client=tab1",
                                                  {"mode": "inter"}),
    ("GET", "/api/features", None), ("GET", "/api/health", None), ("GET", "/api/series", None),
    ("GET", "/snapshot.png", None), ("GET", "/stream.mjpg?client=tab1", None),
    ("POST", "/api/record/start?client=tab1", {}), ("POST", "/api/record/stop?client=tab1", {}),
    ("GET", "/recordings/slamlens-x.mp4", None), ("GET", "/no/such/route", None),
]


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, *args: Any, **kwargs: Any) -> None:
        return None  # a 303 is an answer the tests look at


_OPENER = urllib.request.build_opener(_NoRedirect)


def http(url: str, *, method: str = "GET", headers: dict[str, str] | None = None,
         body: bytes | None = None, timeout: float = 10.0) -> tuple[int, dict[str, str], bytes]:
    """(status, headers, body) of one request; redirects are not followed."""
    request = urllib.request.Request(url, data=body, method=method, headers={
        "Content-Type": "application/json", **(headers or {})})
    try:
        with _OPENER.open(request, timeout=timeout) as response:
            return response.status, dict(response.headers), response.read()
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers), exc.read()


def post_json(url: str, data: Any, **kwargs: Any) -> tuple[int, dict[str, str], bytes]:
    return http(url, method="POST", body=json.dumps(data).encode(), **kwargs)


async def _ws(url: str, headers: dict[str, str], timeout: float) -> dict[str, Any]:
    async with aiohttp.ClientSession() as session:
        try:
            async with session.ws_connect(url, headers=headers, timeout=aiohttp.ClientWSTimeout(
                    ws_receive=timeout), max_msg_size=0) as ws:
                first = await ws.receive(timeout=timeout)
                frame = json.loads(first.data) if first.type == aiohttp.WSMsgType.TEXT else None
                return {"status": 101, "frame": frame}
        except aiohttp.WSServerHandshakeError as exc:
            return {"status": exc.status, "frame": None}


def websocket(url: str, *, headers: dict[str, str] | None = None,
              timeout: float = 10.0) -> dict[str, Any]:
    """Open a websocket (``ws://…``) and read its first message: {"status": 101, "frame":
    its JSON header} if the upgrade was accepted, else {"status": the HTTP status}."""
    return asyncio.run(_ws(url, headers or {}, timeout))


def main() -> int:
    answers = []
    for r in json.load(sys.stdin):
        if r.get("websocket"):
            answers.append(websocket(r["url"], headers=r.get("headers")))
            continue
        body = r.get("body")
        try:
            status, headers, data = http(r["url"], method=r.get("method", "GET"),
                                         headers=r.get("headers"),
                                         body=None if body is None else body.encode())
        except OSError as exc:  # nothing listens there (from where this runs)
            answers.append({"status": 0, "headers": {}, "body": str(exc)})
            continue
        answers.append({"status": status, "headers": headers,
                        "body": data[:2000].decode("utf-8", "replace")})
    json.dump(answers, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
