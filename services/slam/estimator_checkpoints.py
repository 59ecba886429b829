"""The estimator service's checkpoints (docs/delivery.md): resuming from one at start,
writing one whenever one is due and a last one at exit.

A resume puts the map back into the :class:`~slamlens.services.slam.estimator.Estimator`,
each input source's position into the
:class:`~slamlens.services.slam.input_order.InputOrder` and the running input counts a
state carries (``inputs.NAME``) into its stats; the epoch, seq and stamps to continue from
are the checkpointed state's. Files are read and written by
:mod:`slamlens.services.slam.checkpoint` (written on its own thread).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping

from slamlens.common.messages import SlamState
from slamlens.common.state_header import INPUT_COUNTS
from slamlens.common.state_outlet import StateOutlet
from slamlens.services.slam import checkpoint as ckpt
from slamlens.services.slam.estimator import Estimator
from slamlens.services.slam.input_order import InputOrder, OrderStats
from slamlens.services.slam.settings import EstimatorSettings

log = logging.getLogger("slamlens.estimator")

#: the settings a checkpoint records (a resume with others says so)
NOISE = ("sigma_v", "sigma_w", "sigma_range", "sigma_bearing")


class Checkpoints:
    """Checkpoints of one estimator in ``settings.checkpoint`` (a directory)."""

    def __init__(self, settings: EstimatorSettings, estimator: Estimator,
                 order: InputOrder) -> None:
        self.directory = settings.checkpoint
        self.settings = settings
        self.estimator = estimator
        self.order = order
        #: writes the checkpoints on a thread of its own (once a resume was tried)
        #: writes the checkpoints on a thread of its own (once a resume was tried)
        self.writer: ckpt.CheckpointWriter | None = None
        self._last = time.monotonic()

    def resume(self, *, epoch: int) -> SlamState | None:
        """The checkpointed state, with the estimator and the input order put back where
        it stood; None (a new map, ``epoch``) when the directory holds none yet. After
        it, checkpoints are written (:meth:`maybe_write`)."""
        robot = self.settings.robot
        cp = ckpt.load(self.directory, robot)
        if cp is None:
            log.info("no checkpoint in %s yet: a new map, epoch %d", self.directory, epoch)
            self.writer = ckpt.CheckpointWriter(self.directory)
            return None
        state = SlamState.from_bytes(cp.state)
        if cp.noise != self._noise():
            log.warning("the checkpoint was made with %s, now %s: the map continues with the "
                        "new settings", cp.noise, self._noise())
        self.estimator.restore(state, next_anonymous_id=cp.next_anonymous_id,
                               linearisation=cp.linearisation)
        self.order.resume(cp.positions)
        restore_counts(self.order.stats, state.diagnostics or {})
        log.info("resumed epoch %d at seq %d (input stamp %.3f, %d landmarks) from %s",
                 state.epoch, state.seq, state.input_stamp, state.n,
                 ckpt.checkpoint_path(self.directory, robot))
        self.writer = ckpt.CheckpointWriter(self.directory)
        return state

    def maybe_write(self, outlet: StateOutlet) -> None:
        """A checkpoint if one is due — after the states it covers were put."""
        if self.writer is not None and \
                time.monotonic() - self._last >= self.settings.checkpoint_interval_s:
            outlet.flush()
            self._last = time.monotonic()
            self.writer.submit(self._checkpoint(outlet))

    def close(self, outlet: StateOutlet) -> None:
        """Write a last checkpoint and stop the writer."""
        if self.writer is not None:
            self.writer.close(final=self._checkpoint(outlet))

    def _noise(self) -> dict[str, float]:
        return {k: float(getattr(self.settings, k)) for k in NOISE}

    def _checkpoint(self, outlet: StateOutlet) -> ckpt.Checkpoint:
        return ckpt.Checkpoint(
            robot=self.settings.robot, state=outlet.latest_bytes(),
            positions=self.order.positions(),
            next_anonymous_id=self.estimator.next_anonymous_id, noise=self._noise(),
            linearisation=self.estimator.linearisation_points())


def restore_counts(stats: OrderStats, diagnostics: Mapping[str, float]) -> None:
    """The input counts a checkpointed state carried (``inputs.*``), so they keep running."""
    for name in INPUT_COUNTS:
        value = diagnostics.get(f"inputs.{name}")
        if value is not None:
            setattr(stats, name, int(value))
