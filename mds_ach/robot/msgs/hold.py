"""``MDS_HOLD``: hold / resume / cancel requests to the joint mux on ``mds-hold`` (new; not in the original).

The mux is the one place that decides what each joint is commanded towards, so the command lifecycle lives
there: ``HOLD`` stops the joints where the pipeline has them (braking within the filter's bounds) and nothing
moves until ``RESUME`` or a new command; ``RESUME`` lets the held joints go back to their controllers' targets;
``CANCEL`` ends the current targets of the joints for good (a command that timed out, failed or stopped at
contact): they hold where their reference is and only a new command moves them again.

A CANCEL stops; it never moves (issue 25). Stopping is every writer's right, as HOLD is: a CANCEL ends the target
of any joint, whichever controller owns it. Moving is not, so an explicit ``target`` is no position to go to: it
says where the sender saw the joint stop (the collision gate: the reference it holds the arm at) and is taken only
when it is within the effective limits and within ``CANCEL_TOLERANCE`` of where the joint's reference is now;
then the joint holds where its reference is (not at ``target``), so no CANCEL moves a joint, not even by the
tolerance. Otherwise the whole request is refused (``check_cancel``: the mux and the network server use it).

Writers: the console (``hold``/``resume``, a ``goto ... wait`` that timed out), ``mds-ach hold``/``resume``,
the bridge (``mds/hold``, ``mds/resume``), the collision gate (an arm stopped at contact), user programs.
The mux reads every frame in order and acknowledges the newest ``seq`` it handled in ``mds-mux-state``.
Stdlib + ctypes only, so C clients and the console use it without numpy or rclpy.
"""

from __future__ import annotations

import ctypes
import math
from collections.abc import Sequence
from typing import Protocol

from mds_ach.robot.joints import BY_ADDRESS
from mds_ach.robot.msgs.legacy import MDS_JOINT_COUNT, Name30, _Packed

HOLD_HOLD = 1
"""Stop the joints where the pipeline has them; nothing moves until RESUME or a new command."""
HOLD_RESUME = 2
"""Release a HOLD: the joints go on to their controllers' (still live) targets."""
HOLD_CANCEL = 3
"""End the joints' targets: hold where the reference is now until a new command (``target``: ``check_cancel``)."""
HOLD_ACTIONS: dict[int, str] = {HOLD_HOLD: "hold", HOLD_RESUME: "resume", HOLD_CANCEL: "cancel"}
HOLD_REASON_SIZE = 64
CANCEL_TOLERANCE = 0.25
"""rad: how far an explicit CANCEL target may lie from the joint's reference now (``mds-ref-gated``): the braking
distance at the daemon's motion bounds (config/joints.yaml ``motion``: (2 rad/s)^2 / (2 * 8 rad/s^2)), which is
also how far the reference can run at the 2 rad/s speed bound in 125 ms. So the collision gate's CANCEL is still
taken when the arm it stopped was released and moved on before the mux (late on a loaded host) took the request;
a target farther away asks for a move, not a stop. The joint then holds where its reference is, never at the
target, so the tolerance moves nothing."""


class MDS_HOLD(_Packed):  # noqa: N801 - MDS struct naming
    """``mds-hold`` frame (packed).

    seq              the writer's request counter (the mux echoes the newest it handled)
    action           HOLD_HOLD / HOLD_RESUME / HOLD_CANCEL
    joints[address]  1 = the request applies to this joint; all 0 = every joint
    target[address]  CANCEL only: NaN or where the sender saw the reference stop, rad (``check_cancel``)
    source           who asked (console, mds-ach, ros, collision, a client's name), char[30]
    reason           why, for the logs and the status (e.g. "goto timed out"), NUL-terminated ASCII
    time             CLOCK_MONOTONIC when written
    """

    _fields_ = [
        ("seq", ctypes.c_uint32),
        ("action", ctypes.c_int16),
        ("joints", ctypes.c_uint8 * MDS_JOINT_COUNT),
        ("target", ctypes.c_double * MDS_JOINT_COUNT),
        ("source", Name30),
        ("reason", ctypes.c_char * HOLD_REASON_SIZE),
        ("time", ctypes.c_double),
    ]


def check_hold(hold: MDS_HOLD) -> str | None:
    """A known action, a 0/1 joint mask, targets NaN or finite within one turn."""
    if hold.action not in HOLD_ACTIONS:
        return f"unknown hold action {hold.action} (1 hold, 2 resume, 3 cancel)"
    for address in range(MDS_JOINT_COUNT):
        if hold.joints[address] not in (0, 1):
            return f"joints[{address:#x}] is {hold.joints[address]}, not 0 or 1"
        t = hold.target[address]
        if not math.isnan(t) and (not math.isfinite(t) or abs(t) > 2 * math.pi):
            return f"hold target {t} at address {address:#x} is not NaN or within one turn"
    return None


class JointLimits(Protocol):
    """What ``check_cancel`` asks of the limits (``mds_ach.kinematics.limits.EffectiveLimits``)."""

    def problem(self, address: int, value: float) -> str | None: ...


def _label(address: int) -> str:
    joint = BY_ADDRESS.get(address)
    return joint.short if joint is not None else f"{address:#04x}"


def check_cancel(hold: MDS_HOLD, limits: JointLimits | None, reference: Sequence[float] | None) -> str | None:
    """Why a CANCEL's explicit targets must not be taken (None: they may, or the request has none): a target
    outside the effective limits (``limits``; None: not checked), or not within ``CANCEL_TOLERANCE`` of the joint's
    reference now (``reference`` by address; None or NaN: unknown, so no explicit target is taken). A CANCEL stops,
    it never moves: the one rule the mux and the network server (``achd``) apply to ``mds-hold``."""
    if hold.action != HOLD_CANCEL:
        return None
    masked = [a for a in range(MDS_JOINT_COUNT) if hold.joints[a]] or list(range(MDS_JOINT_COUNT))
    for address in masked:
        target = float(hold.target[address])
        if math.isnan(target):
            continue
        name = _label(address)
        problem = limits.problem(address, target) if limits is not None else None
        if problem:
            return f"CANCEL {name}: {problem}"
        here = float(reference[address]) if reference is not None else math.nan
        if not math.isfinite(here):
            return f"CANCEL {name} to {target:.5f} rad: its reference now is unknown (NaN holds it where it is)"
        if abs(target - here) > CANCEL_TOLERANCE:
            return (f"CANCEL {name} to {target:.5f} rad is {abs(target - here):.4f} rad from its reference "
                    f"{here:.5f}: a CANCEL never moves a joint (tolerance {CANCEL_TOLERANCE:g} rad; NaN holds it "
                    f"where it is)")
    return None
