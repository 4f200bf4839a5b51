#!/usr/bin/env python3
"""ROS 2: print the robot's joint positions from ``/joint_states`` (published by the bridge).

The bridge publishes one ``sensor_msgs/JointState`` per ``mds-state`` frame (names = URDF short names, positions
= measured, rad; velocity, rad/s) with a reliable QoS by default, so a default-QoS subscriber like this one
receives it (a bridge started with ``state_qos:=sensor_data`` publishes best effort: subscribe with
``qos_profile_sensor_data`` then).

Run the system first (``make run``), then, from another terminal, inside its ROS graph (network namespace and
ROS_DOMAIN_ID): ``mds-ach ros python examples/ros_joint_state_subscriber.py --count 5``
(or ``python ...`` in ``mds-ach ros-shell``).
"""

from __future__ import annotations

import argparse
import sys

import rclpy
from rclpy.node import Node
from rclpy.utilities import remove_ros_args
from sensor_msgs.msg import JointState


class JointStatePrinter(Node):
    def __init__(self, count: int) -> None:
        super().__init__("joint_state_printer")
        self.remaining = count  # 0: forever
        self.create_subscription(JointState, "joint_states", self.on_state, 10)  # default QoS: reliable

    def on_state(self, msg: JointState) -> None:
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        joints = "  ".join(f"{n}={p:+.4f}" for n, p in zip(msg.name, msg.position, strict=False))
        print(f"{stamp:.3f}  {joints}", flush=True)
        if self.remaining:
            self.remaining -= 1


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=0, help="messages to print, then exit (default 0: forever)")
    parser.add_argument("--timeout", type=float, default=30.0, help="s to wait for each message")
    args = parser.parse_args(remove_ros_args(sys.argv)[1:])

    rclpy.init()
    node = JointStatePrinter(args.count)
    try:
        while rclpy.ok() and (args.count == 0 or node.remaining > 0):
            before = node.remaining
            rclpy.spin_once(node, timeout_sec=args.timeout)
            if args.count and node.remaining == before:
                print(f"no /joint_states within {args.timeout:g} s: is the bridge running? (after "
                      "'make run': run this through 'mds-ach ros' or inside 'mds-ach ros-shell')", file=sys.stderr)
                return 1
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
