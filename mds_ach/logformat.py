"""The one log-line format of every node: each line starts with its wall-clock time (to the millisecond).

Why: a node's log is read next to a recording (``mds-ach record``), a CAN log and the other nodes' logs; without a
time on each line nobody can tell which refusal belonged to which moment. Two loggers write the nodes' lines:

* Python's ``logging`` (the daemon's control loop, achd): :func:`setup_python_logging`;
* rclpy's (every ROS node, the bridge): rcutils formats them from ``RCUTILS_CONSOLE_OUTPUT_FORMAT``, which
  :func:`use_ros_console_format` sets before ``rclpy.init`` unless the user chose one already (theirs wins).

Imports: the standard library only (a leaf module usable from every layer).
"""

from __future__ import annotations

import logging
import os

DATE_FORMAT = "%Y-%m-%d %H:%M:%S"
PYTHON_FORMAT = "%(asctime)s.%(msecs)03d [{name}] %(levelname)s: %(message)s"
"""``2026-11-27 22:40:01.123 [daemon] WARNING: ...``: local time, as rcutils' ``{date_time_with_ms}``."""
ROS_CONSOLE_ENV = "RCUTILS_CONSOLE_OUTPUT_FORMAT"
ROS_CONSOLE_FORMAT = "{date_time_with_ms} [{severity}] [{name}]: {message}"
"""rcutils' default is ``[{severity}] [{time}] [{name}]: {message}`` (seconds since 1970); this one reads like the
Python lines."""


def setup_python_logging(name: str, level: int = logging.INFO) -> None:
    """Python ``logging`` of process ``name`` (``[name]`` on each line) to stderr, every line with its time."""
    logging.basicConfig(level=level, format=PYTHON_FORMAT.format(name=name), datefmt=DATE_FORMAT)


def use_ros_console_format() -> None:
    """Let rclpy's console lines carry their date and time (call before ``rclpy.init``); a format the user set in
    the environment is kept."""
    os.environ.setdefault(ROS_CONSOLE_ENV, ROS_CONSOLE_FORMAT)
