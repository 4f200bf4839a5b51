"""FollowJointTrajectory goals: the controllers MoveIt knows, goal validation with result codes, tolerances.

The pure part of the action servers (``mds_ach_bridge.actions`` is the rclpy glue, the node runs the goals): which
joints each controller drives, how a goal is checked before it moves anything (the same checks as the
``mds/joint_trajectory`` topic, ``trajectory.from_message``, plus "these joints belong to this controller"), and
how the JointTolerance entries of a goal become per-joint bounds, as control_msgs documents them and
ros2_controllers' joint_trajectory_controller reads them: a tolerance > 0 is used, 0 takes the server's default (a
node parameter), -1 "erases" it (not checked). Anything else means nothing and the goal is refused (INVALID_GOAL,
the reason in error_string): NaN (every comparison with it is false, so the goal succeeded however far away), +-Inf,
any other negative value, and a negative goal_time_tolerance. Acceleration tolerances are validated the same way
but not checked (the bridge has no measured acceleration).
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
    goal: dict[str, Tolerance]  # at the end: |final - actual|, |actual velocity|
    goal_time: float  # s after the trajectory's end to meet the goal tolerances


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


def tolerances(names: Sequence[str], goal: FollowJointTrajectory.Goal, default_path: Tolerance,
               default_goal: Tolerance, default_goal_time: float) -> Tolerances:
    """The goal's JointTolerance entries (by joint name; others ignored) over the server's defaults; a value that
    means nothing is a ``GoalError`` (see module doc)."""
    for field in ("path_tolerance", "goal_tolerance"):
        for i, e in enumerate(getattr(goal, field)):
            for what, unit in (("position", "rad"), ("velocity", "rad/s"), ("acceleration", "rad/s^2")):
                _check(getattr(e, what), f"{field}[{i}] ({e.name}): {what}", unit)
    t = trajectory.seconds(goal.goal_time_tolerance)
    if t < 0.0:
        raise GoalError(Result.INVALID_GOAL, f"goal_time_tolerance {t:g} s is negative: give > 0 s, or 0 for the "
                                             f"default")

    def resolve(entries: Sequence, default: Tolerance) -> dict[str, Tolerance]:
        given = {e.name: e for e in entries}
        out = {}
        for n in names:
            e = given.get(n)
            out[n] = default if e is None else Tolerance(_bound(e.position, default.position),
                                                         _bound(e.velocity, default.velocity))
        return out

    return Tolerances(resolve(goal.path_tolerance, default_path), resolve(goal.goal_tolerance, default_goal),
                      t if t > 0.0 else default_goal_time)


def path_violation(tol: Tolerances, desired: Mapping[str, float], actual: Mapping[str, float]) -> str | None:
    """Why the path tolerance is violated now, or None."""
    for n, want in desired.items():
        err = want - actual[n]
        if abs(err) > tol.path[n].position:
            return (f"{n}: position error {err:+.4f} rad exceeds the path tolerance {tol.path[n].position:g} rad "
                    f"(desired {want:.4f}, actual {actual[n]:.4f})")
    return None


def goal_missing(tol: Tolerances, final: Mapping[str, float], actual: Mapping[str, float],
                 velocity: Mapping[str, float]) -> str | None:
    """Which joint is not within the goal tolerance yet, or None when all are."""
    for n, want in final.items():
        err = want - actual[n]
        if abs(err) > tol.goal[n].position:
            return f"{n}: position error {err:+.4f} rad > goal tolerance {tol.goal[n].position:g} rad"
        if abs(velocity[n]) > tol.goal[n].velocity:
            return f"{n}: velocity {velocity[n]:+.4f} rad/s > goal tolerance {tol.goal[n].velocity:g} rad/s"
    return None


def validate(controller: str, goal: FollowJointTrajectory.Goal, now: float, limits: Limits) -> trajectory.Trajectory:
    """The goal's trajectory, checked completely, or a ``GoalError`` with the result code and the reason."""
    own = CONTROLLERS[controller]
    msg: JointTrajectory = goal.trajectory
    if goal.multi_dof_trajectory.joint_names or goal.multi_dof_trajectory.points:
        raise GoalError(Result.INVALID_GOAL, "multi_dof_trajectory is not supported (the MDS has no multi-DOF joints)")
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
    try:
        return trajectory.from_message(msg, now, limits)
    except trajectory.StaleTrajectoryError as exc:
        raise GoalError(Result.OLD_HEADER_TIMESTAMP, str(exc)) from None
    except CommandError as exc:
        raise GoalError(Result.INVALID_GOAL, str(exc)) from None
