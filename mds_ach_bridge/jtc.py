"""joint_trajectory_controller's interface for each controller: its parameters and the state it reports.

MoveIt and ROS users drive a robot through ros2_controllers' joint_trajectory_controller (JTC, Jazzy). The bridge
serves that interface for each controller of ``follow.CONTROLLERS`` from one node, so JTC's per-controller
parameters are the bridge's and apply to every controller (joint names are unique across them). This module holds
what is not trajectory execution: the parameters with their per-joint defaults (``Settings``), the
``<controller>/controller_state`` message and the ``<controller>/query_state`` answer. Trajectories are only
sampled here (``Trajectory.sample``), never run. The differences from JTC, and why, are tabled in
mds_ach_bridge/README.md.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from builtin_interfaces.msg import Time

from mds_ach.nodes.rosnode import Param
from mds_ach.robot import joints
from mds_ach_bridge.follow import CONTROLLERS, Tolerance
from mds_ach_bridge.trajectory import Trajectory

PARTIAL = "allow_partial_joints_goal"
NONZERO_END = "allow_nonzero_velocity_at_trajectory_end"
STOPPED = "constraints.stopped_velocity_tolerance"
GOAL_TIME = "constraints.goal_time"


def path_param(joint: str) -> str:
    """JTC's per-joint path tolerance: |desired - measured| position while the trajectory runs."""
    return f"constraints.{joint}.trajectory"


def goal_param(joint: str) -> str:
    """JTC's per-joint goal tolerance: |last point - measured| position at the end."""
    return f"constraints.{joint}.goal"


GOAL_POSITION_DEFAULT = 0.02
"""rad; JTC's default is 0 (not checked): a goal at rest 0.3 rad short of its end would be SUCCESSFUL."""
_JOINTS = tuple(n for names in CONTROLLERS.values() for n in names)
assert sorted(_JOINTS) == sorted(joints.MODEL_JOINTS)

PARAMETERS: tuple[Param, ...] = (
    Param(PARTIAL, False, "FollowJointTrajectory and <controller>/joint_trajectory: accept a trajectory for only "
                          "some joints of the controller (false: refused in the goal callback, as "
                          "joint_trajectory_controller)", read_only=False),
    Param(NONZERO_END, False, "accept a trajectory whose last point has a non-zero velocity (false: refused, as "
                              "joint_trajectory_controller on Jazzy)", read_only=False),
    Param(STOPPED, 0.01, "rad/s: a goal succeeds only once every joint's measured velocity is within this of the last "
                         "point's (the goal velocity tolerance a goal leaves 0); 0 = not checked",
          range=(0.0, 10.0), read_only=False),
    Param(GOAL_TIME, 2.0, "s after the trajectory's end to meet the goal tolerances, else GOAL_TOLERANCE_VIOLATED (a "
                          "goal's goal_time_tolerance overrides it); 0 = no limit", range=(0.0, 600.0),
          read_only=False),
    *(Param(path_param(n), 0.0, f"rad: path tolerance of {n} (largest |desired - measured| while moving, else "
                                 f"PATH_TOLERANCE_VIOLATED) for a goal that leaves it 0; 0 = not checked",
            range=(0.0, 3.2), read_only=False) for n in _JOINTS),
    *(Param(goal_param(n), GOAL_POSITION_DEFAULT,
            f"rad: goal tolerance of {n} (|last point - measured| at the end) for a goal that leaves it 0; 0 = not "
            f"checked", range=(0.0, 3.2), read_only=False) for n in _JOINTS),
)
NAMES = frozenset(p.name for p in PARAMETERS)


@dataclass(frozen=True)
class Settings:
    """The JTC parameters' values as the goal checks use them."""

    allow_partial: bool
    allow_nonzero_end: bool
    goal_time: float  # s; 0 = no limit
    path: dict[str, Tolerance]  # per-joint defaults; math.inf = not checked
    goal: dict[str, Tolerance]

    @classmethod
    def from_values(cls, values: Mapping[str, Any]) -> Settings:
        """From ``{parameter name: value}`` (every name of ``NAMES``); a tolerance 0 is "not checked"."""
        def bound(v: float) -> float:
            return float(v) if v > 0.0 else math.inf

        stopped = bound(values[STOPPED])
        return cls(bool(values[PARTIAL]), bool(values[NONZERO_END]), float(values[GOAL_TIME]),
                   {n: Tolerance(bound(values[path_param(n)])) for n in _JOINTS},
                   {n: Tolerance(bound(values[goal_param(n)]), stopped) for n in _JOINTS})


def defaults() -> dict[str, Any]:
    return {p.name: p.default for p in PARAMETERS}


# ------------------------------------------------------------------------------------ what a controller reports


def velocity(traj: Trajectory, t: float) -> dict[str, float]:
    """The desired velocity at ``t``: the executor's own (``Trajectory.sample_state``, the derivative of what it
    executes); 0 outside the trajectory, where it holds. ``traj`` must be anchored."""
    return traj.sample_state(t)[1]


def reference(running: Mapping[str, Trajectory], names: Sequence[str], t: float,
              hold: Mapping[str, float]) -> dict[str, tuple[float, float]]:
    """``{joint: (position, velocity)}`` desired at ``t``: the running trajectory of each joint (``running`` by
    joint, anchored), else ``hold`` (where the joint is commanded to stay) at rest."""
    out: dict[str, tuple[float, float]] = {}
    sampled: dict[int, tuple[dict[str, float], dict[str, float]]] = {}
    for n in names:
        traj = running.get(n)
        if traj is None:
            out[n] = (hold[n], 0.0)
            continue
        if id(traj) not in sampled:
            sampled[id(traj)] = (traj.sample(t)[0], velocity(traj, t))
        pos, vel = sampled[id(traj)]
        out[n] = (pos[n], vel[n])
    return out


def controller_state(names: Sequence[str], stamp: Time, desired: Mapping[str, tuple[float, float]],
                     position: Mapping[str, float], rate: Mapping[str, float], output: Mapping[str, float]) -> Any:
    """A JointTrajectoryControllerState: reference (desired), feedback (measured), error = reference - feedback,
    output (the position the daemon commands the joint to: after mux, filter and gate)."""
    from control_msgs.msg import JointTrajectoryControllerState

    msg = JointTrajectoryControllerState(joint_names=list(names), speed_scaling_factor=1.0)
    msg.header.stamp = stamp
    msg.reference.positions = [desired[n][0] for n in names]
    msg.reference.velocities = [desired[n][1] for n in names]
    msg.feedback.positions = [float(position[n]) for n in names]
    msg.feedback.velocities = [float(rate[n]) for n in names]
    msg.error.positions = [desired[n][0] - position[n] for n in names]
    msg.error.velocities = [desired[n][1] - rate[n] for n in names]
    msg.output.positions = [float(output[n]) for n in names]
    return msg


@dataclass(frozen=True)
class Query:
    """The answer of ``query_state``, JTC's fields (``acceleration`` left empty: the trajectories have none)."""

    success: bool
    message: str
    position: list[float]
    velocity: list[float]


def query(names: Sequence[str], running: Mapping[str, Trajectory], t: float, position: Mapping[str, float],
          rate: Mapping[str, float]) -> Query:
    """The controller's state at ``t`` as JTC answers it: with no trajectory running, the measured state
    (success); otherwise the running trajectory sampled at ``t``, a failure when ``t`` is outside it."""
    trajs = {id(running[n]): running[n] for n in names if n in running}
    if not trajs:
        return Query(True, "no trajectory is running: the measured state", [position[n] for n in names],
                     [rate[n] for n in names])
    start, end = min(tr.start for tr in trajs.values()), max(tr.end for tr in trajs.values())
    ok, message = True, f"sampled at {t - start:.3f} s of the running trajectory"
    if t < start:
        ok, message = False, f"the time is {start - t:.3f} s before the running trajectory's start"
    elif t > end:
        ok, message = False, f"the time is {t - end:.3f} s after the running trajectory's end"
    want = reference(running, names, t, position)
    return Query(ok, message, [want[n][0] for n in names], [want[n][1] if n in running else rate[n] for n in names])
