"""Crash recovery for the estimator (docs/delivery.md): its whole state on disk, written atomically.

A checkpoint is one msgpack file ``DIR/estimator-{robot}.ckpt`` holding the last published
``SlamState`` (pose, map, covariance, seq, epoch, input stamp) plus what the state does not
say: where each input source stood (:mod:`slamlens.services.slam.input_order`), the next id for a
landmark found by association, and the noise settings it was made with. It is written to a
temporary file, flushed to disk and renamed over the old one, so a process killed at any
moment leaves either the previous checkpoint or the new one, never half of one.

Writing happens on a thread of its own (:class:`CheckpointWriter`): the estimator hands
over bytes it already has and never waits for the disk.
"""

from __future__ import annotations

import logging
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack

from slamlens.common.errors import SlamlensError

log = logging.getLogger("slamlens.estimator")

FORMAT = 1


class CheckpointError(SlamlensError):
    """A checkpoint could not be read or written (the file and the reason are named)."""


@dataclass(frozen=True)
class Checkpoint:
    """Everything needed to continue one map exactly where it stood."""

    robot: str
    state: bytes  #: the SlamState payload, as published
    positions: dict[str, dict[str, Any]]  #: InputOrder.positions()
    next_anonymous_id: int
    noise: dict[str, float]  #: σ settings the map was built with
    #: the FEJ linearisation points (``Estimator.linearisation_points``), None for the
    #: standard filter (and then not written: such a file is what it always was)
    linearisation: dict[str, Any] | None = None

    def to_bytes(self) -> bytes:
        fields: dict[str, Any] = {"format": FORMAT, "robot": self.robot, "state": self.state,
                                  "positions": self.positions,
                                  "next_anonymous_id": self.next_anonymous_id,
                                  "noise": self.noise}
        if self.linearisation is not None:
            fields["linearisation"] = self.linearisation
        return msgpack.packb(fields, use_bin_type=True)

    @classmethod
    def from_bytes(cls, payload: bytes, *, path: Path) -> Checkpoint:
        try:
            raw = msgpack.unpackb(payload, raw=False, strict_map_key=False)
        except Exception as exc:
            raise CheckpointError(f"checkpoint {path} is unreadable ({type(exc).__name__}); "
                                  "move it away to start a new map") from None
        if not isinstance(raw, dict) or raw.get("format") != FORMAT:
            raise CheckpointError(f"checkpoint {path} is not a format-{FORMAT} checkpoint; "
                                  "move it away to start a new map")
        try:
            return cls(robot=str(raw["robot"]), state=bytes(raw["state"]),
                       positions={str(k): dict(v) for k, v in raw["positions"].items()},
                       next_anonymous_id=int(raw["next_anonymous_id"]),
                       noise={str(k): float(v) for k, v in raw["noise"].items()},
                       linearisation=_linearisation(raw.get("linearisation"), path))
        except Exception as exc:
            raise CheckpointError(f"checkpoint {path} is unreadable ({exc}); move it away "
                                  "to start a new map") from None


def _linearisation(raw: Any, path: Path) -> dict[str, Any] | None:
    """The FEJ points as saved (checked when the estimator takes them), or None."""
    if raw is None:
        return None
    if not isinstance(raw, dict):
        raise CheckpointError(f"checkpoint {path}: its linearisation points are not a map; "
                              "move it away to start a new map")
    return dict(raw)


def checkpoint_path(directory: str | Path, robot: str) -> Path:
    return Path(directory) / f"estimator-{robot}.ckpt"


def load(directory: str | Path, robot: str) -> Checkpoint | None:
    """The checkpoint of ``robot`` in ``directory``, or None if there is none yet."""
    path = checkpoint_path(directory, robot)
    try:
        payload = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise CheckpointError(f"checkpoint {path} cannot be read: {exc.strerror}") from None
    cp = Checkpoint.from_bytes(payload, path=path)
    if cp.robot != robot:
        raise CheckpointError(f"checkpoint {path} is robot {cp.robot!r}'s, not {robot!r}'s")
    return cp


def save(directory: str | Path, cp: Checkpoint) -> Path:
    """Write ``cp`` atomically (temporary file, fsync, rename, fsync of the folder)."""
    path = checkpoint_path(directory, cp.robot)
    tmp = path.with_suffix(".ckpt.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            f.write(cp.to_bytes())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as exc:
        raise CheckpointError(f"checkpoint {path} cannot be written: {exc.strerror}") \
            from None
    return path


class CheckpointWriter:
    """Writes the newest checkpoint handed to it, on its own thread (latest wins)."""

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        self.written = 0
        self.failed = 0
        self._pending: Checkpoint | None = None
        self._cond = threading.Condition()
        self._stopping = False
        self._thread = threading.Thread(target=self._loop, name="checkpoint", daemon=True)
        self._thread.start()

    def submit(self, cp: Checkpoint) -> None:
        with self._cond:
            self._pending = cp
            self._cond.notify()

    def close(self, final: Checkpoint | None = None) -> None:
        """Write ``final`` (or what is pending) now, then stop the thread."""
        with self._cond:
            self._stopping = True
            if final is not None:
                self._pending = final
            self._cond.notify()
        self._thread.join(timeout=5.0)

    def _loop(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending is not None or self._stopping)
                cp, self._pending = self._pending, None
                stopping = self._stopping
            if cp is not None:
                try:
                    save(self.directory, cp)
                    self.written += 1
                except CheckpointError as exc:
                    self.failed += 1
                    if self.failed == 1 or self.failed % 100 == 0:
                        log.warning("%s (%d failures)", exc, self.failed)
            if stopping:
                with self._cond:
                    if self._pending is None:
                        return
