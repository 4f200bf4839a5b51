"""Position limits for the joints the bridge accepts commands for: the effective limits.

The one limit authority (``mds_ach.kinematics.limits``, issue #17): URDF ``<limit>`` intersected with the
active joint table, read from ``mds-limits`` when the daemon published them. So the bridge refuses exactly what
the mux, the gate and the daemon would refuse or clamp, and says so at once. Disabled joints are left out: a
command for them is refused instead of being silently ignored downstream.
"""

from __future__ import annotations

from mds_ach.kinematics.limits import EffectiveLimits, current_limits
from mds_ach.robot import config, joints

Limits = dict[str, tuple[float, float]]


def load_limits(names: tuple[str, ...] = joints.MODEL_JOINTS, robot: str | None = None,
                effective: EffectiveLimits | None = None) -> Limits:
    """``{short name: (lower, upper)}`` in rad for the enabled joints among ``names``."""
    effective = current_limits(robot) if effective is None else effective
    table = config.load(effective.robot)
    return {n: rng for n, rng in effective.by_short(names).items() if table[n].enabled}
