"""ROS-argument stripping, once for every executable (nodes, bridge, operator tools).

Every executable accepts ``--ros-args ... [--]`` (``ros2 run`` and launch files add them) and parses the rest with
argparse. This does what ``rclpy.utilities.remove_ros_args`` does, without importing rclpy: the tools must start
fast and work where ROS is not installed.

Imports: nothing of mds_ach.
"""

from __future__ import annotations

from collections.abc import Sequence

ROS_ARGS = "--ros-args"
ROS_ARGS_END = "--"


def strip_ros_args(argv: Sequence[str]) -> list[str]:
    """``argv`` without its ``--ros-args ... [--]`` blocks (there may be several)."""
    out: list[str] = []
    in_ros = False
    for word in argv:
        if word == ROS_ARGS:
            in_ros = True
        elif in_ros and word == ROS_ARGS_END:
            in_ros = False
        elif not in_ros:
            out.append(word)
    return out
