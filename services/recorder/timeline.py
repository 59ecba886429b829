"""The player's clock: recorded time → wall time at a rate, with pause and seek (pure).

Positions are recording log times (ns). While playing at ``rate`` r, the message logged at
``t`` is due at ``anchor_wall + (t − anchor_pos) / r``; pausing freezes the position, a seek
moves it, a new rate re-anchors at the current position. ``rate = 0`` means no timing: every
message is due at once (the caller paces on its consumers instead).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class PlayClock:
    """Where the playback is, and when each message is due (wall seconds, monotonic)."""

    rate: float
    anchor_pos_ns: int
    anchor_wall: float
    paused: bool = False

    def position_ns(self, now: float) -> int:
        """The recording time being played now."""
        if self.paused or self.rate == 0:
            return self.anchor_pos_ns
        return self.anchor_pos_ns + int((now - self.anchor_wall) * self.rate * 1e9)

    def due(self, log_time_ns: int) -> float:
        """Wall time the message logged at ``log_time_ns`` is due (−inf at rate 0)."""
        if self.rate == 0:
            return float("-inf")
        return self.anchor_wall + (log_time_ns - self.anchor_pos_ns) / (self.rate * 1e9)

    def played(self, log_time_ns: int) -> None:
        """At rate 0 the position is the last message played."""
        if self.rate == 0:
            self.anchor_pos_ns = log_time_ns

    def pause(self, now: float) -> None:
        if not self.paused:
            self.anchor_pos_ns, self.anchor_wall, self.paused = self.position_ns(now), now, True

    def resume(self, now: float) -> None:
        if self.paused:
            self.anchor_wall, self.paused = now, False

    def seek(self, position_ns: int, now: float) -> None:
        self.anchor_pos_ns, self.anchor_wall = int(position_ns), now

    def set_rate(self, rate: float, now: float) -> None:
        self.anchor_pos_ns, self.anchor_wall = self.position_ns(now), now
        self.rate = max(0.0, float(rate))
