"""What to send a MOVETO so the joint passes a trajectory on time: the trajectory's stopping point (issue #26).

The MCB runs every MOVETO as an acceleration-limited move that *stops* at its target with the commanded acceleration
``A`` (``mds_ach.bus.simbus.trajectory_step`` models it; 80 deg/s^2 by default). Sent the trajectory's position
itself, a moving joint lags it by about ``v^2 / 2A`` plus the daemon's period (0.26-0.48 s measured before this).
Sent the *stopping point* of the desired state, ``q + v|v| / 2A``, the MCB runs at the largest speed that still stops
there, which is the desired speed at the desired position: the joint passes ``q`` with ``v``. The target is sampled
one daemon period after the cycle that sends it (:func:`lookahead`): the MCB keeps running towards it until the next
target, so a target for the send time itself would trail the trajectory by a period.

Properties the safety stages rely on:

* every target is a point the joint can stop at from the commanded state with ``A``: a target that is not
  renewed (a stall, a late frame, a cancel or a hold that freezes the reference) brakes the joint at ``A`` onto the
  last target, it never runs on; the joint does not pass its target (in the MCB's model), so the collision gate's
  check of the reference is a check of where the joint can get to;
* at rest the stopping point is the position itself: a trajectory's end and any point held at rest are exact;
* the target sequence moves at ``v (1 + a / A)``: the published limits (``mds_ach.kinematics.limits.followable``)
  keep that within the daemon's motion bounds, so the limiter passes it unchanged.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass


def stopping_point(q: float, v: float, accel: float) -> float:
    """Where a joint at ``q`` moving at ``v`` stops braking at ``accel`` (> 0)."""
    return q + v * abs(v) / (2.0 * accel)


def limiter_lead(step_velocity: float, accel: float) -> float:
    """How far ahead of the target it should send a reference must be, for the daemon's limiter (``motion.limit``)
    to send that target: the limiter never plans a step from which it could not stop at its reference with its
    acceleration bound ``accel`` (so a reference the collision gate stops at once is never passed), i.e. a target
    sequence moving at ``step_velocity`` trails its reference by ``v|v| / 2 accel``. The target lands on the intended
    one; frozen there (a cancel, a hold), the daemon's target brakes onto the reference within its bounds."""
    return step_velocity * abs(step_velocity) / (2.0 * accel)


@dataclass(frozen=True)
class Braking:
    """A joint braking at ``accel`` from ``q0`` with speed ``v0`` at time ``t0`` (what the MCB does with a target
    that is no longer renewed): its state at any later time."""

    q0: float
    v0: float
    t0: float
    accel: float

    def moving(self, t: float) -> bool:
        """Still braking at ``t``?"""
        return self.v0 != 0.0 and t < self.t0 + abs(self.v0) / self.accel

    def at(self, t: float) -> tuple[float, float]:
        """(position, velocity) at ``t``; before ``t0`` the state at ``t0``."""
        dt = max(0.0, t - self.t0)
        stop = abs(self.v0) / self.accel
        if dt >= stop:
            return stopping_point(self.q0, self.v0, self.accel), 0.0
        s = math.copysign(1.0, self.v0)
        return self.q0 + self.v0 * dt - s * 0.5 * self.accel * dt * dt, self.v0 - s * self.accel * dt


RETRACT_MARGIN = 0.02
"""s: how long before the daemon's next send a stop's retraction must be decided to reach the daemon's input (through
the mux, the filter and the collision gate: a few ms) in time; later, the daemon takes the newest target first and
that is the target the stop holds (:func:`retraction_in_time`)."""


def retraction_in_time(state_time: float, period: float, now: float) -> bool:
    """May a stop decided at ``now`` still take back the newest target, holding the daemon's reference of its last
    cycle (``mds-state`` ``ref_r``, the frame put at ``state_time``) instead? Every target aims at the daemon's next
    send and the one after (:meth:`CycleClock.lookahead`): held at the newest, a stop travels up to two periods of
    the motion more than braking needs; held at the daemon's reference, the joint brakes from the commanded state
    onto the last target sent, which the MCB is already running to (no target sent is taken back). Only when at
    least ``RETRACT_MARGIN`` is left before the daemon's next send (one ``period`` after the sends of that frame's
    cycle, ``SEND_TO_STATE`` before it); otherwise the newest goes out first and is the stop's target. The one rule
    for every stage that stops a joint (the bridge's frame, the filter's hold); times on ``time.monotonic``, the
    daemon's stamps."""
    return state_time + period - CycleClock.SEND_TO_STATE - now >= RETRACT_MARGIN


def took_newest(taken: float, newest: float, hold: float) -> bool:
    """A stop held ``hold`` (the daemon's reference) instead of ``newest``: did the daemon take ``newest`` first
    (its reference ``taken`` at its next cycle is nearer it; the retraction arrived after that cycle)? Then
    ``newest`` is its last target and the stop must go back to it before the next cycle, else that target would be
    taken back (a reversal)."""
    return hold != newest and abs(taken - newest) < abs(taken - hold)


class CycleClock:
    """The daemon's cycle as seen from its ``mds-state`` frames: their own stamps give the period."""

    WINDOW = 9
    MIN_PERIOD = 1e-3  # s: the daemon's fastest loop
    MAX_PERIOD = 0.1  # s: its slowest (10 Hz, ``motion.MIN_RATE_HZ``)
    SEND_TO_STATE = 0.01  # s: a state frame is put this long after the cycle's MOVETOs went out (the reply window;
    # 3-10 ms on the simulated bus; measured: with it the best-fit lag of a tracked trajectory is 0-5 ms, without it
    # the arm runs 10-15 ms ahead)

    def __init__(self) -> None:
        self._last: float | None = None
        self._gaps: deque[float] = deque(maxlen=self.WINDOW)

    def update(self, stamp: float) -> None:
        """A new state frame stamped ``stamp`` (s, the daemon's clock); a gap of a stall is not a period."""
        if self._last is not None:
            gap = stamp - self._last
            if self.MIN_PERIOD <= gap <= 1.5 * self.MAX_PERIOD:
                self._gaps.append(gap)
        self._last = stamp

    @property
    def period(self) -> float:
        """The median frame interval (the daemon's default 10 Hz until frames tell)."""
        if not self._gaps:
            return self.MAX_PERIOD
        return min(max(statistics.median(self._gaps), self.MIN_PERIOD), self.MAX_PERIOD)

    def lookahead(self) -> float:
        """How far after a state frame the target written for it is sampled: the daemon sends it at its next cycle
        (one period after the sends of this frame's cycle, ``SEND_TO_STATE`` before the frame), and the MCB runs
        towards it for one more period."""
        return 2.0 * self.period - self.SEND_TO_STATE

