"""The answer to ``get state?header`` (docs/protocol.md): a state's header without its map,
and its publisher's counts — what a driver paces on. Pure: a state and counts in, bytes out.
"""

from __future__ import annotations

from collections.abc import Mapping

import msgpack

from slamlens.common.messages import SlamState

#: what an estimator's input order counts, as the stop line, ``state?header``, ``slamlens
#: status`` and a state's ``diagnostics`` (``inputs.NAME``) name it
INPUT_COUNTS = ("duplicates", "late", "lost", "waited", "reordered", "joined_late")


def state_header(state: SlamState, counts: Mapping[str, int]) -> bytes:
    """``get state?header``'s answer (docs/protocol.md): what a driver paces on, not the
    map, and the publisher's counts now — ``dropped`` and :data:`INPUT_COUNTS`, 0 where
    ``counts`` has none (a publisher without an input order)."""
    return msgpack.packb({"schema": 1, "robot": state.robot, "seq": state.seq,
                          "stamp": state.stamp, "step": state.step, "epoch": state.epoch,
                          "input_stamp": state.input_stamp, "n": state.n,
                          "origin_stamp": state.origin_stamp,
                          **{name: int(counts.get(name, 0))
                             for name in ("dropped", *INPUT_COUNTS)}},
                         use_bin_type=True)
