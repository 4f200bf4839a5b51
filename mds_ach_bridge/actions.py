"""The rclpy side of the FollowJointTrajectory servers: one per controller of ``follow.CONTROLLERS``.

As joint_trajectory_controller does, a goal is checked in the goal callback (``on_request``): a goal the bridge
cannot run (wrong or missing joints, bad times, limits, old stamp, a moving last point, a tolerance that means
nothing, no live state stream) is rejected there, before anything moves. The action protocol's goal response has
no room for a reason, so it goes to the bridge's log and ``mds/command_status`` (a rejected goal has no result).

The bridge's state thread runs the accepted goals (it samples their trajectories, checks their tolerances and
publishes their feedback on every state frame); the executor only takes goals and cancel requests in. rclpy runs
an action's execute callback as an executor task, and a task that waits is resumed on every executor turn (a busy
loop on the bridge's single executor thread). So ``_Server`` splits ``execute()``: on acceptance it only marks the
goal EXECUTING (the status clients see while it runs); the execute task is started when the goal has ended, applies
the outcome the bridge decided (succeed, abort, canceled) and returns the result at once.
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


class _Server(ActionServer):
    """An ActionServer whose ``ServerGoalHandle.execute()`` without a callback only sets the status EXECUTING: the
    execute task (which delivers the result) is started by ``Goal.publish_end`` once the goal has ended."""

    def notify_execute(self, goal_handle: ServerGoalHandle, execute_callback: Any) -> None:
        if execute_callback is not None:
            super().notify_execute(goal_handle, execute_callback)


class Goal:
    """One accepted goal: its handle, controller and tolerances, and how it ended (set once, by the bridge)."""

    def __init__(self, handle: ServerGoalHandle, controller: str, server: ActionServer) -> None:
        self.handle = handle
        self.controller = controller
        self._server = server
        self.tolerances: follow.Tolerances | None = None
        self.outcome: tuple[str, int, str] | None = None  # (SUCCEED|ABORT|CANCELED, result code, error_string)
        self._published = threading.Event()

    def end(self, how: str, code: int, text: str) -> bool:
        """Decide the outcome (the caller serialises this, under the bridge's lock); False if already ended."""
        if self.outcome is not None:
            return False
        self.outcome = (how, code, text)
        return True

    def executing(self) -> None:
        """Status EXECUTING (from ACCEPTED), published now; nothing runs on the executor until ``publish_end``."""
        self.handle.execute()

    def publish_end(self) -> None:
        """Hand the decided outcome to the client: start the execute callback, which returns the result."""
        if self.outcome is None or self._published.is_set():
            return
        self._published.set()
        self._server.notify_execute(self.handle, self._execute)

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
                 velocity: Sequence[float], desired_velocity: Sequence[float]) -> None:
        """One feedback message: desired (the trajectory sampled now), actual (measured), error = desired - actual."""
        fb = FollowJointTrajectory.Feedback(joint_names=list(names))
        fb.header.stamp = stamp
        fb.desired.positions = [float(v) for v in desired]
        fb.desired.velocities = [float(v) for v in desired_velocity]
        fb.actual.positions = [float(v) for v in actual]
        fb.actual.velocities = [float(v) for v in velocity]
        fb.error.positions = [d - a for d, a in zip(fb.desired.positions, fb.actual.positions, strict=True)]
        fb.error.velocities = [d - a for d, a in zip(fb.desired.velocities, fb.actual.velocities, strict=True)]
        try:
            self.handle.publish_feedback(fb)
        except Exception:  # noqa: BLE001 - the goal or the context went away; its result tells the rest
            pass


def create_servers(node: Node, on_request: Callable[[str, Any], bool],
                   on_goal: Callable[[str, ServerGoalHandle, ActionServer], None],
                   on_cancel: Callable[[ServerGoalHandle], bool]) -> list[ActionServer]:
    """``<controller>/follow_joint_trajectory`` for every controller; ``on_request`` checks a goal request (False:
    rejected, the reason logged), ``on_goal`` starts an accepted goal, ``on_cancel`` stops it and says whether it
    was still running."""
    def cancel(handle: ServerGoalHandle) -> CancelResponse:
        return CancelResponse.ACCEPT if on_cancel(handle) else CancelResponse.REJECT

    def unused(handle: ServerGoalHandle) -> FollowJointTrajectory.Result:  # every goal gets its own callback
        handle.abort()
        return FollowJointTrajectory.Result(error_code=FollowJointTrajectory.Result.INVALID_GOAL,
                                            error_string="internal: goal executed without an outcome")

    servers: list[ActionServer] = []
    for controller in follow.CONTROLLERS:
        server = _Server(
            node, FollowJointTrajectory, f"{controller}/{follow.ACTION}", unused,
            goal_callback=lambda request, c=controller: GoalResponse.ACCEPT if on_request(c, request)
            else GoalResponse.REJECT,
            cancel_callback=cancel)
        server.register_handle_accepted_callback(lambda h, c=controller, s=server: on_goal(c, h, s))
        servers.append(server)
    return servers
