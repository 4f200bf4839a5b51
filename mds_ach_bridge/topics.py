"""Topic names of the bridge: all relative, so a namespace (``mds-ach start --namespace``) or a remap moves them."""

from __future__ import annotations

from mds_ach.nodes.status_msgs import DIAGNOSTICS_TOPIC
from mds_ach.robot import joints

JOINT_STATES = "joint_states"  # sensor_msgs/JointState, measured positions, one message per mds-state frame
JOINT_REFERENCES = "mds/joint_references"  # sensor_msgs/JointState, the daemon's reference (state.ref)
JOINT_COMMAND = "mds/joint_command"  # sensor_msgs/JointState in: position commands by joint name
JOINT_TRAJECTORY = "mds/joint_trajectory"  # trajectory_msgs/JointTrajectory in
JOINT_POSITIONS = "mds/joint_positions"  # std_msgs/Float64MultiArray in: one value per MODEL_JOINTS entry
IK_LEFT = "mds/ik/left"  # geometry_msgs/PoseStamped in: left hand target -> mds-ik
IK_RIGHT = "mds/ik/right"  # geometry_msgs/PoseStamped in: right hand target -> mds-ik
COMMAND_STATUS = "mds/command_status"  # mds_ach_interfaces/CommandStatus out: one per command event (accepted, ...)
HOLD_SERVICE = "mds/hold"  # std_srvs/Trigger: hold every joint (through the mux), stop the bridge's trajectory
RESUME_SERVICE = "mds/resume"  # std_srvs/Trigger: release held joints (a stopped trajectory is not restarted)
ROBOT_DESCRIPTION = "robot_description"  # std_msgs/String, transient local: the URDF
DIAGNOSTICS = DIAGNOSTICS_TOPIC  # diagnostic_msgs/DiagnosticArray ("diagnostics": /diagnostics outside a namespace)

FOLLOW_JOINT_TRAJECTORY = "follow_joint_trajectory"
"""control_msgs/action/FollowJointTrajectory at ``<controller>/follow_joint_trajectory``, for MoveIt."""
CONTROLLERS: dict[str, tuple[str, ...]] = {
    "left_arm_controller": joints.LEFT_ARM,
    "right_arm_controller": joints.RIGHT_ARM,
    "head_controller": joints.TORSO + joints.NECK,
}
"""Controller name -> its joints, as config/moveit_controllers.yaml tells MoveIt's simple controller manager."""
CONTROLLER_STATE = "controller_state"
"""control_msgs/JointTrajectoryControllerState at ``<controller>/controller_state``, one per state frame."""
CONTROLLER_TRAJECTORY = "joint_trajectory"
"""trajectory_msgs/JointTrajectory in at ``<controller>/joint_trajectory`` (the controller's joints only)."""
QUERY_STATE = "query_state"
"""control_msgs/srv/QueryTrajectoryState at ``<controller>/query_state``."""
