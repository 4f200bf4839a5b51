"""Joint velocities for ``/joint_states``: finite differences of the measured positions of consecutive state frames.

The difference is taken over the frames' own stamps (``mds_state_t.time``, the daemon's monotonic clock when it
published the frame), not over the receipt times, so scheduling jitter in the bridge does not show up as velocity
noise, and a frame the bridge missed (newest frame wins) only lengthens the interval. The first frame, and a frame
whose stamp is not after the previous one (a restarted daemon, a replayed log), report 0 rad/s: no estimate, rather
than a spike. The daemon's own ``vel`` field is per-joint and zero for a stale joint; this is the derivative of
exactly the positions the message carries.
"""

from __future__ import annotations

from collections.abc import Sequence

MAX_INTERVAL = 1.0
"""s: frames further apart than this (a stalled stream) give no estimate (0 rad/s), not an average over the gap."""


class FiniteDifference:
    """Feed it every published frame's positions and stamp; it returns the velocities to publish with them."""

    def __init__(self) -> None:
        self._last: tuple[float, list[float]] | None = None

    def update(self, stamp: float, positions: Sequence[float]) -> list[float]:
        """Velocities (rad/s) for the frame stamped ``stamp`` (s) with ``positions`` (rad)."""
        last, self._last = self._last, (stamp, list(positions))
        if last is None or len(last[1]) != len(positions):
            return [0.0] * len(positions)
        dt = stamp - last[0]
        if not 0.0 < dt <= MAX_INTERVAL:
            return [0.0] * len(positions)
        return [(p - q) / dt for p, q in zip(positions, last[1], strict=True)]
