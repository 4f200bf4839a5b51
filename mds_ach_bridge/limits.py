"""Position limits for the joints the bridge accepts commands for, from the joint table (mds_ach.robot.config).

The joint table is the daemon's authority (ROM, margin, offset, direction, optional narrower limits per
robot variant), so the bridge refuses exactly what the daemon would have to clamp. Disabled joints are
left out: a command for them is refused instead of being silently ignored downstream.
"""

from __future__ import annotations

from mds_ach.robot import config, joints

Limits = dict[str, tuple[float, float]]


def load_limits(names: tuple[str, ...] = joints.MODEL_JOINTS, robot: str | None = None) -> Limits:
    """``{short name: (lower, upper)}`` in rad for the enabled joints among ``names``."""
    table = config.load(robot)
    return {n: (table[n].lower, table[n].upper) for n in names if table[n].enabled}
