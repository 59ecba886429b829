"""The covariance each published state carries, materialised from L once per state.

Its buffers are recycled once no message or view of an earlier state holds them any more
(:class:`~slamlens.common.arrays.RecycledBuffers`; backed by a bytearray, so shared memory
takes one with one copy: common/bus.py). After only predicts P_mm is as it was
(docs/estimator.md): then the last state's matrix, if nothing holds it, has its robot rows
and columns patched in place, O(N), or else is copied with them patched. No I/O.
"""

from __future__ import annotations

import numpy as np

from slamlens.common.arrays import RecycledBuffers
from slamlens.services.slam import ekf


class PublishedCovariance:
    """Makes each state's symmetric covariance from L, reusing the last when it can."""

    def __init__(self) -> None:
        #: the covariance of the last state made
        self._last: np.ndarray | None = None
        #: whether anything but the robot rows/columns may have changed since the last
        #: state (then it is materialised again whole)
        self.dirty = True
        self.buffers = RecycledBuffers(keep=4)
        #: predict states whose matrix was the last state's, patched in place
        self.predicts_in_place = 0

    def materialise(self, L: np.ndarray, N: int) -> np.ndarray:
        """The N×N covariance of L's lower triangle, read-only (the message keeps it
        without another copy)."""
        previous, self._last = self._last, None
        if not self.dirty and previous is not None and previous.shape == (N, N):
            # only predicts since the last state. If nothing holds its matrix any more (its
            # message went out: a large state is sent from shared memory and a get answers
            # with that), its robot rows and columns are patched in place
            reclaimed = self.buffers.reclaim(previous, holders=1)
            if reclaimed is not None:
                cov = ekf.robot_rows_into(L, N, reclaimed)
                self.predicts_in_place += 1
            else:
                cov = self.buffers.array((N, N), "<f8")
                ekf.symmetric_after_predict(L, N, previous, out=cov)
        else:
            cov = self.buffers.array((N, N), "<f8")
            ekf.symmetric(L, N, out=cov)
        del previous
        cov.flags.writeable = False
        self._last, self.dirty = cov, False
        return cov
