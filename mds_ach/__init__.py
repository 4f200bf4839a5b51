"""mds_ach: ROS 2 Jazzy + Ach-compatible middleware for the Xitome MDS humanoid upper body.

``import mds_ach as mds`` gives the legacy constants, channel names, struct layouts and the joint table,
like the original ``mds_ach.py`` did. Heavy modules (torch, fcl, rclpy) are never imported from here.
"""

from __future__ import annotations

import os

# One BLAS thread (before anything imports numpy): OpenBLAS's worker threads take process-directed signals from the
# main thread (a console blocked in readline then missed Ctrl-C and SIGTERM) and add jitter to the real-time loops;
# the matrices here are 6x6. A value the user set wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
del _var

from mds_ach.robot import joints, msgs  # noqa: F401  (mds.joints, mds.msgs: public before the sub-packages)

# Channel names and geometry are declared once, with their structs and rules, in mds_ach.robot.contracts.
from mds_ach.robot.contracts import (
    ALL_CHANNELS,
    CHANNEL_FRAME_COUNT,
    CHANNEL_FRAME_SIZE,
    LEGACY_CHANNELS,
    MDS_CHAN_BOARD_CMD_NAME,
    MDS_CHAN_COLLIDE_NAME,
    MDS_CHAN_DAEMON_INPUT_NAME,
    MDS_CHAN_DAEMON_STATUS_NAME,
    MDS_CHAN_HOLD_NAME,
    MDS_CHAN_IK_NAME,
    MDS_CHAN_IK_STATE_NAME,
    MDS_CHAN_LIMITS_NAME,
    MDS_CHAN_MUX_STATE_NAME,
    MDS_CHAN_PARAM_NAME,
    MDS_CHAN_REF_FILTER_NAME,
    MDS_CHAN_REF_GATED_NAME,
    MDS_CHAN_REF_IK_NAME,
    MDS_CHAN_REF_MUX_NAME,
    MDS_CHAN_REF_NAME,
    MDS_CHAN_REF_ROS_NAME,
    MDS_CHAN_REF_SMOOTH_NAME,
    MDS_CHAN_STATE_NAME,
    PIPELINE_CHANNELS,
)
from mds_ach.robot.joints import BY_ADDRESS, BY_NAME, BY_SHORT, JOINTS, Joint, getAddress, lookup
from mds_ach.robot.legacy_names import (
    COLLISION_L_ELBOW,
    COLLISION_L_FOREARM,
    COLLISION_L_HAND,
    COLLISION_L_SHOULDER,
    COLLISION_L_WRIST,
    COLLISION_R_ELBOW,
    COLLISION_R_FOREARM,
    COLLISION_R_HAND,
    COLLISION_R_SHOULDER,
    COLLISION_R_WRIST,
    FALSE,
    IK1,
    IK2,
    IK3,
    IK4,
    IK5,
    IK6,
    MAX_EFF,
    MAX_SAFE_STACK,
    MDS_CAN_BUFFER_CLEAR_I,
    MDS_CAN_CHAN_NUM,
    MDS_CAN_TIMEOUT_DEFAULT,
    MDS_CHAN_CAN_DAEMON_NAME,
    MDS_CHAN_COLLLIDE_NAME,
    MDS_CHAN_VIRTUAL_FROM_SIM_NAME,
    MDS_CHAN_VIRTUAL_TO_SIM_NAME,
    MDS_STARTUP_SEND_REF_DELAY,
    RIGTH,
    TRUE,
    getAddressOnly,
    getNameAndAddress,
    getNameShort,
    hubo_era_constants,
    p2f,
    str2ubytes,
    ubytes2str,
)
from mds_ach.robot.msgs import (
    MDS_ARM_COUNT,
    MDS_CHAR_PARAM_BUFFER_SIZE,
    MDS_CMD,
    MDS_COLLIDE,
    MDS_COLLIDE_JNT_NUM,
    MDS_IK,
    MDS_IK_ARM,
    MDS_JNT_COLLIDE,
    MDS_JNT_PARAM,
    MDS_JOINT_COUNT,
    MDS_JOINT_PARAM,
    MDS_JOINT_REF,
    MDS_JOINT_STATE,
    MDS_POWER,
    MDS_REF,
    MDS_STATE,
)
from mds_ach.robot.msgs.legacy import (
    MDS_REF_MODE_COMPLIANT,
    MDS_REF_MODE_ENC_FILTER,
    MDS_REF_MODE_REF,
    MDS_REF_MODE_REF_FILTER,
)

__version__ = "0.1.0"

# --- arms and modes -----------------------------------------------------------------------------
RIGHT = 0
LEFT = 1

# --- mds_collide_t part indices -----------------------------------------------------------------
COLLIDE_L_HAND = 0
COLLIDE_R_HAND = 1
COLLIDE_R_SHOULDER = 2
COLLIDE_L_SHOULDER = 3
COLLIDE_R_FOREARM = 4
COLLIDE_L_FOREARM = 5
COLLIDE_R_ELBOW = 6
COLLIDE_L_ELBOW = 7
COLLIDE_R_WRIST = 8
COLLIDE_L_WRIST = 9
COLLIDE_PART_NAMES: tuple[str, ...] = (
    "L_HAND",
    "R_HAND",
    "R_SHOULDER",
    "L_SHOULDER",
    "R_FOREARM",
    "L_FOREARM",
    "R_ELBOW",
    "L_ELBOW",
    "R_WRIST",
    "L_WRIST",
)

# --- timing constants (mds.h) ---------------------------------------------------------------------
MDS_LOOP_PERIOD = 0.1
MDS_REF_FILTER_LENGTH = 40

# --- mds-cmd commands (new) -----------------------------------------------------------------------
MDS_CMD_ENABLE = 1
MDS_CMD_DISABLE = 2
MDS_CMD_HOME = 3
MDS_CMD_RESET = 4
MDS_CMD_ZERO_ENCODER = 5
MDS_CMD_RESET_BUS = 6
MDS_CMD_MODE = 7  # value 1: collaborative mode (hands/elbows <= the Cartesian bound), 0: normal
MDS_CMD_ESTOP = 8  # category-1 e-stop: brake at the bounds, then DISABLE every drive; latched
MDS_CMD_ESTOP_RESET = 9  # the operator's reset of a latched e-stop (the drives stay disabled until ENABLE)


def _export_joint_constants() -> None:
    """Legacy ``mds.LSP == 0x5f`` style constants for every short and long joint name."""
    g = globals()
    for j in JOINTS:
        g[j.short] = j.address
        g[j.name] = j.address


_export_joint_constants()
# The original mds_ach.py's Hubo-era joint names (LEB, NYH, ...): see mds_ach.robot.legacy_names.
globals().update(hubo_era_constants())

# Every channel this process opens (clients: the tools, this legacy API, the examples) must be owned by root,
# this user or the stack's user; symlinks and non-regular files are refused in the ach layer itself.
from mds_ach.robot import access as _access  # noqa: E402  (after the constants: access imports this package)

_access.install_client_rule()

__all__ = [
    "ALL_CHANNELS",
    "CHANNEL_FRAME_COUNT",
    "CHANNEL_FRAME_SIZE",
    "LEGACY_CHANNELS",
    "PIPELINE_CHANNELS",
    "MDS_CHAN_BOARD_CMD_NAME",
    "MDS_CHAN_COLLIDE_NAME",
    "MDS_CHAN_DAEMON_INPUT_NAME",
    "MDS_CHAN_DAEMON_STATUS_NAME",
    "MDS_CHAN_IK_NAME",
    "MDS_CHAN_IK_STATE_NAME",
    "MDS_CHAN_MUX_STATE_NAME",
    "MDS_CHAN_HOLD_NAME",
    "MDS_CHAN_LIMITS_NAME",
    "MDS_CHAN_PARAM_NAME",
    "MDS_CHAN_REF_FILTER_NAME",
    "MDS_CHAN_REF_GATED_NAME",
    "MDS_CHAN_REF_IK_NAME",
    "MDS_CHAN_REF_MUX_NAME",
    "MDS_CHAN_REF_NAME",
    "MDS_CHAN_REF_ROS_NAME",
    "MDS_CHAN_REF_SMOOTH_NAME",
    "MDS_CHAN_STATE_NAME",
    "MDS_REF_MODE_COMPLIANT",
    "MDS_REF_MODE_ENC_FILTER",
    "MDS_REF_MODE_REF",
    "MDS_REF_MODE_REF_FILTER",
    "BY_ADDRESS",
    "BY_NAME",
    "BY_SHORT",
    "JOINTS",
    "Joint",
    "getAddress",
    "getAddressOnly",
    "getNameAndAddress",
    "getNameShort",
    "p2f",
    "str2ubytes",
    "ubytes2str",
    "lookup",
    "MDS_ARM_COUNT",
    "MDS_CHAR_PARAM_BUFFER_SIZE",
    "MDS_CMD",
    "MDS_COLLIDE",
    "MDS_COLLIDE_JNT_NUM",
    "MDS_IK",
    "MDS_IK_ARM",
    "MDS_JNT_COLLIDE",
    "MDS_JNT_PARAM",
    "MDS_JOINT_COUNT",
    "MDS_JOINT_PARAM",
    "MDS_JOINT_REF",
    "MDS_JOINT_STATE",
    "MDS_POWER",
    "MDS_REF",
    "MDS_STATE",
    # the original mds_ach.py's constants (mds_ach.robot.legacy_names)
    "COLLISION_L_ELBOW",
    "COLLISION_L_FOREARM",
    "COLLISION_L_HAND",
    "COLLISION_L_SHOULDER",
    "COLLISION_L_WRIST",
    "COLLISION_R_ELBOW",
    "COLLISION_R_FOREARM",
    "COLLISION_R_HAND",
    "COLLISION_R_SHOULDER",
    "COLLISION_R_WRIST",
    "FALSE",
    "IK1",
    "IK2",
    "IK3",
    "IK4",
    "IK5",
    "IK6",
    "MAX_EFF",
    "MAX_SAFE_STACK",
    "MDS_CAN_BUFFER_CLEAR_I",
    "MDS_CAN_CHAN_NUM",
    "MDS_CAN_TIMEOUT_DEFAULT",
    "MDS_CHAN_CAN_DAEMON_NAME",
    "MDS_CHAN_COLLLIDE_NAME",
    "MDS_CHAN_VIRTUAL_FROM_SIM_NAME",
    "MDS_CHAN_VIRTUAL_TO_SIM_NAME",
    "MDS_STARTUP_SEND_REF_DELAY",
    "RIGTH",
    "TRUE",
]
