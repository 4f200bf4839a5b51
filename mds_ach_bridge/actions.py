"""The rclpy side of the FollowJointTrajectory servers: one per controller of ``follow.CONTROLLERS``.

The bridge's state thread runs the goals (it samples their trajectories, checks their tolerances and publishes
their feedback on every state frame); the executor only takes goals and cancel requests in. rclpy runs an action's
execute callback as an executor task, and a task that waits is resumed on every executor turn (a busy loop on the
bridge's single executor thread). So a goal's execute callback is started only when the goal has ended: it applies
the outcome the bridge decided (succeed, abort, canceled) and returns the result at once. Until then the goal's
status is ACCEPTED (not EXECUTING); clients such as MoveIt and ``ros2 action send_goal`` only wait for the result.

A goal the bridge cannot run (wrong joints, bad times, limits, old stamp, a tolerance that means nothing) is
accepted and ended at once as aborted with the result code and the reason in ``error_string``: the action
protocol's goal response has no room for a reason, and MoveIt logs a result's error_string.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any

from builtin_interfaces.msg import Time
from control_msgs.action import FollowJointTrajectory
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.action.server import ServerGoalHandle
from rclpy.node import Node

from mds_ach_bridge import follow

SUCCEED, ABORT, CANCELED = "succeeded", "aborted", "canceled"


class Goal:
    """One accepted goal: its handle, controller and tolerances, and how it ended (set once, by the bridge)."""

    def __init__(self, handle: ServerGoalHandle, controller: str) -> None:
        self.handle = handle
        self.controller = controller
        self.tolerances: follow.Tolerances | None = None
        self.outcome: tuple[str, int, str] | None = None  # (SUCCEED|ABORT|CANCELED, result code, error_string)
        self._published = threading.Event()

    def end(self, how: str, code: int, text: str) -> bool:
        """Decide the outcome (the caller serialises this, under the bridge's lock); False if already ended."""
        if self.outcome is not None:
            return False
        self.outcome = (how, code, text)
        return True

    def publish_end(self) -> None:
        """Hand the decided outcome to the client: start the execute callback, which returns the result."""
        if self.outcome is None or self._published.is_set():
            return
        self._published.set()
        self.handle.execute(self._execute)

    def _execute(self, handle: ServerGoalHandle) -> FollowJointTrajectory.Result:
        assert self.outcome is not None
        how, code, text = self.outcome
        if how == CANCELED and handle.is_cancel_requested:
            handle.canceled()
        elif how == SUCCEED and not handle.is_cancel_requested:
            handle.succeed()
        else:
            handle.abort()
        return FollowJointTrajectory.Result(error_code=code, error_string=text)

    def feedback(self, stamp: Time, names: Sequence[str], desired: Sequence[float], actual: Sequence[float],
                 velocity: Sequence[float]) -> None:
        """One feedback message: desired (the trajectory sampled now), actual (measured), error = desired - actual."""
        fb = FollowJointTrajectory.Feedback(joint_names=list(names))
        fb.header.stamp = stamp
        fb.desired.positions = [float(v) for v in desired]
        fb.actual.positions = [float(v) for v in actual]
        fb.actual.velocities = [float(v) for v in velocity]
        fb.error.positions = [d - a for d, a in zip(fb.desired.positions, fb.actual.positions, strict=True)]
        try:
            self.handle.publish_feedback(fb)
        except Exception:  # noqa: BLE001 - the goal or the context went away; its result tells the rest
            pass


def create_servers(node: Node, on_goal: Callable[[str, ServerGoalHandle], None],
                   on_cancel: Callable[[ServerGoalHandle], bool]) -> list[ActionServer]:
    """``<controller>/follow_joint_trajectory`` for every controller; ``on_goal`` validates and starts a goal,
    ``on_cancel`` stops it and says whether it was still running."""
    def accept(_request: Any) -> GoalResponse:
        return GoalResponse.ACCEPT  # checked in on_goal, so a bad goal's reason reaches the client in its result

    def cancel(handle: ServerGoalHandle) -> CancelResponse:
        return CancelResponse.ACCEPT if on_cancel(handle) else CancelResponse.REJECT

    def unused(handle: ServerGoalHandle) -> FollowJointTrajectory.Result:  # every goal gets its own callback
        handle.abort()
        return FollowJointTrajectory.Result(error_code=FollowJointTrajectory.Result.INVALID_GOAL,
                                            error_string="internal: goal executed without an outcome")

    servers = []
    for controller in follow.CONTROLLERS:
        servers.append(ActionServer(
            node, FollowJointTrajectory, f"{controller}/{follow.ACTION}", unused, goal_callback=accept,
            handle_accepted_callback=lambda h, c=controller: on_goal(c, h), cancel_callback=cancel))
    return servers
