"""Who may use the web viewer: Host, Origin and the access token.

A real viewer service on loopback Zenoh and its real aiohttp server; real HTTP (urllib)
and websocket (aiohttp) clients send the headers a hostile page would make a browser
send: a foreign ``Host`` (DNS rebinding: attacker.example resolving to 127.0.0.1), a
foreign ``Origin`` (cross-site request forgery, cross-site websocket hijacking).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from slamlens.common.keys import Keys
from slamlens.services.harness.web_client import ROUTES, http, post_json, websocket
from slamlens.services.visualiser.service import ViewerService
from slamlens.services.visualiser.settings import ViewerConfig
from slamlens.services.visualiser.web import WebServer

KEYS = Keys()
ROBOT = "robot1"
TOKEN = "lab-token-0123456789abcdef"
WEB_LOG = "slamlens.viewer.web"

def request(url: str, method: str, path: str, data: dict | None,
            headers: dict[str, str]) -> tuple[int, dict[str, str], bytes]:
    if method == "POST":
        return post_json(url + path, data, headers=headers)
    return http(url + path, headers=headers)


def ws_url(url: str, path: str = "/ws?client=tab1") -> str:
    return url.replace("http://", "ws://") + path


@pytest.fixture
def start_viewer(make_client, tmp_path: Path) -> Iterator[Callable[..., tuple[WebServer, str]]]:
    started: list[tuple[ViewerService, WebServer]] = []

    def start(*, token: str | None = None, allowed_hosts: tuple[str, ...] = (),
              allowed_origins: tuple[str, ...] = ()) -> tuple[WebServer, str]:
        service = ViewerService(make_client(), keys=KEYS, config=ViewerConfig(
            robot=ROBOT, recordings_dir=str(tmp_path / "recordings"), late_join_timeout_s=0))
        service.start()
        web = WebServer(service, host="127.0.0.1", port=0, token=token,
                        allowed_hosts=allowed_hosts, allowed_origins=allowed_origins)
        url = web.start()
        started.append((service, web))
        return web, url

    yield start
    for service, web in started:
        web.stop()
        service.stop()


def refusal_lines(caplog: pytest.LogCaptureFixture, kind: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.name == WEB_LOG and f"bad web {kind} " in
            r.getMessage()]


def settings_mode(url: str, client: str = "tab1") -> str:
    status, _, body = http(f"{url}/api/settings?client={client}")
    assert status == 200, body
    return json.loads(body)["settings"]["mode"]


def test_a_foreign_host_is_refused_on_every_route_and_the_websocket(
        start_viewer, caplog: pytest.LogCaptureFixture) -> None:
    """DNS rebinding: a page of attacker.example, whose name now resolves to 127.0.0.1,
    reaches the viewer with Host: attacker.example:PORT."""
    caplog.set_level(logging.WARNING, logger=WEB_LOG)
    web, url = start_viewer()
    port = web.port
    foreign = [f"attacker.example:{port}", "attacker.example", f"127.0.0.1:{port + 1}",
               f"localhost.attacker.example:{port}", f"[::1]:{port}"]
    refused = 0
    for host in foreign:
        for method, path, data in ROUTES:
            status, headers, body = request(url, method, path, data, {"Host": host})
            assert status == 403, (host, method, path, body)
            assert headers["Content-Type"].startswith("application/json")
            assert "Host" in json.loads(body)["error"]
            refused += 1
        assert websocket(ws_url(url), headers={"Host": host})["status"] == 403, host
        refused += 1
    # the POSTs changed nothing and started nothing
    assert settings_mode(url) == "all"
    status = json.loads(http(url + "/api/status")[2])
    assert status["recording"] == [] and status["refused"] == {"web host": refused}
    # one line per refusal, with the reason and no traceback (the first few of a kind,
    # then one in a hundred: slamlens.common.drops.DropCounter)
    lines = refusal_lines(caplog, "host")
    assert len(lines) == 5
    assert all("attacker.example" in r.getMessage() and r.exc_info is None for r in lines)
    assert not [r for r in caplog.records if r.exc_info]

    # the names that do mean this viewer
    for host in (f"127.0.0.1:{port}", f"localhost:{port}", f"LOCALHOST:{port}"):
        assert http(url + "/api/status", headers={"Host": host})[0] == 200, host
        answer = websocket(ws_url(url), headers={"Host": host})
        assert answer["status"] == 101 and answer["frame"]["width"] == 1280, host


def test_allowed_hosts_name_the_viewer_too(start_viewer) -> None:
    web, url = start_viewer(allowed_hosts=("viewer.lab", "proxy.lab:9000"))
    for host in ("viewer.lab", f"viewer.lab:{web.port}", "viewer.lab:1234", "proxy.lab:9000"):
        assert http(url + "/api/status", headers={"Host": host})[0] == 200, host
    for host in ("proxy.lab", f"proxy.lab:{web.port}", "other.lab"):
        assert http(url + "/api/status", headers={"Host": host})[0] == 403, host


def test_a_foreign_origin_is_refused_on_post_and_the_websocket_upgrade(
        start_viewer, caplog: pytest.LogCaptureFixture) -> None:
    """Cross-site request forgery and websocket hijacking: the browser sends the right
    Host (the user's own viewer) and the attacking page's Origin."""
    caplog.set_level(logging.WARNING, logger=WEB_LOG)
    web, url = start_viewer(allowed_origins=("https://dashboard.lab",))
    own = f"http://127.0.0.1:{web.port}"
    foreign = ["http://attacker.example", "null", f"http://127.0.0.1:{web.port + 1}",
               f"http://localhost:{web.port}", "https://dashboard.lab:8443"]
    for origin in foreign:
        status, _, body = post_json(url + "/api/settings?client=tab1", {"mode": "inter"},
                                    headers={"Origin": origin})
        assert status == 403 and "Origin" in json.loads(body)["error"], (origin, body)
        status, _, _ = post_json(url + "/api/record/start?client=tab1", {},
                                 headers={"Origin": origin})
        assert status == 403, origin
        assert websocket(ws_url(url), headers={"Origin": origin})["status"] == 403, origin
    assert settings_mode(url) == "all"
    status = json.loads(http(url + "/api/status")[2])
    assert status["recording"] == [] and status["refused"] == {"web origin": 3 * len(foreign)}
    lines = refusal_lines(caplog, "origin")
    assert len(lines) == 5 and all("Origin" in r.getMessage() and r.exc_info is None
                                   for r in lines)

    # the page's own origin, and an allowed one, may
    status, _, body = post_json(url + "/api/settings?client=tab1", {"mode": "inter"},
                                headers={"Origin": own})
    assert status == 200 and json.loads(body)["settings"]["mode"] == "inter"
    assert websocket(ws_url(url), headers={"Origin": own})["status"] == 101
    assert websocket(ws_url(url), headers={"Origin": "https://dashboard.lab"})["status"] == 101
    status, _, _ = post_json(url + "/api/settings?client=tab2", {"mode": "inter"},
                             headers={"Origin": "https://dashboard.lab"})
    assert status == 200


def test_with_a_token_nothing_is_served_without_it(start_viewer,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger=WEB_LOG)
    web, url = start_viewer(token=TOKEN)
    for credentials in ({}, {"Authorization": "Bearer wrong-token-0123456789"},
                        {"Cookie": f"slamlens_token_{web.port}=wrong-token-0123456"}):
        for method, path, data in ROUTES:
            status, _, body = request(url, method, path, data, credentials)
            assert status == 401, (credentials, method, path, body)
            assert "token" in json.loads(body)["error"]
        assert websocket(ws_url(url), headers=credentials)["status"] == 401
    for method, path, data in ROUTES:  # a wrong token in the query
        sep = "&" if "?" in path else "?"
        assert request(url, method, f"{path}{sep}token=wrong", data, {})[0] == 401, path
    assert websocket(ws_url(url, "/ws?client=tab1&token=wrong"))["status"] == 401
    lines = refusal_lines(caplog, "token")
    assert len(lines) == 5 and all(r.exc_info is None for r in lines)

    # the URL printed at start: the page sets a cookie and drops the token from the URL
    status, headers, _ = http(f"{url}/?token={TOKEN}")
    assert status == 303 and headers["Location"] == "/"
    cookie = headers["Set-Cookie"]
    assert cookie.startswith(f"slamlens_token_{web.port}={TOKEN};")
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
    jar = {"Cookie": f"slamlens_token_{web.port}={TOKEN}"}
    status, _, body = http(url + "/", headers=jar)
    assert status == 200 and b"slamlens viewer" in body
    assert http(url + "/static/app.js", headers=jar)[0] == 200
    status, _, body = post_json(url + "/api/settings?client=tab1", {"mode": "inter"},
                                headers=jar)
    assert status == 200 and json.loads(body)["settings"]["mode"] == "inter"
    answer = websocket(ws_url(url), headers=jar)  # the page's websocket carries the cookie
    assert answer["status"] == 101 and answer["frame"]["width"] == 1280
    # scripts: a bearer header, or the token in the query of any route
    bearer = {"Authorization": f"Bearer {TOKEN}"}
    assert http(url + "/api/status", headers=bearer)[0] == 200
    assert http(f"{url}/api/health?token={TOKEN}")[0] == 200
    assert websocket(ws_url(url, f"/ws?client=tab1&token={TOKEN}"))["status"] == 101
    # Host and Origin are still checked for a client with the token
    assert http(url + "/api/status", headers={**bearer, "Host": "attacker.example"})[0] == 403
