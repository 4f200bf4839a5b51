"""Joint trajectories sampled on the state cycles: the bridge writes ``sample(now)`` once per state frame.

Semantics follow ROS's joint_trajectory_controller: ``time_from_start`` is relative to the header
stamp (or to the time of receipt when the stamp is zero); if the first point is later than 0 the
trajectory starts from the current reference (``anchor``, done by the bridge on the state cycle that
first samples it); before the start it holds that start; after the last point it holds the last point
and is finished. Segments are cubic Hermite when every point carries
velocities, linear otherwise (so no overshoot is invented from position-only points).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

from mds_ach_bridge.commands import CommandError, check_names, check_value
from mds_ach_bridge.limits import Limits

if TYPE_CHECKING:
    from trajectory_msgs.msg import JointTrajectory


class StaleTrajectoryError(CommandError):
    """The trajectory ended before it arrived (``header.stamp`` in the past)."""


@dataclass(frozen=True)
class Trajectory:
    names: tuple[str, ...]
    times: tuple[float, ...]  # seconds from start, strictly increasing; times[0] == 0 once anchored
    positions: tuple[tuple[float, ...], ...]  # one row per point
    velocities: tuple[tuple[float, ...], ...] | None  # None: linear interpolation
    start: float  # seconds on the node's clock

    @property
    def end(self) -> float:
        return self.start + self.times[-1]

    @property
    def anchored(self) -> bool:
        return self.times[0] == 0.0

    def anchor(self, current: Mapping[str, float], limits: Limits,
               velocity: Mapping[str, float] | None = None) -> Trajectory:
        """Start from ``current`` at t = 0 when the first point is later, with ``velocity`` there for cubics (the
        commanded state, as joint_trajectory_controller starts from its desired state; default at rest)."""
        if self.anchored:
            return self
        missing = [n for n in self.names if n not in current]
        if missing:
            raise CommandError(f"no current reference for {', '.join(missing)} to start from")
        start = tuple(float((velocity or {}).get(n, 0.0)) for n in self.names)
        vels = None if self.velocities is None else (start, *self.velocities)
        traj = replace(
            self,
            times=(0.0, *self.times),
            positions=(tuple(float(current[n]) for n in self.names), *self.positions),
            velocities=vels,
        )
        if traj.velocities is not None:
            check_sampled(traj, limits)
        return traj

    def sample(self, now: float) -> tuple[dict[str, float], bool]:
        """Positions at ``now`` and whether the trajectory is finished (anchor it first)."""
        values, _, done = self.sample_state(now)
        return values, done

    def sample_state(self, now: float) -> tuple[dict[str, float], dict[str, float], bool]:
        """Positions and velocities at ``now``, and whether the trajectory is finished (anchor it first). Linear
        segments move at their slope; before the start and after the end the joints are at rest."""
        if not self.anchored:
            raise ValueError("sample() on a trajectory that does not start at t = 0; anchor() it first")
        t = now - self.start
        rest = dict.fromkeys(self.names, 0.0)
        if t <= 0.0:
            return dict(zip(self.names, self.positions[0], strict=True)), rest, False
        if t >= self.times[-1]:
            return dict(zip(self.names, self.positions[-1], strict=True)), rest, True
        k = bisect.bisect_right(self.times, t) - 1  # times[k] <= t < times[k+1]
        t0, t1 = self.times[k], self.times[k + 1]
        h = t1 - t0
        s = (t - t0) / h
        p0, p1 = self.positions[k], self.positions[k + 1]
        if self.velocities is None:
            values = [a + (b - a) * s for a, b in zip(p0, p1, strict=True)]
            speeds = [(b - a) / h for a, b in zip(p0, p1, strict=True)]
        else:
            v0, v1 = self.velocities[k], self.velocities[k + 1]
            h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
            h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
            values = [
                h00 * a + h10 * h * va + h01 * b + h11 * h * vb for a, b, va, vb in zip(p0, p1, v0, v1, strict=True)
            ]
            # d/dt of the basis functions (d/ds divided by h)
            d00, d10 = (6 * s**2 - 6 * s) / h, 3 * s**2 - 4 * s + 1
            d01, d11 = (-6 * s**2 + 6 * s) / h, 3 * s**2 - 2 * s
            speeds = [
                d00 * a + d10 * va + d01 * b + d11 * vb for a, b, va, vb in zip(p0, p1, v0, v1, strict=True)
            ]
        return dict(zip(self.names, values, strict=True)), dict(zip(self.names, speeds, strict=True)), False


def build(
    names: Sequence[str],
    points: Sequence[tuple[float, Sequence[float], Sequence[float]]],
    start: float,
    limits: Limits,
) -> Trajectory:
    """Validate a trajectory message completely (all or nothing).

    ``points`` are ``(time_from_start_s, positions, velocities)``; velocities may be empty on every
    point (linear) or given on every point (cubic). Positions are checked against ``limits`` at every
    waypoint; linear segments stay between their waypoints, and cubic segments are checked on sampled
    values (:func:`check_sampled`). A first point later than t = 0 needs ``anchor()`` before sampling.
    """
    names = check_names(names, limits)
    if not points:
        raise CommandError("trajectory has no points")
    with_vel = [len(v) > 0 for _, _, v in points]
    if any(with_vel) and not all(with_vel):
        raise CommandError("velocities must be given on every point or on none")
    times: list[float] = []
    rows: list[tuple[float, ...]] = []
    vels: list[tuple[float, ...]] = []
    for i, (t, pos, vel) in enumerate(points):
        if not math.isfinite(t) or t < 0.0:
            raise CommandError(f"point {i}: time_from_start {t} must be finite and >= 0")
        if times and t <= times[-1]:
            raise CommandError(f"point {i}: time_from_start {t} s is not after the previous point ({times[-1]} s)")
        if len(pos) != len(names):
            raise CommandError(f"point {i}: {len(pos)} positions for {len(names)} joints")
        try:
            rows.append(tuple(check_value(n, p, limits) for n, p in zip(names, pos, strict=True)))
        except CommandError as exc:
            raise CommandError(f"point {i}: {exc}") from None
        if all(with_vel):
            if len(vel) != len(names):
                raise CommandError(f"point {i}: {len(vel)} velocities for {len(names)} joints")
            if not all(math.isfinite(v) for v in vel):
                raise CommandError(f"point {i}: velocities must be finite")
            vels.append(tuple(float(v) for v in vel))
        times.append(float(t))
    traj = Trajectory(names, tuple(times), tuple(rows), tuple(vels) if vels else None, start)
    if traj.velocities is not None:
        check_sampled(traj, limits)
    return traj


def seconds(t: Any) -> float:
    """A ``builtin_interfaces`` Time or Duration (``sec``, ``nanosec``) in seconds."""
    return t.sec + t.nanosec * 1e-9


def from_message(msg: JointTrajectory, now: float, limits: Limits) -> Trajectory:
    """A ``trajectory_msgs/JointTrajectory`` received at ``now`` (s, the node's clock), validated: the checks
    the ``mds/joint_trajectory`` topic and the FollowJointTrajectory goals share."""
    stamp = seconds(msg.header.stamp)
    start = stamp if stamp > 0.0 else now
    points = [(seconds(p.time_from_start), p.positions, p.velocities) for p in msg.points]
    traj = build(msg.joint_names, points, start, limits)
    if traj.end < now:
        raise StaleTrajectoryError(f"the trajectory ended {now - traj.end:.3f} s ago (header.stamp in the past)")
    return traj


def check_sampled(traj: Trajectory, limits: Limits, samples_per_segment: int = 20) -> None:
    """Cubic segments can bulge past their waypoints: refuse a trajectory that leaves the limits."""
    # Sample segment by segment from the first point (an unanchored trajectory has no segment before it).
    shifted = replace(traj, times=tuple(t - traj.times[0] for t in traj.times), start=traj.start + traj.times[0])
    for k in range(len(shifted.times) - 1):
        for j in range(1, samples_per_segment):
            t = shifted.times[k] + (shifted.times[k + 1] - shifted.times[k]) * j / samples_per_segment
            values, _ = shifted.sample(shifted.start + t)
            for n, v in values.items():
                lower, upper = limits[n]
                if not lower <= v <= upper:
                    raise CommandError(
                        f"{n}: a cubic segment reaches {v:.6g} rad at t={t + traj.times[0]:.3g} s, outside the "
                        f"limits [{lower:.6g}, {upper:.6g}] (check the velocities)"
                    )
