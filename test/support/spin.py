"""Spinning an rclpy executor until a condition holds, for the ROS test harnesses (bridge, lifecycle)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any


class Spinner:
    """``spin_until`` / ``spin_for`` on ``self.executor``; a failed wait shows ``self.bridge_log()``."""

    executor: Any

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
