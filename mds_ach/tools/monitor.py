"""Read-only views of a running system, shared by the operator tools (console, read monitor, status): the
channel reader (:class:`mds_ach.ach.watch.Latest`, re-exported) and the formatting of what it reads.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import mds_ach as mds
from mds_ach.ach.watch import Latest  # noqa: F401 - the one read-only channel watcher; the tools import it here
from mds_ach.kinematics.limits import EffectiveLimits
from mds_ach.paths import runtime_dir
from mds_ach.robot.msgs.daemon_status import (
    JOINT_BAD_REPLY,
    JOINT_ENABLED,
    JOINT_FOLLOW_FAULT,
    JOINT_FRESH,
    JOINT_STALE,
    JOINT_UNREFERENCED,
    MDS_DAEMON_STATUS,
    summary_line,
)

# --------------------------------------------------------------------------------------------- formatting


COLLIDE_PARTS: tuple[str, ...] = ("Hand", "Wrist", "Forearm", "Elbow", "Shoulder")
# (right index, left index) of each part in mds_collide_t.joint[]
COLLIDE_INDEX: dict[str, tuple[int, int]] = {
    "Hand": (mds.COLLIDE_R_HAND, mds.COLLIDE_L_HAND),
    "Wrist": (mds.COLLIDE_R_WRIST, mds.COLLIDE_L_WRIST),
    "Forearm": (mds.COLLIDE_R_FOREARM, mds.COLLIDE_L_FOREARM),
    "Elbow": (mds.COLLIDE_R_ELBOW, mds.COLLIDE_L_ELBOW),
    "Shoulder": (mds.COLLIDE_R_SHOULDER, mds.COLLIDE_L_SHOULDER),
}


def collision_parts(collide: mds.MDS_COLLIDE) -> list[str]:
    """Names of the parts flagged in a collide frame, e.g. ['L_HAND', 'R_HAND']."""
    return [mds.COLLIDE_PART_NAMES[i] for i in range(mds.MDS_COLLIDE_JNT_NUM) if collide.joint[i].isCollide]


def collision_summary(collide: mds.MDS_COLLIDE | None) -> str:
    """One line per ``isCollide`` value of the gate (mds_ach.nodes.collision): 1 held, 2 expert override, 3 in
    contact while moving out of it."""
    if collide is None:
        return f"unknown (nothing on {mds.MDS_CHAN_COLLIDE_NAME})"
    parts = " ".join(collision_parts(collide))
    if collide.isCollide == 2:
        return "EXPERT OVERRIDE passes a predicted collision: " + (parts or "-")
    if collide.isCollide == 3:
        return "CONTACT, only moves out of it pass (nothing held): " + (parts or "-")
    if collide.isCollide or parts:
        return "BLOCKED: " + (parts or "collision predicted")
    return "clear"


def collision_block(collide: mds.MDS_COLLIDE | None) -> list[str]:
    """The original read utility's ``[ Collisions ]`` table (rows Right/Left, 0/1 per part)."""
    lines = ["[ Collisions ]", "          " + "".join(f"{p:>10}" for p in COLLIDE_PARTS)]
    for side, k in (("Right", 0), ("Left", 1)):
        if collide is None:
            cells = "".join(f"{'-':>10}" for _ in COLLIDE_PARTS)
        else:
            cells = "".join(f"{int(bool(collide.joint[COLLIDE_INDEX[p][k]].isCollide)):>10}" for p in COLLIDE_PARTS)
        lines.append(f"{side:<10}{cells}")
    if collide is None:
        lines.append(f"Collide: unknown (no frames on {mds.MDS_CHAN_COLLIDE_NAME})")
    else:
        lines.append(f"Collide: {bool(collide.isCollide)!s:<6}  dt = {collide.time_dt:.7f}")
    return lines


def daemon_line(status: MDS_DAEMON_STATUS | None, age: float | None) -> str:
    """The daemon's health in one line (``mds-daemon-status``), flagged when it stopped publishing."""
    if status is None:
        return f"unknown (nothing on {mds.MDS_CHAN_DAEMON_STATUS_NAME})"
    line = summary_line(status)
    if age is not None and age > 1.0:
        line += f"  STALE: no update for {age:.1f} s"
    return line


def joint_fresh(status: ctypes.Structure | None, address: int) -> str:
    """'yes' when the daemon heard the joint's node recently, 'STALE' when not, 'BAD' when the node answers with
    implausible positions (not trusted), 'UNREF' when its encoder count lost its calibrated zero (ZERO_ENCODER or
    RESET: no motion until HOME), 'FAULT' when a mode 2/3 joint's replies disagree with its motion (held until
    ENABLE or HOME), '-' for joints it does not poll, '?' without daemon status."""
    if status is None:
        return "?"
    flags = status.joint_flags[address]
    if flags & JOINT_UNREFERENCED:
        return "UNREF"
    if flags & JOINT_FOLLOW_FAULT:
        return "FAULT"
    if flags & JOINT_FRESH:
        return "yes"
    if flags & JOINT_STALE:
        return "STALE"
    if flags & JOINT_BAD_REPLY:
        return "BAD"
    return "-" if not flags & JOINT_ENABLED else "?"


def gate_refusals(gate_input: mds.MDS_REF | None, limits: EffectiveLimits) -> list[str]:
    """What the collision gate refuses now (it holds those joints at their last value): the joints of its input
    (``mds-ref-smooth``) outside the effective limits, or not finite. The gate's counter is on mds/collision."""
    if gate_input is None:
        return []
    out = []
    for a in range(mds.MDS_JOINT_COUNT):
        if limits.valid[a]:
            problem = limits.problem(a, gate_input.joint[a].ref)
            if problem is not None:
                out.append(problem.split(" (the effective limits")[0])
    return out


def limits_line(limits: EffectiveLimits, gate_input: mds.MDS_REF | None) -> str:
    """Where the limits come from and whether the gate refuses anything against them, in one line."""
    where = "mds-limits (the daemon's)" if limits.published else "computed here: no daemon published mds-limits"
    refused = gate_refusals(gate_input, limits)
    verdict = ("the gate REFUSES (held at the last value): " + "; ".join(refused)) if refused else "nothing refused"
    return f"{limits.describe()} from {where}; {verdict}"


TABLE_FILE = "joint-table"  # in the runtime dir: the joint table line of the last `mds-ach start` (launcher)


def recorded_table(rt: Path | None = None) -> str | None:
    """The joint table line the last ``mds-ach start`` recorded, if any."""
    try:
        return (rt or runtime_dir()).joinpath(TABLE_FILE).read_text().strip() or None
    except OSError:
        return None


def table_line(published: EffectiveLimits | None, recorded: str | None = None) -> str:
    """Which files the joint table came from: the running daemon's (its ``mds-limits`` source, after the URDF;
    ``recorded``, the whole line ``mds-ach start`` wrote, when it agrees: the channel's field may be cut short),
    else what a start would load now (``mds_ach.robot.config.load``), or why that fails."""
    from mds_ach.robot import config  # lazy: reads the calibration files only when asked
    from mds_ach.robot.msgs.limits import LIMITS_SOURCE_SIZE

    if published is not None:
        files = published.source.split(" & ", 1)[-1]
        if recorded and recorded.startswith(f"robot {published.robot} from {files}"):
            return f"{recorded} (the running daemon's, from mds-limits)"
        cut = "..." if len(published.source) >= LIMITS_SOURCE_SIZE - 1 else ""
        kind = "calibration XML" if published.robot == config.XML_ROBOT else "YAML"
        return f"robot {published.robot} from {files}{cut} ({kind}; the running daemon's, from mds-limits)"
    try:
        return config.describe(config.load()) + " (what a start loads now: no daemon published mds-limits)"
    except ValueError as exc:
        return f"UNUSABLE: {exc}"
