"""ROS pose targets -> legacy ``MDS_IK`` requests for the IK node on ``mds-ik``.

``mds_ik_t`` carries one target per arm (x, y, z in metres, then t_x, t_y, t_z in radians) and
``ik_method`` = the number of task DOF, always a prefix of ``p-x p-y p-z t-x t-y t-z``: 3 is
position only, 6 the full pose. The angles are the roll/pitch/yaw of a Z-Y-X (yaw-pitch-roll) Euler
decomposition, as the original IK module extracts them from the rotation matrix.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import mds_ach as mds
from mds_ach.robot.msgs import MDS_IK
from mds_ach_bridge.commands import CommandError

ARMS: dict[str, int] = {"left": mds.LEFT, "right": mds.RIGHT}


def quaternion_to_rpy(x: float, y: float, z: float, w: float) -> tuple[float, float, float]:
    """Roll (about x), pitch (about y), yaw (about z) with R = Rz(yaw)·Ry(pitch)·Rx(roll)."""
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    sin_pitch = max(-1.0, min(1.0, 2.0 * (w * y - z * x)))
    pitch = math.asin(sin_pitch)
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def make_request(arm: str, position: Sequence[float], orientation: Sequence[float], dof: int) -> MDS_IK:
    """Build the request for one arm; refuses NaN/Inf, a bad quaternion, an unknown arm or dof."""
    if arm not in ARMS:
        raise CommandError(f"unknown arm {arm!r}; use 'left' or 'right'")
    if not 1 <= dof <= 6:
        raise CommandError(f"ik dof {dof} must be 1..6 (a prefix of p-x p-y p-z t-x t-y t-z)")
    if not all(math.isfinite(v) for v in (*position, *orientation)):
        raise CommandError("pose contains NaN or Inf")
    qx, qy, qz, qw = orientation
    norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if abs(norm - 1.0) > 1e-3:
        raise CommandError(f"orientation quaternion has norm {norm:.6g}, expected 1")
    roll, pitch, yaw = quaternion_to_rpy(qx / norm, qy / norm, qz / norm, qw / norm)
    req = MDS_IK()
    a = req.arm[ARMS[arm]]
    a.t_x, a.t_y, a.t_z = (float(v) for v in position)
    a.r_x, a.r_y, a.r_z = roll, pitch, yaw
    a.ik_method = dof
    req.move = ARMS[arm]
    return req
