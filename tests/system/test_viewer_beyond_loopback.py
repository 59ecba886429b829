"""The web viewer bound beyond loopback serves nothing without its token (§7b).

Two network namespaces joined by a veth pair: the viewer runs on the "workstation" and
binds its veth address; the browser side is a real HTTP / websocket client
(services/harness/web_client.py) run in the "robot" namespace, across the link.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

from slamlens.services.harness.netns import Hosts
from slamlens.services.harness.procs import REPO, Service, spawn, stop
from slamlens.services.harness.web_client import ROUTES

ROBOT = "robot1"


def probe(ns: str, requests: list[dict]) -> list[dict]:
    """Run the requests from inside namespace ``ns``; their answers."""
    out = subprocess.run(["ip", "netns", "exec", ns, sys.executable, "-m",
                          "slamlens.services.harness.web_client"],
                         input=json.dumps(requests), capture_output=True, text=True, cwd=REPO,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout)


def every_route(base: str, headers: dict[str, str] | None = None) -> list[dict]:
    """One request per route (and the websocket) with ``headers``."""
    requests = [{"url": base + path, "method": method, "headers": headers or {},
                 "body": None if data is None else json.dumps(data)}
                for method, path, data in ROUTES]
    return requests + [{"url": base.replace("http://", "ws://") + "/ws?client=tab1",
                        "headers": headers or {}, "websocket": True}]


def start_viewer(ns: str, *args: str) -> tuple[Service, str]:
    proc = spawn("viewer", "--robot", ROBOT, "--late-join-timeout-s", "0", *args, netns=ns)
    line = proc.wait_for_line("viewer ready")
    return proc, line.split()[-1]


def test_beyond_loopback_nothing_is_served_without_the_token(two_hosts: Hosts,
                                                              tmp_path: Path) -> None:
    h = two_hosts
    procs: list[Service] = []
    try:
        # the viewer runs as a peer listening on its own loopback (no router needed)
        viewer, printed = start_viewer(h.workstation, "--listen", "tcp/127.0.0.1:7447",
                                       "--http", f"{h.workstation_ip}:8080")
        procs.append(viewer)
        m = re.fullmatch(rf"http://{re.escape(h.workstation_ip)}:8080/\?token=([\w-]+)",
                         printed)
        assert m, printed  # a token was made and printed in the URL to open
        token = m.group(1)
        assert len(token) >= 32
        base = f"http://{h.workstation_ip}:8080"

        wrong = every_route(base, {"Authorization": "Bearer not-the-token-at-all-000"})
        answers = probe(h.robot, every_route(base) + wrong + [
            {"url": base + "/api/status?token=wrong"}])
        assert [a["status"] for a in answers] == [401] * len(answers), answers
        assert all("token" in json.loads(a["body"])["error"] for a in answers
                   if "body" in a)

        answers = probe(h.robot, [
            {"url": printed},  # the printed URL: sets the cookie, drops the token
            {"url": base + "/api/status", "headers": {"Cookie": f"slamlens_token_8080={token}"}},
            {"url": base + "/api/status", "headers": {"Authorization": f"Bearer {token}"}},
            {"url": base.replace("http://", "ws://") + "/ws?client=tab1",
             "headers": {"Cookie": f"slamlens_token_8080={token}"}, "websocket": True},
        ])
        assert answers[0]["status"] == 303 and answers[0]["headers"]["Location"] == "/"
        assert answers[0]["headers"]["Set-Cookie"].startswith(f"slamlens_token_8080={token};")
        assert answers[1]["status"] == answers[2]["status"] == 200
        assert json.loads(answers[1]["body"])["robot"] == ROBOT
        assert answers[3]["status"] == 101 and answers[3]["frame"]["width"] == 1280

        # a token from a file: asked for, and kept out of the printed URL
        token_file = tmp_path / "viewer.token"
        token_file.write_text("file-token-0123456789abcdefghij\n")
        token_file.chmod(0o600)
        filed, printed = start_viewer(h.workstation, "--connect", "tcp/127.0.0.1:7447",
                                      "--http", f"{h.workstation_ip}:8081",
                                      "--token-file", str(token_file))
        procs.append(filed)
        assert printed == f"http://{h.workstation_ip}:8081"
        other = f"http://{h.workstation_ip}:8081"
        answers = probe(h.robot, every_route(other) + every_route(other, {
            "Authorization": f"Bearer {token}"}))  # the first viewer's token is not this one
        assert [a["status"] for a in answers] == [401] * len(answers), answers
        answers = probe(h.robot, [{"url": other + "/api/status", "headers": {
            "Authorization": "Bearer file-token-0123456789abcdefghij"}}])
        assert answers[0]["status"] == 200

        # the default binds loopback only: no token, and not reachable from the other host
        local, printed = start_viewer(h.workstation, "--connect", "tcp/127.0.0.1:7447",
                                      "--http", "127.0.0.1:8082")
        procs.append(local)
        assert printed == "http://127.0.0.1:8082"
        assert probe(h.workstation, [{"url": printed + "/api/status"}])[0]["status"] == 200
        assert probe(h.robot, [{"url": f"http://{h.workstation_ip}:8082/api/status"}]
                     )[0]["status"] == 0  # nothing listens there
    finally:
        outputs = [stop(p) for p in procs]
    assert [p.returncode for p in procs] == [0] * len(procs)
    for _, err in outputs:
        assert "Traceback" not in err, err[-2000:]
