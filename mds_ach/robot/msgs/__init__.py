"""Every wire struct on an MDS channel: packed little-endian ctypes layouts, one module per family.

* :mod:`.legacy` -- the original ``mds.h`` structs (``MDS_REF``, ``MDS_STATE``, ``MDS_JOINT_PARAM``, ``MDS_IK``,
  ``MDS_COLLIDE``) and ``MDS_CMD``, with the char[30] name helpers;
* :mod:`.ik_status` -- ``MDS_IK_STATUS`` (``mds-ik-state``), the IK node's answers;
* :mod:`.mux_state` -- ``MDS_MUX_STATE`` (``mds-mux-state``), the mux's joint owners;
* :mod:`.hold` -- ``MDS_HOLD`` (``mds-hold``), hold / resume / cancel requests to the mux;
* :mod:`.limits` -- ``MDS_LIMITS`` (``mds-limits``), the effective joint limits (the one limit authority);
* :mod:`.daemon_status` -- ``MDS_DAEMON_STATUS`` (``mds-daemon-status``), the daemon's health.

Which channel carries which struct is :mod:`mds_ach.robot.contracts`; ``include/mds.h`` is generated from both.
Stdlib + ctypes only: C-like clients read these without numpy or rclpy.
"""

from __future__ import annotations

from mds_ach.robot.msgs.daemon_status import MDS_DAEMON_STATUS
from mds_ach.robot.msgs.hold import MDS_HOLD
from mds_ach.robot.msgs.ik_status import MDS_IK_STATUS
from mds_ach.robot.msgs.legacy import (
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
    Name30,
    _Packed,
    get_name,
    set_name,
    set_padded,
)
from mds_ach.robot.msgs.limits import MDS_LIMITS
from mds_ach.robot.msgs.mux_state import MDS_MUX_STATE

Packed = _Packed
"""Base class of every wire struct (public spelling of ``_Packed``)."""

__all__ = [
    "MDS_ARM_COUNT",
    "MDS_CHAR_PARAM_BUFFER_SIZE",
    "MDS_CMD",
    "MDS_COLLIDE",
    "MDS_COLLIDE_JNT_NUM",
    "MDS_DAEMON_STATUS",
    "MDS_HOLD",
    "MDS_IK",
    "MDS_IK_ARM",
    "MDS_IK_STATUS",
    "MDS_JNT_COLLIDE",
    "MDS_JNT_PARAM",
    "MDS_JOINT_COUNT",
    "MDS_JOINT_PARAM",
    "MDS_JOINT_REF",
    "MDS_JOINT_STATE",
    "MDS_LIMITS",
    "MDS_MUX_STATE",
    "MDS_POWER",
    "MDS_REF",
    "MDS_STATE",
    "Name30",
    "Packed",
    "get_name",
    "set_name",
    "set_padded",
]
