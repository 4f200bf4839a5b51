"""Validation of joint position commands from ROS: all or nothing, with a reason a user can act on.

Every function returns a new ``{short name: position}`` dict or raises :class:`CommandError`; nothing
here touches a channel, so a rejected message can never be partly applied.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from mds_ach.robot import joints
from mds_ach_bridge.limits import Limits


class CommandError(ValueError):
    """A command that must not be applied; ``str()`` says why."""


def _unknown(name: str, limits: Limits) -> CommandError:
    why = "is disabled in the joint table" if name in joints.BY_SHORT else "is not an MDS joint name"
    return CommandError(f"joint {name!r} {why}; accepted joints: {' '.join(limits)}")


def check_value(name: str, value: float, limits: Limits) -> float:
    """One joint position: known joint, finite, inside its limits."""
    if name not in limits:
        raise _unknown(name, limits)
    v = float(value)
    if not math.isfinite(v):
        raise CommandError(f"{name}: position {v} is not finite")
    lower, upper = limits[name]
    if not lower <= v <= upper:
        raise CommandError(f"{name}: position {v:.6g} rad is outside the limits [{lower:.6g}, {upper:.6g}]")
    return v


def check_names(names: Sequence[str], limits: Limits) -> tuple[str, ...]:
    """Joint names of a command: not empty, no duplicates, all commandable."""
    if len(names) == 0:
        raise CommandError("no joint names")
    seen: set[str] = set()
    for n in names:
        if n in seen:
            raise CommandError(f"joint {n!r} appears twice")
        if n not in limits:
            raise _unknown(n, limits)
        seen.add(n)
    return tuple(names)


def positions_by_name(names: Sequence[str], positions: Sequence[float], limits: Limits) -> dict[str, float]:
    """A ``sensor_msgs/JointState`` command: ``name[i]`` goes to ``position[i]``."""
    check_names(names, limits)
    if len(positions) != len(names):
        raise CommandError(f"{len(names)} joint names but {len(positions)} positions")
    return {n: check_value(n, p, limits) for n, p in zip(names, positions, strict=True)}


def positions_from_array(values: Sequence[float], limits: Limits,
                         order: Sequence[str] = joints.MODEL_JOINTS) -> dict[str, float]:  # fmt: skip
    """A ``std_msgs/Float64MultiArray`` command: one value per joint of ``order`` (MODEL_JOINTS)."""
    if len(values) != len(order):
        raise CommandError(f"expected {len(order)} values in the order {' '.join(order)}, got {len(values)}")
    return {n: check_value(n, v, limits) for n, v in zip(order, values, strict=True)}
