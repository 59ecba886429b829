"""``slamlens replay`` with its progress bar, as a real process."""

from __future__ import annotations

from slamlens.services.harness.procs import REPO, spawn

SMALL = REPO / "tests" / "fixtures" / "mrclam_small"


def test_replay_shows_a_bar_when_asked_and_none_in_a_log(router_endpoint) -> None:
    args = ("replay", str(SMALL), "--no-wait", "--rate", "0", "--duration", "20",
            "--connect", router_endpoint)
    shown = spawn(*args, "--progress", "on")
    out, err = shown.communicate(timeout=120)
    assert shown.returncode == 0, err
    assert "replay done" in out
    assert "s of data" in err and "× real time" in err and "20/20 s of data" in err
    quiet = spawn(*args)  # auto: stderr is a pipe here, so no bar
    out, err = quiet.communicate(timeout=120)
    assert quiet.returncode == 0 and "replay done" in out
    assert "× real time" not in err and "\r" not in err
