"""``bridge`` (= ``ros2 run mds_ach bridge``): the ROS 2 bridge's command line.

rclpy is imported only after the arguments are parsed, so ``--help`` is instant; the rest of ``main`` (rclpy
start-up, signals, exit status 2 for bad parameters) is the nodes' shared ``mds_ach.nodes.rosnode.run_node``.
"""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

import mds_ach as mds
from mds_ach.nodes.pipeline import HANDOFF_RT_PRIORITY
from mds_ach.nodes.rosnode import run_node
from mds_ach.robot import joints
from mds_ach_bridge import topics

if TYPE_CHECKING:
    from mds_ach_bridge.node import BridgeNode

DESCRIPTION = f"""\
ROS 2 bridge for MDS-Ach. Every new {mds.MDS_CHAN_STATE_NAME} frame is published at once as
sensor_msgs/JointState on {topics.JOINT_STATES} (measured positions) and {topics.JOINT_REFERENCES}
(the daemon's reference), stamped with the frame's publish time. Commands from ROS are checked against
the joint limits (all or nothing; rejections are logged with the reason) and written to the bridge's
reference channel ({mds.MDS_CHAN_REF_ROS_NAME}, the bridge's mux input) once per state cycle.
"""

ACTIONS = "\n".join(f"  {c + '/' + topics.FOLLOW_JOINT_TRAJECTORY:<46} {' '.join(j)}"
                    for c, j in topics.CONTROLLERS.items())

EPILOG = f"""\
topics (relative: remap with --ros-args -r old:=new, or move with -r __ns:=/robot):
  {topics.JOINT_STATES:<24} out  sensor_msgs/JointState      measured positions, velocities (finite
                                   differences over the frames' stamps); reliable unless state_qos:=sensor_data
  {topics.JOINT_REFERENCES:<24} out  sensor_msgs/JointState      the daemon's reference (state.ref)
  {topics.ROBOT_DESCRIPTION:<24} out  std_msgs/String             the URDF (transient local)
  {topics.DIAGNOSTICS:<24} out  diagnostic_msgs/DiagnosticArray  stream health, command counters
  {topics.COMMAND_STATUS:<24} out  mds_ach_interfaces/CommandStatus  one per command event (accepted,
                                   rejected, refused by the mux + owner, stopped, finished, goal ends)
  {topics.JOINT_COMMAND:<24} in   sensor_msgs/JointState      positions by joint name
  {topics.JOINT_POSITIONS:<24} in   std_msgs/Float64MultiArray  {len(joints.MODEL_JOINTS)} positions in this order:
                                   {' '.join(joints.MODEL_JOINTS)}
  {topics.JOINT_TRAJECTORY:<24} in   trajectory_msgs/JointTrajectory  sampled on every state cycle
  {topics.IK_LEFT:<24} in   geometry_msgs/PoseStamped   left hand target -> {mds.MDS_CHAN_IK_NAME}
  {topics.IK_RIGHT:<24} in   geometry_msgs/PoseStamped   right hand target -> {mds.MDS_CHAN_IK_NAME}
services:
  {topics.HOLD_SERVICE:<24} std_srvs/Trigger  hold every joint (mux); stops the bridge's trajectory for good
  {topics.RESUME_SERVICE:<24} std_srvs/Trigger  release held joints; a stopped trajectory is not restarted
actions (control_msgs/action/FollowJointTrajectory, for MoveIt: config/moveit_controllers.yaml):
{ACTIONS}
  and per controller, as joint_trajectory_controller: <controller>/{topics.CONTROLLER_STATE} (out, one per state
  frame), <controller>/{topics.CONTROLLER_TRAJECTORY} (in), <controller>/{topics.QUERY_STATE} (service)
A frame the mux refuses (another controller owns a joint) is logged once with the owner; a trajectory that
is refused, held, aborted or preempted stops and its joints are cancelled where they are.
IK targets are in the robot frame (frame_id '' or 'torso': between the shoulders, x forward, y left,
z up); the task DOF per arm are the parameters ik_dof_left / ik_dof_right (a prefix of
p-x p-y p-z t-x t-y t-z: 3 = position only, 6 = full pose).

parameters (--ros-args -p name:=value; `ros2 param describe` shows every one):
  state_channel, ref_channel, ik_channel, allow_ungated, state_qos (reliable|sensor_data),
  joint_trajectory_controller's (mds_ach_bridge/README.md): allow_partial_joints_goal,
  allow_nonzero_velocity_at_trajectory_end, constraints.stopped_velocity_tolerance, constraints.goal_time,
  constraints.<joint>.trajectory, constraints.<joint>.goal,
  stale_timeout, max_state_age, command_mode, trajectory_mode,
  ik_dof_left, ik_dof_right, ik_frame, urdf, robot, publish_robot_description, publish_tf,
  diagnostics_period,
  rt_priority (SCHED_FIFO priority of the state thread, 0 = normal)

examples:
  bridge
  bridge --ros-args -p ref_channel:=mds-ref-filter      # no mux running: write the legacy input
  bridge --ros-args -r __ns:=/mds1 -p state_qos:=sensor_data
  bridge --ros-args -p rt_priority:=50                  # real-time state thread (root or rtprio limit)
"""


SWITCH_INTERVAL_S = 0.0005


def build_parser() -> argparse.ArgumentParser:
    return argparse.ArgumentParser(prog="bridge", description=DESCRIPTION, epilog=EPILOG,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)


def _make_node(args: argparse.Namespace) -> BridgeNode:
    # Imported here, after the command line was parsed: `bridge --help` must not load rclpy (see rosnode);
    # the node module costs ~190 ms (rclpy, messages; measured with -X importtime) against ~60 ms for bridge.
    from mds_ach_bridge.node import BridgeNode

    # The state thread must get the GIL back quickly when a frame arrives while a callback runs
    # (the default switch interval is 5 ms, longer than the whole latency budget).
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    return BridgeNode()


def main(argv: list[str] | None = None) -> int:
    """``argv`` without the program name (``sys.argv[1:]`` when None)."""
    # The executor thread and the DDS reception threads hand a command over like the pipeline's hand-off threads:
    # at normal priority a busy machine stretched a ROS command's p99 to 30+ ms (docs/reliability.md E).
    return run_node([sys.argv[0], *(sys.argv[1:] if argv is None else argv)], build_parser(), _make_node,
                    rt_priority=HANDOFF_RT_PRIORITY)


if __name__ == "__main__":
    raise SystemExit(main())
