"""``MDS_MUX_STATE``: the joint mux's ownership report on ``mds-mux-state`` (new; not in the original).

Here rather than in :mod:`mds_ach.nodes.mux` because it is a wire contract: the console, ``mds-ach dump``, the
launcher and C clients (``include/mds.h``) read it without importing the node.
"""

from __future__ import annotations

import ctypes

from mds_ach.robot.msgs.legacy import MDS_JOINT_COUNT, Name30, _Packed, get_name

MUX_MAX_CONTROLLERS = 8
"""Controllers one mux serves at most (the length of the per-controller arrays)."""
MUX_NO_OWNER = -1
"""``owner[address]`` of a joint nobody owns (the mux holds its last value)."""

# held[address]
MUX_FREE = 0
"""The joint follows its output (``mds-ref-mux``)."""
MUX_HELD = 1
"""HOLD: the filter brakes the joint to rest and keeps it there until RESUME or a new command for it."""
MUX_CANCELLED = 2
"""CANCEL: held like HOLD, but RESUME does not release it; once it rests, its output becomes where it rests."""

# verdict[i]: what the mux did with controller i's newest frame
VERDICT_NONE = 0
"""No frame yet, or the frame changed nothing (an unchanged re-send)."""
VERDICT_APPLIED = 1
"""Every modified joint of the frame was taken (the frame is now the output for them)."""
VERDICT_OWNED = 2
"""Refused as a whole: a fresher, higher-priority controller (``blocker[i]``) owns one of its joints."""
VERDICT_NOT_PERMITTED = 3
"""Refused as a whole: it modifies joints the controller may not move (config/mux.yaml ``joints``)."""
VERDICT_INVALID = 4
"""Refused as a whole: NaN/Inf in a known joint, or (inputs that validate before sending: ``ros``, ``ik``) a
modified joint outside the effective limits (mds-limits)."""
VERDICT_CLAMPED = 5
"""Applied, but values outside the effective limits were clamped to them (legacy inputs, config/mux.yaml
``legacy: true``, as the original hardware stopped at its limits): ``clamped[address]`` bit i names the joints,
``blocked_joint[i]`` the first of them."""
VERDICT_NAMES: dict[int, str] = {VERDICT_NONE: "none", VERDICT_APPLIED: "applied", VERDICT_OWNED: "owned",
                                 VERDICT_NOT_PERMITTED: "not permitted", VERDICT_INVALID: "invalid",
                                 VERDICT_CLAMPED: "clamped"}

# hold_status: the mux's answer to the newest mds-hold request
MUX_HOLD_DONE = 0
MUX_HOLD_REFUSED = 1
"""The request was refused, ``hold_reason`` says why (``check_hold``, ``check_cancel``); nothing changed."""
MUX_HOLD_REASON_SIZE = 120
"""Bytes of ``hold_reason`` (NUL-terminated ASCII, cut to fit)."""


class MDS_MUX_STATE(_Packed):  # noqa: N801 - MDS struct naming
    """``mds-mux-state`` frame (packed, 920 B): who owns each joint, how fresh each controller is, what
    was held and what each controller's newest frame got.

    owner[address]     controller index (into name[]) that owns the joint, -1 = nobody (holding)
    count              number of configured controllers (<= 8)
    priority[i]        controller priority (higher wins)
    stale[i]           1 when the controller is stale (no change within its timeout) or never sent
    age[i]             s since the controller's last frame, -1 = never
    change_age[i]      s since its last frame that changed a joint, -1 = never
    name[i]            controller name, char[30]
    time               CLOCK_MONOTONIC at publish
    seq                publish counter
    --- appended with the command lifecycle (issue 17); the fields above keep their offsets ---
    held[address]      MUX_FREE / MUX_HELD / MUX_CANCELLED
    hold_seq           seq of the newest mds-hold request handled (the acknowledgement), 0 = none yet
    hold_action        its action (HOLD_HOLD / HOLD_RESUME / HOLD_CANCEL)
    hold_status        MUX_HOLD_DONE, or MUX_HOLD_REFUSED (see hold_reason)
    hold_source        its source, char[30]
    verdict[i]         what the mux did with controller i's newest frame (VERDICT_*)
    blocker[i]         VERDICT_OWNED: index of the owning controller, else -1
    blocked_joint[i]   the first joint (address) that made the frame refused, -1 = none
    refused[i]         frames of controller i refused since the mux started
    --- appended with issue 25 ---
    hold_reason        why the newest mds-hold request was refused (MUX_HOLD_REFUSED), else empty
    --- appended with issue 26 ---
    clamped[address]   bit i set: controller i's newest applied frame was clamped to the limits at this joint
                       (VERDICT_CLAMPED); 0 = no controller's
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
        ("held", ctypes.c_uint8 * MDS_JOINT_COUNT),
        ("hold_seq", ctypes.c_uint32),
        ("hold_action", ctypes.c_int16),
        ("hold_status", ctypes.c_int16),
        ("hold_source", Name30),
        ("verdict", ctypes.c_int8 * MUX_MAX_CONTROLLERS),
        ("blocker", ctypes.c_int8 * MUX_MAX_CONTROLLERS),
        ("blocked_joint", ctypes.c_int8 * MUX_MAX_CONTROLLERS),
        ("refused", ctypes.c_uint32 * MUX_MAX_CONTROLLERS),
        ("hold_reason", ctypes.c_char * MUX_HOLD_REASON_SIZE),
        ("clamped", ctypes.c_uint8 * MDS_JOINT_COUNT),
    ]

    def controller_names(self) -> list[str]:
        """``name[0:count]`` as text; ``count`` clamped to the array (a scribbled frame never reads past it)."""
        return [get_name(bytes(self.name[i])) for i in range(max(0, min(int(self.count), MUX_MAX_CONTROLLERS)))]

    def clamped_joints(self, i: int) -> list[int]:
        """Addresses where controller ``i``'s newest applied frame was clamped to the limits."""
        return [a for a in range(MDS_JOINT_COUNT) if self.clamped[a] >> i & 1] if 0 <= i < MUX_MAX_CONTROLLERS else []

    def controller_index(self, controller: str) -> int | None:
        """Index of ``controller`` in ``name[]``, None when the mux does not have it."""
        names = self.controller_names()
        return names.index(controller) if controller in names else None
