"""Header stamps for state frames: the ROS time at which the daemon published the frame.

``mds_state_t.time`` is CLOCK_MONOTONIC seconds on the daemon's machine, which ROS cannot use directly
(ROS stamps are ROS time: system time, or /clock with use_sim_time). The bridge measures the frame's
age on its own monotonic clock at receipt and stamps ``ROS now - age``: that is ``state.time`` moved by
the current offset between the two clocks, so consecutive stamps keep the daemon's spacing rather than
the receipt jitter. When the age is negative or
implausibly large the two monotonic clocks are not comparable (a channel shared over the network
from another machine, a replayed log), and the stamp falls back to the time of receipt.
"""

from __future__ import annotations


def state_stamp_ns(ros_now_ns: int, monotonic_now: float, state_time: float, max_age: float) -> tuple[int, bool]:
    """``(stamp in ns, True)`` when the frame's age is in ``[0, max_age]`` s, else ``(ros_now_ns, False)``."""
    age = monotonic_now - state_time
    if 0.0 <= age <= max_age:
        return ros_now_ns - round(age * 1e9), True
    return ros_now_ns, False
