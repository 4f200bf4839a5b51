"""``MDS_MUX_STATE``: the joint mux's ownership report on ``mds-mux-state`` (new; not in the original).

Here rather than in :mod:`mds_ach.nodes.mux` because it is a wire contract: the console, ``mds-ach dump``, the
launcher and C clients (``include/mds.h``) read it without importing the node.
"""

from __future__ import annotations

import ctypes

from mds_ach.robot.msgs.legacy import MDS_JOINT_COUNT, Name30, _Packed

MUX_MAX_CONTROLLERS = 8
"""Controllers one mux serves at most (the length of the per-controller arrays)."""
MUX_NO_OWNER = -1
"""``owner[address]`` of a joint nobody owns (the mux holds its last value)."""


class MDS_MUX_STATE(_Packed):  # noqa: N801 - MDS struct naming
    """``mds-mux-state`` frame (packed, 506 B): who owns each joint and how fresh each controller is.

    owner[address]     controller index (into name[]) that owns the joint, -1 = nobody (holding)
    count              number of configured controllers (<= 8)
    priority[i]        controller priority (higher wins)
    stale[i]           1 when the controller is stale (no change within its timeout) or never sent
    age[i]             s since the controller's last frame, -1 = never
    change_age[i]      s since its last frame that changed a joint, -1 = never
    name[i]            controller name, char[30]
    time               CLOCK_MONOTONIC at publish
    seq                publish counter
    """

    _fields_ = [
        ("owner", ctypes.c_int8 * MDS_JOINT_COUNT),
        ("count", ctypes.c_int16),
        ("priority", ctypes.c_int16 * MUX_MAX_CONTROLLERS),
        ("stale", ctypes.c_uint8 * MUX_MAX_CONTROLLERS),
        ("age", ctypes.c_double * MUX_MAX_CONTROLLERS),
        ("change_age", ctypes.c_double * MUX_MAX_CONTROLLERS),
        ("name", Name30 * MUX_MAX_CONTROLLERS),
        ("time", ctypes.c_double),
        ("seq", ctypes.c_uint32),
    ]
