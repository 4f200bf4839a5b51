"""Every node's log lines carry their time (issue 30 item 5): the daemon's Python lines and rclpy's lines of the
ROS nodes (through ``mds_ach.nodes.rosnode.run_node``), both ``YYYY-MM-DD HH:MM:SS.mmm`` first."""

from __future__ import annotations

import os
import re
import subprocess
import sys

from support import REPO

STAMP = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3} ")


def test_daemon_lines_start_with_their_time() -> None:
    out = subprocess.run([sys.executable, "-m", "mds_ach.nodes.daemon", "--nocan", "--no-ros", "--duration", "1.5",
                          "--rt-priority", "0"], cwd=REPO, capture_output=True, text=True, timeout=120)
    lines = [line for line in (out.stdout + out.stderr).splitlines() if "[daemon]" in line]
    assert lines, out.stdout + out.stderr
    assert all(STAMP.match(line) for line in lines), lines


def test_ros_node_lines_start_with_their_time() -> None:
    """What run_node sets before rclpy.init reaches rcutils: an rclpy logger's line starts with the time; a format
    the user chose in the environment is kept."""
    code = ("import rclpy\nimport rclpy.logging\nfrom mds_ach import logformat\n"
            "logformat.use_ros_console_format()\nrclpy.init()\nrclpy.logging.get_logger('probe').warning('hello')\nrclpy.shutdown()\n")
    env = {k: v for k, v in os.environ.items() if k != "RCUTILS_CONSOLE_OUTPUT_FORMAT"}
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120, env=env)
    line = next(x for x in out.stderr.splitlines() if "hello" in x)
    assert STAMP.match(line) and line.endswith("[WARN] [probe]: hello"), line
    env["RCUTILS_CONSOLE_OUTPUT_FORMAT"] = "mine: {message}"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120, env=env)
    assert "mine: hello" in out.stderr


def test_run_node_uses_the_format() -> None:
    """Every ROS node starts through run_node, which sets the format before rclpy.init."""
    src = (REPO / "mds_ach" / "nodes" / "rosnode.py").read_text()
    body = src[src.index("def run_node"):]
    assert body.index("logformat.use_ros_console_format()") < body.index("rclpy.init(")
