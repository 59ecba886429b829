"""`slamlens demo` as a user runs it: every service as a process, a link, a picture."""

from __future__ import annotations

import re
import subprocess
import time
import urllib.request

import cv2
import numpy as np

from slamlens.services.harness.procs import REPO, slamlens_cmd


def test_demo_runs_everything_and_serves_the_picture(tmp_path) -> None:
    proc = subprocess.Popen(
        slamlens_cmd("demo", "--faulty", "--rate", "4", "--duration", "40",
                     "--http", "127.0.0.1:0", "--listen", "tcp/127.0.0.1:0",
                     "--log-dir", str(tmp_path)),
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    url = None
    try:
        deadline = time.monotonic() + 60
        while url is None and time.monotonic() < deadline:
            line = proc.stdout.readline()
            lines.append(line)
            m = re.search(r"open (http://\S+/) in a browser", line)
            if m:
                url = m.group(1)
        assert url, "".join(lines)
        # once the robot moves, the picture is served and the monitor names the fault, in
        # the words the page and the picture's legend use (common/verdict.py)
        png = None
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            lines.append(line)
            if "| estimator fault since seq " in line and "suspects 3, 12" in line:
                with urllib.request.urlopen(url + "snapshot.png", timeout=10) as reply:
                    png = reply.read()
                break
        assert png is not None, "".join(lines[-5:])
        image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        assert image.shape == (720, 1280, 3)
        red = (image[:, :, 2] > 150) & (image[:, :, 1] < 80) & (image[:, :, 0] < 80)
        assert red.sum() > 500  # the correlation ellipsoids are drawn
        out, _ = proc.communicate(timeout=90)
        lines.append(out)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    text = "".join(lines)
    assert proc.returncode == 0, text[-2000:]
    final = [ln for ln in text.splitlines() if ln.startswith("final:")]
    assert final and "15 landmarks" in final[0], text[-1000:]
    for name in ("router", "estimator", "monitor", "registration", "viewer", "sim"):
        assert (tmp_path / f"{name}.log").exists(), name
    assert "registered" in (tmp_path / "registration.log").read_text()
