"""``MDS_LIMITS``: the effective joint limits on ``mds-limits`` (new; not in the original).

One limit authority (issue #17): the URDF's ``<limit>`` intersected with the active joint table (robot
variant and calibration chosen by the daemon). The daemon computes them once at start
(``mds_ach.kinematics.limits``) and publishes them here, so every entry point (console, bridge, viewer, IK,
mux, gate, achd) refuses exactly what the daemon would have to clamp. Arrays are indexed by CAN address like
every legacy struct. Stdlib + ctypes only, so C clients read it without numpy or rclpy.

Issue #26 appended what each joint can *follow* (``velocity``, ``acceleration``: what a trajectory planner may
use, the numbers of ``config/joint_limits.yaml``) after ``time``, so the offsets of the first fields are unchanged.
"""

from __future__ import annotations

import ctypes
import math

from mds_ach.robot.msgs.legacy import MDS_JOINT_COUNT, Name30, _Packed

LIMITS_SOURCE_SIZE = 128


class MDS_LIMITS(_Packed):  # noqa: N801 - MDS struct naming
    """``mds-limits`` frame (packed).

    seq              the writer's publication counter (1 for the daemon's start-up frame)
    valid[address]   1 = the joint has limits (every joint of the table); 0 = no such joint
    lower[address]   lowest allowed reference, rad (joint space)
    upper[address]   highest allowed reference, rad
    robot            the joint table's robot variant (default, isaac, ...), char[30]
    source           where the numbers come from (files), NUL-terminated ASCII
    time             CLOCK_MONOTONIC when written
    velocity[address]      the highest speed the joint follows, rad/s (NaN where valid is 0)
    acceleration[address]  the highest acceleration the joint follows, rad/s^2 (NaN where valid is 0)
    """

    _fields_ = [
        ("seq", ctypes.c_uint32),
        ("valid", ctypes.c_uint8 * MDS_JOINT_COUNT),
        ("lower", ctypes.c_double * MDS_JOINT_COUNT),
        ("upper", ctypes.c_double * MDS_JOINT_COUNT),
        ("robot", Name30),
        ("source", ctypes.c_char * LIMITS_SOURCE_SIZE),
        ("time", ctypes.c_double),
        ("velocity", ctypes.c_double * MDS_JOINT_COUNT),
        ("acceleration", ctypes.c_double * MDS_JOINT_COUNT),
    ]


def check_limits(frame: MDS_LIMITS) -> str | None:
    """A 0/1 valid mask; for every valid joint finite ``lower <= upper`` within one turn and a finite velocity and
    acceleration > 0 (a joint that cannot move has no limits: it is not valid)."""
    for address in range(MDS_JOINT_COUNT):
        if frame.valid[address] not in (0, 1):
            return f"valid[{address:#x}] is {frame.valid[address]}, not 0 or 1"
        if not frame.valid[address]:
            continue
        lo, hi = frame.lower[address], frame.upper[address]
        if not (math.isfinite(lo) and math.isfinite(hi)) or abs(lo) > 2 * math.pi or abs(hi) > 2 * math.pi:
            return f"limits [{lo}, {hi}] at address {address:#x} are not finite within one turn"
        if lo > hi:
            return f"empty range [{lo}, {hi}] at address {address:#x}"
        for what, value in (("velocity", frame.velocity[address]), ("acceleration", frame.acceleration[address])):
            if not (math.isfinite(value) and value > 0):
                return f"{what} {value} at address {address:#x} is not finite and > 0"
    return None
