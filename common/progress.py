"""Progress bars for long runs on a terminal (``replay``, ``sim``, ``tune``), with tqdm.

``progress = "auto"`` (every command's default) shows a bar only when stderr is a terminal,
so logs, pipes and tests stay clean; ``"on"`` forces it (to stderr), ``"off"`` never.
Two kinds:

* :func:`time_bar` counts *data* seconds (a replay's dataset time, a simulation's robot
  time) and shows the speed as "× real time" with the time left;
* :func:`count_bar` counts items (events a tuner pushes through its estimator runs).

tqdm is imported only when a bar is shown, so ``--help`` stays fast. Updates are cheap
(tqdm redraws at most every 0.1 s).
"""

from __future__ import annotations

import sys
from typing import Any

MODES = ("auto", "on", "off")


class NoBar:
    """What a hidden bar is: every call does nothing."""

    def update(self, n: float = 1) -> None:
        pass

    def set_description_str(self, text: str) -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self) -> NoBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def enabled(mode: str) -> bool:
    """Whether a bar is shown for ``mode`` (auto: stderr is a terminal)."""
    if mode == "on":
        return True
    if mode == "off":
        return False
    return bool(getattr(sys.stderr, "isatty", lambda: False)())


def _tqdm_class() -> Any:
    from tqdm import tqdm

    class _TimeBar(tqdm):  # type: ignore[misc]
        @property
        def format_dict(self) -> dict[str, Any]:
            d = super().format_dict
            rate = d.get("rate")
            if rate is None and d.get("elapsed"):
                rate = d["n"] / d["elapsed"]
            d["speed"] = f"{rate:.1f}× real time" if rate else "… × real time"
            return dict(d)

    return _TimeBar


def time_bar(total_s: float, *, desc: str, mode: str = "auto") -> Any:
    """A bar over ``total_s`` seconds of data; ``update(ds)`` with the data time advanced."""
    if not enabled(mode) or not total_s > 0:
        return NoBar()
    return _tqdm_class()(
        total=float(total_s), desc=desc, unit="s", file=sys.stderr, leave=True,
        bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s of data "
                   "[{elapsed}<{remaining}, {speed}]")


def count_bar(total: int, *, desc: str, unit: str = "event", mode: str = "auto") -> Any:
    """A bar over ``total`` items (rate per second and time left)."""
    if not enabled(mode) or total <= 0:
        return NoBar()
    from tqdm import tqdm

    return tqdm(total=int(total), desc=desc, unit=unit, unit_scale=True, file=sys.stderr,
                leave=True)
