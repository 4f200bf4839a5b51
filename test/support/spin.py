"""A probe node in its own rclpy context, spun until a condition holds, for the ROS test harnesses (bridge,
lifecycle, FollowJointTrajectory)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any


class Spinner:
    """``open_node`` / ``close_node`` a probe node (private context, single-threaded executor); ``spin_until`` /
    ``spin_for`` on its executor; a failed wait shows ``self.bridge_log()``."""

    context: Any
    node: Any
    executor: Any

    def open_node(self, name: str) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def close_node(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()

    def bridge_log(self) -> str:
        return ""

    def spin_until(self, pred: Callable[[], object], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not pred():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout} s waiting for {what}; log:\n{self.bridge_log()}")
            self.executor.spin_once(timeout_sec=0.02)

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)
