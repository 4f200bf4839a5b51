"""FollowJointTrajectory goals: the controllers MoveIt knows, goal validation with result codes, tolerances.

The pure part of the action servers (``mds_ach_bridge.actions`` is the rclpy glue, the node runs the goals): which
joints each controller drives, how a goal is checked before it moves anything (the same checks as the
``mds/joint_trajectory`` topic, ``trajectory.from_message``, plus "these joints belong to this controller"), and
how the JointTolerance entries of a goal become per-joint bounds, as control_msgs documents them and
ros2_controllers' joint_trajectory_controller reads them: a tolerance > 0 is used, 0 takes the server's default (a
node parameter), -1 "erases" it (not checked). Anything else means nothing and the goal is refused (INVALID_GOAL,
the reason in error_string): NaN (every comparison with it is false, so the goal succeeded however far away), +-Inf,
any other negative value, and a negative goal_time_tolerance. Acceleration tolerances are validated the same way
but not checked (the bridge has no measured acceleration); velocity path tolerances compare the trajectory's
velocity with the measured one. The defaults are per joint (``constraints.<joint>.*``,
``mds_ach_bridge.jtc``); a goal's velocity goal tolerance left 0 is ``constraints.stopped_velocity_tolerance``, so
a goal succeeds only once the joints have stopped, as in joint_trajectory_controller.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from control_msgs.action import FollowJointTrajectory
from trajectory_msgs.msg import JointTrajectory

from mds_ach_bridge import topics, trajectory
from mds_ach_bridge.commands import CommandError, check_names
from mds_ach_bridge.limits import Limits

Result = FollowJointTrajectory.Result

CONTROLLERS = topics.CONTROLLERS
ACTION = topics.FOLLOW_JOINT_TRAJECTORY
"""The action is ``<controller>/follow_joint_trajectory`` (relative: a node namespace moves it)."""

CODE_NAMES = {
    Result.SUCCESSFUL: "SUCCESSFUL", Result.INVALID_GOAL: "INVALID_GOAL", Result.INVALID_JOINTS: "INVALID_JOINTS",
    Result.OLD_HEADER_TIMESTAMP: "OLD_HEADER_TIMESTAMP", Result.PATH_TOLERANCE_VIOLATED: "PATH_TOLERANCE_VIOLATED",
    Result.GOAL_TOLERANCE_VIOLATED: "GOAL_TOLERANCE_VIOLATED",
}


class GoalError(CommandError):
    """A goal that cannot run: ``code`` is the FollowJointTrajectory result code, the message the error_string."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class Tolerance:
    """Bounds for one joint; ``math.inf`` = not checked."""

    position: float = math.inf
    velocity: float = math.inf


@dataclass(frozen=True)
class Tolerances:
    path: dict[str, Tolerance]  # while the trajectory runs: |desired - actual|
    goal: dict[str, Tolerance]  # at the end: |final - actual|, |actual velocity - final velocity|
    goal_time: float  # s after the trajectory's end to meet the goal tolerances; math.inf = no limit


ERASE = -1.0
"""JointTolerance's documented "no limit" value; like joint_trajectory_controller, within float32 rounding."""
_ERASE_SLACK = 1.2e-7  # float32 epsilon


def _check(value: float, where: str, unit: str) -> None:
    """A ``GoalError`` naming ``where`` unless ``value`` is a tolerance JointTolerance defines (> 0, 0 or -1)."""
    if math.isfinite(value) and (value >= 0.0 or abs(value - ERASE) <= _ERASE_SLACK):
        return
    raise GoalError(Result.INVALID_GOAL, f"{where} {value:g} is not a tolerance: give > 0 {unit}, 0 for the "
                                         f"default or -1 for none")


def _bound(value: float, default: float) -> float:
    if value < 0.0:  # ERASE (the only negative value _check lets through)
        return math.inf
    if value == 0.0:
        return default if default > 0.0 else math.inf
    return value


def tolerances(names: Sequence[str], goal: FollowJointTrajectory.Goal, default_path: Mapping[str, Tolerance],
               default_goal: Mapping[str, Tolerance], default_goal_time: float) -> Tolerances:
    """The goal's JointTolerance entries (by joint name; others ignored) over the server's per-joint defaults; a
    value that means nothing is a ``GoalError`` (see module doc). ``default_goal_time`` 0 = no limit (as
    joint_trajectory_controller's ``constraints.goal_time``)."""
    for field in ("path_tolerance", "goal_tolerance"):
        for i, e in enumerate(getattr(goal, field)):
            for what, unit in (("position", "rad"), ("velocity", "rad/s"), ("acceleration", "rad/s^2")):
                _check(getattr(e, what), f"{field}[{i}] ({e.name}): {what}", unit)
    t = trajectory.seconds(goal.goal_time_tolerance)
    if t < 0.0:
        raise GoalError(Result.INVALID_GOAL, f"goal_time_tolerance {t:g} s is negative: give > 0 s, or 0 for the "
                                             f"default")

    def resolve(entries: Sequence, defaults: Mapping[str, Tolerance]) -> dict[str, Tolerance]:
        given = {e.name: e for e in entries}
        out = {}
        for n in names:
            e, default = given.get(n), defaults.get(n, Tolerance())
            out[n] = default if e is None else Tolerance(_bound(e.position, default.position),
                                                         _bound(e.velocity, default.velocity))
        return out

    chosen = t if t > 0.0 else default_goal_time
    return Tolerances(resolve(goal.path_tolerance, default_path), resolve(goal.goal_tolerance, default_goal),
                      chosen if chosen > 0.0 else math.inf)


def path_violation(tol: Tolerances, desired: Mapping[str, float], actual: Mapping[str, float],
                   desired_velocity: Mapping[str, float] | None = None,
                   velocity: Mapping[str, float] | None = None) -> str | None:
    """Why the path tolerance is violated now (position, and velocity when both velocities are given), or None."""
    for n, want in desired.items():
        err = want - actual[n]
        if abs(err) > tol.path[n].position:
            return (f"{n}: position error {err:+.4f} rad exceeds the path tolerance {tol.path[n].position:g} rad "
                    f"(desired {want:.4f}, actual {actual[n]:.4f})")
        if desired_velocity is not None and velocity is not None:
            verr = desired_velocity[n] - velocity[n]
            if abs(verr) > tol.path[n].velocity:
                return (f"{n}: velocity error {verr:+.4f} rad/s exceeds the path tolerance {tol.path[n].velocity:g} "
                        f"rad/s (desired {desired_velocity[n]:.4f}, actual {velocity[n]:.4f})")
    return None


def goal_missing(tol: Tolerances, final: Mapping[str, float], actual: Mapping[str, float],
                 velocity: Mapping[str, float], final_velocity: Mapping[str, float] | None = None) -> str | None:
    """Which joint is not within the goal tolerance yet, or None when all are: the position, and the measured
    velocity against the last point's (0 unless allow_nonzero_velocity_at_trajectory_end let another through)."""
    for n, want in final.items():
        err = want - actual[n]
        if abs(err) > tol.goal[n].position:
            return f"{n}: position error {err:+.4f} rad > goal tolerance {tol.goal[n].position:g} rad"
        verr = velocity[n] - (final_velocity or {}).get(n, 0.0)
        if abs(verr) > tol.goal[n].velocity:
            return (f"{n}: velocity {velocity[n]:+.4f} rad/s, {abs(verr):.4f} rad/s off the last point's > goal "
                    f"tolerance {tol.goal[n].velocity:g} rad/s (not stopped yet)")
    return None


SPEED_SLACK = 1.01
"""A waypoint speed up to 1 % over the published velocity is rounding (a planner timing at exactly the limit)."""


def validate(controller: str, goal: FollowJointTrajectory.Goal, now: float, limits: Limits,
             allow_partial: bool = False, allow_nonzero_end: bool = False,
             speeds: Mapping[str, float] | None = None) -> trajectory.Trajectory:
    """The goal's trajectory, checked completely, or a ``GoalError`` with the result code and the reason."""
    if goal.multi_dof_trajectory.joint_names or goal.multi_dof_trajectory.points:
        raise GoalError(Result.INVALID_GOAL, "multi_dof_trajectory is not supported (the MDS has no multi-DOF joints)")
    return validate_trajectory(controller, goal.trajectory, now, limits, allow_partial, allow_nonzero_end, speeds)


def validate_trajectory(controller: str, msg: JointTrajectory, now: float, limits: Limits,
                        allow_partial: bool = False, allow_nonzero_end: bool = False,
                        speeds: Mapping[str, float] | None = None) -> trajectory.Trajectory:
    """A trajectory for ``controller`` (a goal's or its ``joint_trajectory`` topic's), checked as
    joint_trajectory_controller checks it before accepting it, or a ``GoalError``: every joint of the controller
    unless ``allow_partial`` (its ``allow_partial_joints_goal``; disabled joints are not required), a last point at
    rest unless ``allow_nonzero_end`` (``allow_nonzero_velocity_at_trajectory_end``), and the topic's checks. With
    ``speeds`` (rad/s by joint: the published velocities, ``mds-limits``) also a timing the joints can follow:
    neither a point's velocity nor the mean speed between two points above it (a faster goal would be stretched
    downstream and end late; JTC has no such check, its hardware follows or faults)."""
    own = CONTROLLERS[controller]
    if not msg.joint_names:
        raise GoalError(Result.INVALID_JOINTS, "trajectory.joint_names is empty")
    foreign = [n for n in msg.joint_names if n not in own]
    if foreign:
        raise GoalError(Result.INVALID_JOINTS,
                        f"{', '.join(map(repr, foreign))} not joints of {controller} ({' '.join(own)})")
    try:
        check_names(msg.joint_names, limits)  # duplicates, joints disabled in the joint table
    except CommandError as exc:
        raise GoalError(Result.INVALID_JOINTS, str(exc)) from None
    left_out = [n for n in own if n in limits and n not in msg.joint_names]
    if left_out and not allow_partial:
        raise GoalError(Result.INVALID_JOINTS,
                        f"{' '.join(left_out)} of {controller} left out: give every joint of the controller "
                        f"(allow_partial_joints_goal is false)")
    if msg.points and not allow_nonzero_end:
        moving = [f"{n} {v:g} rad/s" for n, v in zip(msg.joint_names, msg.points[-1].velocities, strict=False)
                  if v != 0.0]
        if moving:
            raise GoalError(Result.INVALID_GOAL,
                            f"the last point's velocity is not zero ({', '.join(moving)}): a trajectory ends at rest "
                            f"(allow_nonzero_velocity_at_trajectory_end is false)")
    try:
        traj = trajectory.from_message(msg, now, limits)
    except trajectory.StaleTrajectoryError as exc:
        raise GoalError(Result.OLD_HEADER_TIMESTAMP, str(exc)) from None
    except CommandError as exc:
        raise GoalError(Result.INVALID_GOAL, str(exc)) from None
    if speeds is not None:
        why = too_fast(traj, speeds)
        if why is not None:
            raise GoalError(Result.INVALID_GOAL, why)
    return traj


def too_fast(traj: trajectory.Trajectory, speeds: Mapping[str, float]) -> str | None:
    """Why ``traj`` asks a joint for more than its published velocity (a point's velocity, or the mean speed
    between two points: a lower bound of what any interpolation needs), or None."""
    for j, n in enumerate(traj.names):
        limit = speeds.get(n)
        if limit is None or not math.isfinite(limit):
            continue
        for k in range(len(traj.times)):
            if traj.velocities is not None and abs(traj.velocities[k][j]) > limit * SPEED_SLACK:
                return (f"{n}: point {k}'s velocity {traj.velocities[k][j]:+.3f} rad/s is over the {limit:g} rad/s the "
                        f"joint can follow (mds-limits): time the trajectory within the published limits")
            if k == 0:
                continue
            dt = traj.times[k] - traj.times[k - 1]
            need = abs(traj.positions[k][j] - traj.positions[k - 1][j]) / dt
            if need > limit * SPEED_SLACK:
                return (f"{n}: {need:.3f} rad/s needed between points {k - 1} and {k} "
                        f"({abs(traj.positions[k][j] - traj.positions[k - 1][j]):.3f} rad in {dt:.3f} s), over the "
                        f"{limit:g} rad/s the joint can follow (mds-limits): time the trajectory within the "
                        f"published limits")
    return None
