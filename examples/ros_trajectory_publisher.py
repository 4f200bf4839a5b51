#!/usr/bin/env python3
"""ROS 2: send a ``trajectory_msgs/JointTrajectory`` to the bridge (left shoulder and elbow, two points).

The bridge samples the trajectory on every state cycle and writes it to its mux input (``mds-ref-ros``), so it
still goes through the mux, filter and collision gate. Names are the URDF short names (LSP, LEP, ...);
``time_from_start`` counts from the header stamp (zero stamp: when the bridge receives it). A first point
later than 0 starts from the current reference.

Run the system first (``make run``), then, from another terminal, inside its ROS graph (network namespace and
ROS_DOMAIN_ID): ``mds-ach ros python examples/ros_trajectory_publisher.py``
(or ``python ...`` in ``mds-ach ros-shell``).
"""

from __future__ import annotations

import argparse
import sys
import time

import rclpy
from builtin_interfaces.msg import Duration
from rclpy.duration import Duration as RclpyDuration
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

JOINTS = ["LSP", "LEP"]
# (seconds from start, [LSP, LEP] in rad): raise the arm forward a little, bend the elbow, then settle.
POINTS = [(3.0, [-0.3, -0.6]), (6.0, [-0.2, -0.3])]


def make_trajectory() -> JointTrajectory:
    msg = JointTrajectory()
    msg.joint_names = JOINTS
    for t, positions in POINTS:
        point = JointTrajectoryPoint()
        point.positions = [float(p) for p in positions]
        point.time_from_start = Duration(sec=int(t), nanosec=int((t % 1.0) * 1e9))
        msg.points.append(point)
    return msg  # header.stamp left zero: the trajectory starts when the bridge receives it


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timeout", type=float, default=30.0, help="s to wait for the bridge to subscribe")
    args = parser.parse_args(remove_ros_args(sys.argv)[1:])

    rclpy.init()
    node = Node("trajectory_example")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)  # commands are reliable
    pub = node.create_publisher(JointTrajectory, "mds/joint_trajectory", qos)
    try:
        deadline = time.monotonic() + args.timeout
        while pub.get_subscription_count() == 0:  # publishing before discovery would lose the message
            if time.monotonic() > deadline:
                print("nobody subscribes to mds/joint_trajectory: is the bridge running? (after 'make run': run this "
                      "through 'mds-ach ros' or inside 'mds-ach ros-shell')", file=sys.stderr)
                return 1
            rclpy.spin_once(node, timeout_sec=0.1)
        pub.publish(make_trajectory())
        print(f"sent a {POINTS[-1][0]:g} s trajectory for {', '.join(JOINTS)}: " +
              ", ".join(f"t={t:g} s {p}" for t, p in POINTS))
        # A reliable publisher knows when the bridge has the message: wait for that before going away.
        if not pub.wait_for_all_acked(RclpyDuration(seconds=5.0)):
            print("the bridge did not acknowledge the trajectory", file=sys.stderr)
            return 1
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
