"""Who may use the web viewer: Host and Origin checks, the access token, quiet refusals.

Every request, the websocket upgrade included, passes :class:`AccessGuard` first:

1. **Host** must name this viewer: the address the connection came in on (or the bound
   host as given, or ``localhost`` on a loopback connection) with the bound port, or a
   name of ``allowed_hosts``. A foreign name is a DNS-rebinding page: 403.
2. **Origin**, when the browser sends one (it always does for a websocket and a
   cross-site fetch), must be the page's own origin (``http://`` + that Host) or one of
   ``allowed_origins``; anything else (``null`` included) is another site driving the
   viewer (cross-site request forgery, websocket hijacking): 403.
3. **Token**, when the viewer has one: ``?token=`` (which also sets a cookie, so the
   page's own requests and its websocket carry it), the cookie, or
   ``Authorization: Bearer``. Without it: 401, on every route.

Each refusal is one log line with the reason (the first few of a kind, then one in a
hundred: :class:`~slamlens.common.drops.DropCounter`) and is counted; none is a traceback. The
same goes for requests aiohttp's parser refuses (an oversized request line or header):
:class:`QuietServerLog` makes its tracebacks one line.
"""

from __future__ import annotations

import hmac
import logging
import os
import secrets
import ssl
import stat
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError

from slamlens.common.drops import DropCounter
from slamlens.common.errors import ConfigError
from slamlens.common.hosts import is_loopback, split_host

log = logging.getLogger("slamlens.viewer.web")

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
NO_STORE = {"Cache-Control": "no-store"}
PAGES = ("/", "/ar")  #: opened from a URL with the token: redirected without it


# -- addresses: split_host and is_loopback are slamlens.common.hosts's -------------


# -- the token ------------------------------------------------------------------------
def new_token() -> str:
    """A fresh random token (32 URL-safe characters, 192 bits)."""
    return secrets.token_urlsafe(24)


def read_token(path: str | Path) -> str:
    """The token in ``path`` (its first line); ConfigError naming the file if unusable."""
    path = Path(path).expanduser()
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"--token-file {path}: no such file (write a token into it, e.g. "
                          "`python -c 'import secrets; print(secrets.token_urlsafe(24))'`)"
                          ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"--token-file {path}: cannot read it: {exc}") from None
    token = text.strip().splitlines()[0].strip() if text.strip() else ""
    if len(token) < 16 or not token.isprintable() or any(c.isspace() for c in token):
        raise ConfigError(f"--token-file {path}: expected a token of at least 16 printable "
                          "characters without spaces on its first line")
    if os.name == "posix" and path.stat().st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        log.warning("--token-file %s can be read by other users (chmod 600 it)", path)
    return token


# -- HTTPS --------------------------------------------------------------------------
def tls_context(cert: str | Path, key: str | Path) -> ssl.SSLContext:
    """A server TLS context from a PEM certificate (its chain after it, if any) and key;
    ConfigError naming the file that is missing or wrong."""
    for what, path in (("--tls-cert", cert), ("--tls-key", key)):
        if not Path(path).is_file():
            raise ConfigError(f"{what} {path}: no such file")
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        context.load_cert_chain(str(cert), str(key))
    except (ssl.SSLError, ValueError) as exc:
        raise ConfigError(f"--tls-cert {cert} / --tls-key {key}: not a PEM certificate "
                          f"and its key ({exc})") from None
    return context


# -- the guard ------------------------------------------------------------------------
class AccessGuard:
    """Checks Host, Origin and the token of every request (see the module docstring)."""

    COOKIE = "slamlens_token"  # + "_PORT": cookies are per host, not per port

    def __init__(self, *, token: str | None, bound_host: str,
                 allowed_hosts: tuple[str, ...] = (), allowed_origins: tuple[str, ...] = (),
                 refusals: DropCounter, https: bool = False) -> None:
        self.token = token
        self.https = https  #: served over TLS: the cookie is Secure, Host's default port 443
        self.port = 0  #: the bound port, set once the server is bound
        self.refusals = refusals
        self._bound_host = bound_host.lower().strip("[]")
        self._hosts: set[tuple[str, int | None]] = set()
        for entry in allowed_hosts:
            parsed = split_host(entry)
            if parsed is None:
                raise ConfigError(f"allowed host {entry!r}: expected NAME or NAME:PORT")
            self._hosts.add(parsed)
        self._origins = {o.lower().rstrip("/") for o in allowed_origins}

    @property
    def cookie_name(self) -> str:
        return f"{self.COOKIE}_{self.port}"

    def _refuse(self, request: web.Request, status: int, kind: str,
                reason: str) -> web.Response:
        self.refusals.drop(f"web {kind}", f"{status} {request.method} {request.path} from "
                           f"{request.remote}: {reason}")
        return web.json_response({"error": reason}, status=status, headers=NO_STORE)

    # -- the checks ---------------------------------------------------------------
    def host_problem(self, request: web.Request) -> str:
        """Why the request's Host does not name this viewer, or ""."""
        raw = request.headers.get("Host")
        if raw is None:
            return "no Host header"
        parsed = split_host(raw)
        if parsed is None:
            return f"Host {raw[:80]!r} is not HOST[:PORT]"
        host, port = parsed
        if (host, port) in self._hosts or (host, None) in self._hosts:
            return ""
        if (port or (443 if self.https else 80)) == self.port:
            own = {self._bound_host}
            sockname = request.transport.get_extra_info("sockname") if request.transport \
                else None
            if sockname:
                local = str(sockname[0]).split("%")[0].lower()
                own.add(local)
                if is_loopback(local):
                    own.add("localhost")
            if host in own:
                return ""
        return (f"Host {raw[:80]!r} is not this viewer's address (bound to "
                f"{self._bound_host}:{self.port}; more names: --allow-host)")

    def origin_problem(self, request: web.Request) -> str:
        """Why the request's Origin is another site's, or "" (also when it sends none)."""
        origin = request.headers.get("Origin")
        if origin is None:
            return ""
        value = origin.strip().lower().rstrip("/")
        if value in self._origins:
            return ""
        scheme, sep, rest = value.partition("://")
        own = split_host(request.headers.get("Host", ""))
        if sep and scheme in ("http", "https") and own is not None and split_host(rest) == own:
            return ""  # the page's own origin
        return (f"Origin {origin[:80]!r} is not this viewer's page (more origins: "
                "--allow-origin)")

    def token_given(self, request: web.Request) -> str | None:
        """How the request proves the token ("query", "cookie", "header"), or None."""
        assert self.token is not None
        header = request.headers.get("Authorization", "")
        for how, value in (("query", request.query.get("token")),
                           ("cookie", request.cookies.get(self.cookie_name)),
                           ("header", header[7:] if header[:7].lower() == "bearer " else None)):
            if value and hmac.compare_digest(value.encode(), self.token.encode()):
                return how
        return None

    # -- the middleware -----------------------------------------------------------
    @web.middleware
    async def middleware(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        problem = self.host_problem(request)
        if problem:
            return self._refuse(request, 403, "host", problem)
        problem = self.origin_problem(request)
        if problem:
            return self._refuse(request, 403, "origin", problem)
        if self.token is None:
            return await handler(request)
        how = self.token_given(request)
        if how is None:
            why = "a wrong token" if ("token" in request.query or "Authorization"
                                      in request.headers) else "no token"
            return self._refuse(request, 401, "token", f"{why}: open the URL the viewer "
                                "printed at start (…/?token=…), or send Authorization: "
                                "Bearer TOKEN")
        if how == "query" and request.method == "GET" and request.path in PAGES:
            # a page: keep the token in a cookie and out of the address bar
            rest = {k: v for k, v in request.query.items() if k != "token"}
            response: web.StreamResponse = web.Response(status=303, headers={
                **NO_STORE,
                "Location": request.path + (f"?{urlencode(rest)}" if rest else "")})
        else:
            response = await handler(request)
        if how == "query" and not response.prepared:
            response.set_cookie(self.cookie_name, self.token, httponly=True,
                                samesite="Strict", path="/", secure=self.https)
        return response


class QuietServerLog(logging.LoggerAdapter):  # type: ignore[type-arg]
    """aiohttp's server logger for the viewer: a request its HTTP parser refuses (an
    oversized request line or header, a malformed request) is one counted line; other
    errors keep their traceback (they are bugs)."""

    def __init__(self, logger: logging.Logger, refusals: DropCounter) -> None:
        super().__init__(logger, {})
        self.refusals = refusals

    def exception(self, msg: object, *args: object, exc_info: Any = True,
                  **kwargs: Any) -> None:
        exc = exc_info if isinstance(exc_info, BaseException) else sys.exc_info()[1]
        if isinstance(exc, HttpProcessingError):
            remote = args[0] if args else "?"
            detail = " ".join(str(exc.message).split())
            self.refusals.drop("web http", f"{exc.code} for a request from {remote} the HTTP "
                               f"parser refused: {detail[:120]}"
                               f"{'…' if len(detail) > 120 else ''}")
            return
        self.logger.error(msg, *args, exc_info=exc_info, **kwargs)
