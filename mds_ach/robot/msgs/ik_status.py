"""``mds-ik-state``: the IK node's answer to each ``mds-ik`` request (new; the original printed to its console).

One ``MDS_IK_STATUS`` frame per handled request, also published on the ROS topic ``mds/ik_status``
(``mds_ach_interfaces/msg/IkStatus``, made from ``status_to_dict``). Stdlib + ctypes only, so clients (console,
viewer, C code) read it without rclpy or numpy.
"""

from __future__ import annotations

import ctypes
import math
from typing import Any

from mds_ach.robot.msgs.legacy import _Packed

IK_SOLVED = 0  # solution written to the node's output channel
IK_UNREACHABLE = 1  # no solution within the iteration cap (or every one collided); nothing moved
IK_BAD_REQUEST = 2  # refused: move not 0/1, ik_method not 1..6, NaN/Inf target; nothing moved
IK_NOT_READY = 3  # no current reference to start from (is the daemon running?); nothing moved
IK_NOT_APPLIED = 4  # solved, but the mux refused the whole solution (another controller owns a joint); nothing moved
IK_STOPPED_AT_CONTACT = 5  # a second answer (same seq) to a solved request: the gate stopped the arm at contact
STATUS_NAMES: dict[int, str] = {IK_SOLVED: "solved", IK_UNREACHABLE: "unreachable", IK_BAD_REQUEST: "bad request",
                                IK_NOT_READY: "not ready", IK_NOT_APPLIED: "not applied",
                                IK_STOPPED_AT_CONTACT: "stopped at contact"}
IK_MESSAGE_SIZE = 80
# A readiness probe (the launcher's): an MDS_IK with move = IK_PROBE_MOVE. Refused like any move that names no arm
# (IK_BAD_REQUEST, nothing moves) with PROBE_ANSWER as its message, and logged as a probe, not as a warning.
IK_PROBE_MOVE = -1
PROBE_ANSWER = "probe answered: the IK node is up; nothing moved"
IK_STATUS_TOPIC = "mds/ik_status"  # relative: a namespace moves it


class MDS_IK_STATUS(_Packed):  # noqa: N801 - MDS struct naming
    """``mds-ik-state`` frame (packed, 214 B).

    seq          count of requests handled since the node started (1 = first; a follow-up repeats its request's)
    status       IK_SOLVED / IK_UNREACHABLE / IK_BAD_REQUEST / IK_NOT_READY / IK_NOT_APPLIED /
                 IK_STOPPED_AT_CONTACT (follow-up): a second frame for a solved request, when the collision gate
                 stopped that arm at contact (message "stopped at contact: right hand / left hand"; the command is
                 cancelled, the arm holds there)
    arm          0 right, 1 left (as ``MDS_IK.move``; -1 if the request named no valid arm)
    dof          task DOF (``ik_method``), components x, y, z, roll, pitch, yaw in that order
    iterations   solver iterations used
    error        task error at ``q`` (m and rad mixed, like the tolerance)
    solve_time   s spent solving
    target[6]    the request's t_x, t_y, t_z, r_x, r_y, r_z as received
    q[6]         joint solution [SP, SR, SY, EP, WY, WR] in rad; on failure the best attempt (not applied)
    stamp        CLOCK_MONOTONIC s when the answer was published
    message      short human-readable explanation, NUL-terminated ASCII
    """

    _fields_ = [
        ("seq", ctypes.c_uint32),
        ("status", ctypes.c_int16),
        ("arm", ctypes.c_int16),
        ("dof", ctypes.c_int16),
        ("iterations", ctypes.c_int32),
        ("error", ctypes.c_double),
        ("solve_time", ctypes.c_double),
        ("target", ctypes.c_double * 6),
        ("q", ctypes.c_double * 6),
        ("stamp", ctypes.c_double),
        ("message", ctypes.c_char * IK_MESSAGE_SIZE),
    ]


def set_message(status: MDS_IK_STATUS, text: str) -> None:
    """Store ``text`` (ASCII, truncated to fit with its NUL)."""
    status.message = text.encode("ascii", "replace")[: IK_MESSAGE_SIZE - 1]


def get_message(status: MDS_IK_STATUS) -> str:
    """The message text up to its NUL."""
    return bytes(status.message).split(b"\0", 1)[0].decode("ascii", "replace")


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None  # JSON has no NaN/Inf


def status_to_dict(status: MDS_IK_STATUS) -> dict[str, Any]:
    """JSON-friendly view of a status frame (the ROS topic's payload)."""
    return {
        "seq": int(status.seq),
        "status": int(status.status),
        "status_name": STATUS_NAMES.get(int(status.status), "unknown"),
        "arm": {0: "right", 1: "left"}.get(int(status.arm), "none"),
        "dof": int(status.dof),
        "iterations": int(status.iterations),
        "error": _num(status.error),
        "solve_time": _num(status.solve_time),
        "target": [_num(v) for v in status.target],
        "q": [_num(v) for v in status.q],
        "stamp": float(status.stamp),
        "message": get_message(status),
    }
