"""``bridge`` (= ``ros2 run mds_ach bridge``): the ROS 2 bridge's command line.

rclpy is imported only after the arguments are parsed, so ``--help`` is instant.
"""

from __future__ import annotations

import argparse
import sys

import mds_ach as mds
from mds_ach.nodes.rosargs import strip_ros_args
from mds_ach.robot import joints
from mds_ach_bridge import topics

DESCRIPTION = f"""\
ROS 2 bridge for MDS-Ach. Every new {mds.MDS_CHAN_STATE_NAME} frame is published at once as
sensor_msgs/JointState on {topics.JOINT_STATES} (measured positions) and {topics.JOINT_REFERENCES}
(the daemon's reference), stamped with the frame's publish time. Commands from ROS are checked against
the joint limits (all or nothing; rejections are logged with the reason) and written to the bridge's
reference channel ({mds.MDS_CHAN_REF_ROS_NAME}, the bridge's mux input) once per state cycle.
"""

EPILOG = f"""\
topics (relative: remap with --ros-args -r old:=new, or move with -r __ns:=/robot):
  {topics.JOINT_STATES:<24} out  sensor_msgs/JointState      measured positions
  {topics.JOINT_REFERENCES:<24} out  sensor_msgs/JointState      the daemon's reference (state.ref)
  {topics.ROBOT_DESCRIPTION:<24} out  std_msgs/String             the URDF (transient local)
  {topics.DIAGNOSTICS:<24} out  diagnostic_msgs/DiagnosticArray  stream health, command counters
  {topics.JOINT_COMMAND:<24} in   sensor_msgs/JointState      positions by joint name
  {topics.JOINT_POSITIONS:<24} in   std_msgs/Float64MultiArray  {len(joints.MODEL_JOINTS)} positions in this order:
                                   {' '.join(joints.MODEL_JOINTS)}
  {topics.JOINT_TRAJECTORY:<24} in   trajectory_msgs/JointTrajectory  sampled on every state cycle
  {topics.IK_LEFT:<24} in   geometry_msgs/PoseStamped   left hand target -> {mds.MDS_CHAN_IK_NAME}
  {topics.IK_RIGHT:<24} in   geometry_msgs/PoseStamped   right hand target -> {mds.MDS_CHAN_IK_NAME}
IK targets are in the robot frame (frame_id '' or 'torso': between the shoulders, x forward, y left,
z up); the task DOF per arm are the parameters ik_dof_left / ik_dof_right (a prefix of
p-x p-y p-z t-x t-y t-z: 3 = position only, 6 = full pose).

parameters (--ros-args -p name:=value; `ros2 param describe` shows every one):
  state_channel, ref_channel, ik_channel, allow_ungated, state_qos (sensor_data|reliable),
  stale_timeout, max_state_age, command_mode, trajectory_mode,
  ik_dof_left, ik_dof_right, ik_frame, urdf, robot, publish_robot_description, diagnostics_period,
  rt_priority (SCHED_FIFO priority of the state thread, 0 = normal)

examples:
  bridge
  bridge --ros-args -p ref_channel:=mds-ref-filter      # no mux running: write the legacy input
  bridge --ros-args -r __ns:=/mds1 -p state_qos:=reliable
  bridge --ros-args -p rt_priority:=50                  # real-time state thread (root or rtprio limit)
"""


SWITCH_INTERVAL_S = 0.0005


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv if argv is None else [sys.argv[0], *argv])
    parser = argparse.ArgumentParser(
        prog="bridge", description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.parse_args(strip_ros_args(args)[1:])

    import rclpy
    from rclpy.exceptions import ParameterException
    from rclpy.executors import ExternalShutdownException

    from mds_ach.robot import access as channel_access
    from mds_ach_bridge.node import BridgeNode

    channel_access.enforce_in_this_process()  # a node of the stack: refuse channel files another user planted

    # The state thread must get the GIL back quickly when a frame arrives while a callback runs
    # (the default switch interval is 5 ms, longer than the whole latency budget).
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    rclpy.init(args=args)
    node: BridgeNode | None = None
    try:
        node = BridgeNode()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (ValueError, OSError, ParameterException) as exc:  # bad parameters, configuration or files: say what
        print(f"bridge: {exc}", file=sys.stderr)
        return 2
    finally:
        if node is not None:
            node.close()
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
