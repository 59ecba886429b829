"""The viewer over HTTPS with a certificate from ``slamlens certs … --host``, as a phone
opens its AR page: a real viewer process, clients that trust only the authority's ca.pem."""

from __future__ import annotations

import datetime as dt
import http.client
import ssl
import subprocess
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from slamlens.common.certs import load_cert, san_hosts
from slamlens.services.harness.procs import REPO, slamlens_cmd, spawn, stop

TOKEN = "https-token-0123456789abcdef"


def test_https_page_with_the_authoritys_certificate(tmp_path: Path, router_endpoint) -> None:
    pki = tmp_path / "pki"
    made = subprocess.run(slamlens_cmd("certs", str(pki), "--name", "viewer-lab", "--host",
                                       "127.0.0.1"), capture_output=True, text=True,
                          timeout=60, cwd=REPO)
    assert made.returncode == 0, made.stderr
    cert = load_cert(pki / "viewer-lab.pem")
    assert {"127.0.0.1", "localhost"} <= set(san_hosts(cert))
    days = (cert.not_valid_after_utc - cert.not_valid_before_utc) / dt.timedelta(days=1)
    assert days <= 825.01  # iOS trusts no longer TLS server certificate
    token_file = tmp_path / "token"
    token_file.write_text(TOKEN + "\n")
    token_file.chmod(0o600)
    viewer = spawn("viewer", "--robot", "r1", "--http", "127.0.0.1:0", "--tls-cert",
                   str(pki / "viewer-lab.pem"), "--tls-key", str(pki / "viewer-lab.key"),
                   "--token-file", str(token_file), "--connect", router_endpoint)
    try:
        url = viewer.wait_for_line("viewer ready", timeout=60).split()[-1]
        assert url.startswith("https://127.0.0.1:")
        trusted = ssl.create_default_context(cafile=str(pki / "ca.pem"))
        request = urllib.request.Request(f"{url}/ar", headers={
            "Authorization": f"Bearer {TOKEN}"})
        with urllib.request.urlopen(request, context=trusted, timeout=10) as r:
            assert r.status == 200 and b"slamlens AR" in r.read()
        # a client that does not trust the authority refuses the viewer
        with pytest.raises(urllib.error.URLError, match="CERTIFICATE_VERIFY_FAILED"):
            urllib.request.urlopen(f"{url}/ar", context=ssl.create_default_context(),
                                   timeout=10)
        # the token from the URL goes into a Secure cookie, the address bar loses it
        host, port = url.removeprefix("https://").split(":")
        conn = http.client.HTTPSConnection(host, int(port), context=trusted, timeout=10)
        conn.request("GET", f"/ar?token={TOKEN}&camera=phone-1")
        answer = conn.getresponse()
        assert answer.status == 303 and answer.getheader("Location") == "/ar?camera=phone-1"
        cookie = answer.getheader("Set-Cookie") or ""
        assert "Secure" in cookie and "HttpOnly" in cookie
        conn.close()
        # without the token: 401, even over HTTPS
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(f"{url}/ar", context=trusted, timeout=10)
        assert refused.value.code == 401
        refused.value.close()
    finally:
        stop(viewer)
