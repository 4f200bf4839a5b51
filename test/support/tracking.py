"""Trajectory-tracking measurements on the running simulated robot (issue #26), shared by the tests and ``make bench``.

* ``Profile``: a MoveIt-style time-parameterized move of some joints (minimum-jerk, or a trapezoid at given velocity
  and acceleration), exact at any time, and its ``JointTrajectory`` (points every ``dt`` with positions, velocities
  and accelerations, the first at the start state, as MoveIt's time parameterization sends them).
* ``TrackingProbe``: a client node with the FollowJointTrajectory clients and a ``/joint_states`` recorder; ``run``
  sends a goal starting ``lead`` s in the future (``header.stamp``, so the desired motion is known exactly) and
  returns a ``Tracking``: the largest |desired - measured| while it ran, the final error, when the result came,
  and the best-fit lag.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from .spin import Spinner

MINJERK_PEAK_VELOCITY = 1.875  # x D / T
MINJERK_PEAK_ACCELERATION = 5.7735  # x D / T^2 (10 / sqrt(3))


@dataclass(frozen=True)
class Profile:
    """Joints ``names`` moving from ``start`` by ``delta`` (rad, per joint) on the unit shape ``shape``."""

    names: tuple[str, ...]
    start: tuple[float, ...]
    delta: tuple[float, ...]
    duration: float
    shape: Callable[[float], tuple[float, float, float]]  # t -> (s, ds/dt, d2s/dt2), s from 0 to 1

    def at(self, t: float) -> tuple[list[float], list[float], list[float]]:
        s, ds, dds = self.shape(min(max(t, 0.0), self.duration))
        if t <= 0.0 or t >= self.duration:
            ds = dds = 0.0
        return ([q + d * s for q, d in zip(self.start, self.delta, strict=True)],
                [d * ds for d in self.delta], [d * dds for d in self.delta])

    @property
    def end(self) -> list[float]:
        return self.at(self.duration)[0]

    def message(self, stamp_s: float, dt: float = 0.1, still: dict[str, float] | None = None):
        """The ``trajectory_msgs/JointTrajectory``: a point every ``dt`` s and one at the end; the joints of ``still``
        (name -> position) stay where they are (a controller takes goals for all of its joints)."""
        from builtin_interfaces.msg import Duration
        from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

        still = {n: q for n, q in (still or {}).items() if n not in self.names}
        msg = JointTrajectory(joint_names=[*self.names, *still])
        msg.header.stamp.sec, msg.header.stamp.nanosec = int(stamp_s), int((stamp_s % 1.0) * 1e9)
        n = max(1, math.ceil(self.duration / dt - 1e-9))
        for k in range(n + 1):
            t = min(k * dt, self.duration)
            q, v, a = self.at(t)
            rest = [0.0] * len(still)
            ns = round(t * 1e9)  # (a t just below a whole second rounds up to it, not to the second before)
            msg.points.append(JointTrajectoryPoint(
                positions=[*q, *still.values()], velocities=[*v, *rest], accelerations=[*a, *rest],
                time_from_start=Duration(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)))
        return msg


def minimum_jerk(names: Sequence[str], start: Sequence[float], delta: Sequence[float], duration: float) -> Profile:
    def shape(t: float) -> tuple[float, float, float]:
        s = t / duration
        return (10 * s**3 - 15 * s**4 + 6 * s**5, (30 * s**2 - 60 * s**3 + 30 * s**4) / duration,
                (60 * s - 180 * s**2 + 120 * s**3) / duration**2)

    return Profile(tuple(names), tuple(start), tuple(delta), duration, shape)


def trapezoid(names: Sequence[str], start: Sequence[float], delta: Sequence[float], velocity: float,
              acceleration: float) -> Profile:
    """The largest joint moves at ``velocity`` / ``acceleration`` (a triangle if it is too short); the others scaled."""
    dist = max(abs(d) for d in delta)
    ta = velocity / acceleration
    if acceleration * ta * ta > dist:  # never reaches the speed
        ta = math.sqrt(dist / acceleration)
    peak = acceleration * ta
    tc = (dist - acceleration * ta * ta) / peak
    total = 2 * ta + tc

    def shape(t: float) -> tuple[float, float, float]:
        if t < ta:
            return 0.5 * acceleration * t * t / dist, acceleration * t / dist, acceleration / dist
        if t < ta + tc:
            return (0.5 * acceleration * ta * ta + peak * (t - ta)) / dist, peak / dist, 0.0
        r = max(total - t, 0.0)
        return 1.0 - 0.5 * acceleration * r * r / dist, acceleration * r / dist, -acceleration / dist

    return Profile(tuple(names), tuple(start), tuple(delta), total, shape)


def minjerk_amplitude(duration: float, velocity: float, acceleration: float) -> float:
    """The largest minimum-jerk move of ``duration`` s within ``velocity`` and ``acceleration``."""
    return min(velocity * duration / MINJERK_PEAK_VELOCITY, acceleration * duration**2 / MINJERK_PEAK_ACCELERATION)


@dataclass(frozen=True)
class Tracking:
    """How a goal was executed, on the measured positions (``/joint_states``)."""

    max_error: float  # rad: largest |desired - measured| from the start to the end of the trajectory
    final_error: float  # rad: largest |end - measured| when the result came
    result_after: float  # s from the trajectory's start to its result
    lag: float  # s: the delay of the desired motion that fits the measured one best
    status: int
    error_string: str
    duration: float

    @property
    def allowance(self) -> float:
        """MoveIt's default execution allowance: 1.2 T + 0.5 s."""
        return 1.2 * self.duration + 0.5

    def describe(self) -> str:
        return (f"max error {self.max_error:.4f} rad, final {self.final_error:.4f} rad, lag {1e3 * self.lag:.0f} ms, "
                f"result {self.result_after:.2f} s after the start (allowance {self.allowance:.2f} s)")


def fit(profile: Profile, samples: Sequence[tuple[float, dict[str, float]]]) -> tuple[float, float]:
    """(largest |desired - measured|, best-fit lag in s) of measured ``samples`` (time from the start, positions)."""
    def error(t: float, q: dict[str, float], shift: float = 0.0) -> float:
        want = profile.at(t - shift)[0]
        return max(abs(w - q[n]) for n, w in zip(profile.names, want, strict=True))

    lags = [k * 0.005 for k in range(-40, 201)]
    lag = min(lags, key=lambda s: sum(error(t, q, s) ** 2 for t, q in samples))
    return max(error(t, q) for t, q in samples), lag


def direct_path(profile: Profile, rate: float = 10.0) -> tuple[float, float]:
    """The anchor: the original's direct path on the simulated MCB's model (``simbus.trajectory_step``, the MOVETO
    acceleration of the default joint table): the desired position sent as the MOVETO target once per cycle at
    ``rate``. Returns (largest error, best-fit lag) over the MCB's trajectory ticks."""
    import numpy as np

    from mds_ach.bus import mcb, simbus
    from mds_ach.robot import config

    table = config.load()
    accel = np.full(len(profile.names), math.radians(table.accel_deg_s2))
    tick = table.trajectory_period / mcb.TRAJECTORY_TICK_HZ
    pos = np.array(profile.start, dtype=float)
    vel = np.zeros_like(pos)
    samples: list[tuple[float, dict[str, float]]] = []
    t, next_tick, target = 0.0, tick, pos.copy()
    while t <= profile.duration:
        target = np.array(profile.at(t)[0])
        while next_tick <= t + 1.0 / rate:
            pos, vel = simbus.trajectory_step(pos, vel, target, np.full_like(pos, 10.0), accel,
                                              np.full_like(pos, tick))
            if next_tick <= profile.duration:
                samples.append((next_tick, dict(zip(profile.names, pos.tolist(), strict=True))))
            next_tick += tick
        t += 1.0 / rate
    return fit(profile, samples)


class TrackingProbe(Spinner):
    """FollowJointTrajectory clients and a ``/joint_states`` recorder (stamp, name -> position)."""

    def __init__(self, name: str = "tracking_probe") -> None:
        from control_msgs.action import FollowJointTrajectory
        from rclpy.action import ActionClient
        from sensor_msgs.msg import JointState

        self.open_node(name)
        self.states: list[tuple[float, dict[str, float]]] = []
        self._lock = threading.Lock()

        def record(msg: JointState) -> None:
            stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            with self._lock:
                self.states.append((stamp, dict(zip(msg.name, msg.position, strict=True))))

        self.node.create_subscription(JointState, "/joint_states", record, 50)
        self.clients = {c: ActionClient(self.node, FollowJointTrajectory, f"/{c}/follow_joint_trajectory")
                        for c in ("left_arm_controller", "right_arm_controller", "head_controller")}
        for c, client in self.clients.items():
            self.spin_until(client.server_is_ready, 60.0, f"the {c} action server")
        self.spin_until(lambda: self.states, 30.0, "/joint_states")

    def now(self) -> float:
        return self.node.get_clock().now().nanoseconds * 1e-9

    def position(self, name: str) -> float:
        return self.states[-1][1][name]

    def since(self, t: float) -> list[tuple[float, dict[str, float]]]:
        with self._lock:
            return [s for s in self.states if s[0] >= t]

    def goal_message(self, controller: str, profile: Profile, stamp_s: float):
        """``profile``'s trajectory for ``controller``: its other joints stay where they are now."""
        from mds_ach_bridge.follow import CONTROLLERS

        return profile.message(stamp_s, still={n: self.position(n) for n in CONTROLLERS[controller]})

    def send(self, controller: str, msg, tolerance: float | None = None):
        """Send a goal with ``msg`` as its trajectory (goal tolerance ``tolerance`` on every joint); its handle."""
        from control_msgs.action import FollowJointTrajectory
        from control_msgs.msg import JointTolerance

        goal = FollowJointTrajectory.Goal(trajectory=msg)
        if tolerance is not None:
            goal.goal_tolerance = [JointTolerance(name=n, position=tolerance) for n in msg.joint_names]
        sent = self.clients[controller].send_goal_async(goal)
        self.spin_until(sent.done, 20.0, "the goal response")
        handle = sent.result()
        assert handle is not None and handle.accepted
        return handle

    def result(self, handle, timeout: float = 30.0):
        got = handle.get_result_async()
        self.spin_until(got.done, timeout, "the goal's result")
        return got.result()

    def run(self, controller: str, profile: Profile, lead: float = 0.3, tolerance: float = 0.01) -> Tracking:
        """Execute ``profile`` starting ``lead`` s from now and measure it."""
        start = self.now() + lead
        handle = self.send(controller, self.goal_message(controller, profile, start), tolerance)
        res = self.result(handle, timeout=profile.duration + 30.0)
        done = self.now()
        self.spin_for(0.05)
        states = [(t, q) for t, q in self.since(start) if t <= done]
        during = [(t, q) for t, q in states if t <= start + profile.duration]
        assert during, "no /joint_states while the goal ran"

        max_error, lag = fit(profile, [(t - start, q) for t, q in during])
        final = states[-1][1] if states else during[-1][1]
        final_error = max(abs(w - final[n]) for n, w in zip(profile.names, profile.end, strict=True))
        return Tracking(max_error, final_error, done - start, lag, res.status, res.result.error_string,
                        profile.duration)

    def close(self) -> None:
        for client in self.clients.values():
            client.destroy()
        self.close_node()


def room(position: float, lower: float, upper: float, margin: float = 0.05) -> tuple[float, float]:
    """How far a joint at ``position`` can move down and up within its limits less ``margin``."""
    return max(0.0, position - lower - margin), max(0.0, upper - margin - position)


def wait_until(pred: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


def published(names: Sequence[str]) -> tuple[float, float]:
    """The smallest published (velocity, acceleration) of ``names`` (``mds-limits``: what each joint can follow)."""
    from mds_ach.kinematics.limits import current_limits

    limits = current_limits()
    return min(limits.motion(n)[0] for n in names), min(limits.motion(n)[1] for n in names)


def move_with_room(probe: TrackingProbe, names: Sequence[str], amplitude: float,
                   ) -> tuple[list[float], list[float]]:
    """Start positions and per-joint moves of up to ``amplitude`` rad, each joint the way it has more room."""
    from mds_ach.kinematics.limits import current_limits

    ranges = current_limits().by_short(tuple(names))
    start = [probe.position(n) for n in names]
    delta = []
    for n, q in zip(names, start, strict=True):
        down, up = room(q, *ranges[n])
        delta.append(min(amplitude, up) if up >= down else -min(amplitude, down))
    return start, delta


def state_period(probe: TrackingProbe) -> float:
    """The median interval of the recent /joint_states (the daemon's period)."""
    stamps = [t for t, _ in probe.states[-30:]]
    gaps = sorted(b - a for a, b in zip(stamps, stamps[1:], strict=False))
    return gaps[len(gaps) // 2]


def position_at(probe: TrackingProbe, name: str, t: float) -> float:
    """The measured position at ``t``, interpolated between the /joint_states around it."""
    states = probe.since(t - 1.0)
    before = [s for s in states if s[0] <= t][-1]
    after = next((s for s in states if s[0] > t), before)
    if after[0] == before[0]:
        return before[1][name]
    w = (t - before[0]) / (after[0] - before[0])
    return before[1][name] + w * (after[1][name] - before[1][name])


def positions_after(probe: TrackingProbe, t: float, name: str) -> list[float]:
    return [q[name] for _, q in probe.since(t)]


@dataclass(frozen=True)
class Cruise:
    """A trapezoid goal on one joint, started and cruising: its profile, start time, direction and goal handle."""

    profile: Profile
    start: float
    sign: float
    handle: Any


def cruise(probe: TrackingProbe, controller: str, name: str, speed: float, distance: float) -> Cruise:
    """Start a trapezoid on ``name`` at ``speed`` (the published acceleration) over up to ``distance`` the way it has
    room; return once it cruises."""
    _, a = published((name,))
    start, delta = move_with_room(probe, (name,), distance)
    profile = trapezoid((name,), start, delta, speed, a)
    t0 = probe.now() + 0.2
    handle = probe.send(controller, probe.goal_message(controller, profile, t0))
    probe.spin_until(lambda: probe.now() > t0 + speed / a + 0.2, 10.0, f"{name} at its cruising speed")
    return Cruise(profile, t0, math.copysign(1.0, delta[0]), handle)


def stop_report(probe: TrackingProbe, c: Cruise, name: str, t_request: float) -> tuple[float, float, float]:
    """After a stop requested at ``t_request``: (commanded velocity then, travel after the request, how far it came
    back from its furthest point)."""
    q_request = position_at(probe, name, t_request)
    v = abs(c.profile.at(t_request - c.start)[1][0])
    path = [c.sign * (q - q_request) for q in positions_after(probe, t_request, name)]
    back = max(max(path[: k + 1]) - path[k] for k in range(len(path)))
    return v, max(path), back
