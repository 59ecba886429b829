"""The first sample on a new Zenoh route, put until it is seen.

After a publisher matched (Zenoh matching status), a route may still drop samples for a
few hundred ms on a loaded machine (zenoh 1.10, client ↔ router, measured up to 0.3 s);
once one sample went through, the route is there. Tests that need their first sample
delivered put it with :func:`put_until_seen`: again only if it was not seen within
``retry_s``, so a slow consumer is not flooded with copies.
"""

from __future__ import annotations

import time
from collections.abc import Callable


def put_until_seen(put: Callable[[], object], seen: Callable[[], object], *, what: str,
                   timeout_s: float = 30.0, retry_s: float = 2.0) -> None:
    """Call ``put()`` until ``seen()`` is true; fail naming ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        put()
        again = time.monotonic() + retry_s
        while time.monotonic() < again:
            if seen():
                return
            time.sleep(0.02)
        if seen():
            return
        assert time.monotonic() < deadline, f"{what} never arrived"
