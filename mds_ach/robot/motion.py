"""The motion bounds every target sent to a motor obeys: one definition, enforced and audited.

The daemon is the last stage before the bus, so it enforces these bounds on every MOVETO it sends, whatever
happened upstream (a mode change, a stall, a gate release, HOME, a restarted node, a node back online). The
CAN-log auditor (``mds-ach check-log``) checks recorded traffic against the very same definition, so a log
that passes the audit is a log the daemon could have produced, and vice versa.

Definition, per joint, over the sequence of targets q_i sent at times t_i:

* ``t_i`` is the moment the target was limited for, which is also the time stamp its MOVETO carries in the
  daemon's CAN log (``DaemonLoop._send``): the daemon and the auditor date a step by the very same number;
* ``h_i = min(t_i - t_{i-1}, max_interval)``: a stall or a pause never earns a bigger step than one
  ``max_interval`` (``MAX_INTERVAL``, 150 ms at every loop rate: 1.5 periods of the original's 10 Hz, the slowest
  rate the daemon accepts, so jitter at a faster rate never turns an ordinary cycle into a restart);
* speed ``|q_i - q_{i-1}| / h_i <= max_velocity``;
* the step's velocity ``v_i = (q_i - q_{i-1}) / h_i``; the previous velocity is ``v_{i-1}`` if the previous
  target came at most ``max_interval`` earlier, else 0 (the joint was told to stand still meanwhile);
  acceleration ``|v_i - v_prev| / h_i <= max_acceleration``;
* a re-seed restarts the sequence at the measured position with velocity 0, only where the log shows why: the
  daemon's start-up and the setup commands HOME, RESET, ZERO_ENCODER and ENABLE. Nothing else restarts a
  sequence: a node whose replies resume after a silence goes on from its last target (where it was going), so a
  restart never reverses a joint that is still moving.

``limit()`` picks the target closest to the desired one that keeps both bounds at ``margin`` times their
value (clock jitter between the daemon and a log's time stamps must never turn into a violation) and from which
it could still stop at the desired one (which may stop at once: the collision gate at a contact);
``check()`` reports what a recorded step breaks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

# Defaults of the joint table's `motion:` section (config/joints.yaml).
DEFAULT_MAX_VELOCITY = 2.0  # rad/s: the speed bound the pipeline promises (filter: 1.57)
DEFAULT_MAX_ACCELERATION = 8.0  # rad/s^2
MIN_RATE_HZ = 10.0  # the slowest daemon loop the bounds are defined for (the original MDS-Ach rate): a slower
# loop would put a whole move into a handful of targets
MAX_INTERVAL = 1.5 / MIN_RATE_HZ  # s: the longest interval a step counts on, at every rate >= MIN_RATE_HZ
LIMIT_MARGIN = 0.9  # the daemon's limiter stays this far inside the bounds
# Tolerance of the audit: float32 counts on the wire and float rounding, far below any motion of interest.
CHECK_TOLERANCE = 1e-6


@dataclass(frozen=True)
class MotionBounds:
    """Speed and acceleration bounds of one joint, and the longest interval a step may count on."""

    max_velocity: float  # rad/s
    max_acceleration: float  # rad/s^2
    max_interval: float  # s

    def __post_init__(self) -> None:
        for name in ("max_velocity", "max_acceleration", "max_interval"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"motion bound {name} must be finite and > 0, got {value}")

    def interval(self, dt: float) -> float:
        return min(max(dt, 0.0), self.max_interval)


@dataclass
class Track:
    """The last target sent to one joint: position (rad), the velocity of that step, and when."""

    q: float
    v: float = 0.0
    t: float = -math.inf

    def reseed(self, q: float, t: float) -> None:
        """Start again from a measured position at rest (start-up, after HOME, a node back online)."""
        self.q, self.v, self.t = q, 0.0, t

    def previous_velocity(self, now: float, bounds: MotionBounds) -> float:
        return self.v if now - self.t <= bounds.max_interval else 0.0

    def advance(self, q: float, now: float, bounds: MotionBounds) -> None:
        """Record that ``q`` was sent at ``now``."""
        h = bounds.interval(now - self.t)
        self.v = (q - self.q) / h if h > 0 else 0.0
        self.q, self.t = q, now


def _stop_speed(distance: float, h: float, a_max: float) -> float:
    """The largest speed from which braking by ``a_max * h`` per step of ``h`` still stops within ``distance``.

    Within one step's reach (``distance <= a_max h^2``) arrive this step and stop the next; beyond it the root of
    ``v h + v^2 / (2 a_max) = distance`` (travel this step, then brake).
    """
    distance = max(distance, 0.0)
    if distance <= a_max * h * h:
        return distance / h
    return a_max * (math.sqrt(h * h + 2.0 * distance / a_max) - h)


def limit(track: Track, desired: float, now: float, bounds: MotionBounds, margin: float = LIMIT_MARGIN, *,
          desired_velocity: float = 0.0, lower: float = -math.inf, upper: float = math.inf) -> float:
    """The target to send at ``now``: as close to ``desired`` as the bounds allow, braking in time.

    Velocity-limited and acceleration-limited. ``desired_velocity`` is how fast ``desired`` itself moves (0: a
    target at rest): the limiter closes the gap relative to that motion, but never faster than it could still stop
    at ``desired`` itself: whatever the reference does next (it may stop at once, where the collision gate stops an
    arm), the target does not pass it while the steps are regular. A moving reference is therefore trailed by about
    its braking distance ``v^2 / (2 a)`` at speed ``v`` (the MCB's own MOVETO trails it further). A step goes past
    ``desired`` only if the acceleration bound requires it (a reference that jumps back toward a target moving on,
    a longer step than the last): by at most ``v^2 / (2 a)``, never a jump, and never beyond ``lower``/``upper``:
    the limiter brakes for those like for a target at rest (the caller clamps as a last resort).
    """
    h = bounds.interval(now - track.t)
    if h <= 0:
        return track.q
    v_max, a_max = margin * bounds.max_velocity, margin * bounds.max_acceleration
    v0 = track.previous_velocity(now, bounds)
    v_goal = min(max(desired_velocity, -v_max), v_max) if math.isfinite(desired_velocity) else 0.0
    gap = desired - track.q - v_goal * h  # what is left to close after moving along with the target
    v = v_goal + math.copysign(_stop_speed(abs(gap), h, a_max), gap)
    v = min(max(v, -v_max, -_stop_speed(track.q - lower, h, a_max)), v_max, _stop_speed(upper - track.q, h, a_max))
    # Never a step from which the target could not stop at ``desired`` within the bounds: the reference may stop
    # there at any moment (the collision gate stops an arm at a contact more abruptly than the bounds allow, and
    # ``desired_velocity`` is an estimate from sampled references: at 100 Hz a 40 Hz input reads 0 or 2.5 times its
    # speed). A target that trailed the reference and closed in on it at speed passed it by v^2/2a, into the contact
    # the gate stopped the reference at (the 100 Hz adversary). So the target lies between the previous one and
    # ``desired``; only the acceleration bound below may carry it past, if the track came in faster than allowed.
    d = desired - track.q
    reach = _stop_speed(abs(d), h, a_max)
    v = min(v, reach) if d >= 0 else max(v, -reach)
    # The acceleration bound wins: if the track came in faster than allowed, brake as hard as allowed.
    v = min(max(v, v0 - a_max * h), v0 + a_max * h)
    return track.q + v * h


@dataclass(frozen=True)
class Violation:
    """A recorded step that breaks a bound: what, by how much, and the bound."""

    kind: str  # "speed" or "acceleration"
    value: float
    bound: float


def check(track: Track, q: float, t: float, bounds: MotionBounds,
          tolerance: float = CHECK_TOLERANCE) -> list[Violation]:
    """What the step from ``track`` to ``q`` sent at ``t`` violates (empty: nothing). Does not advance."""
    h = bounds.interval(t - track.t)
    if h <= 0:
        return [] if abs(q - track.q) <= tolerance else [Violation("speed", math.inf, bounds.max_velocity)]
    out = []
    slack = tolerance / h
    speed = abs(q - track.q) / h
    if speed > bounds.max_velocity * (1 + tolerance) + slack:
        out.append(Violation("speed", speed, bounds.max_velocity))
    accel = abs((q - track.q) / h - track.previous_velocity(t, bounds)) / h
    if accel > bounds.max_acceleration * (1 + tolerance) + slack / h:
        out.append(Violation("acceleration", accel, bounds.max_acceleration))
    return out
