"""``MDS_HOLD``: hold / resume / cancel requests to the joint mux on ``mds-hold`` (new; not in the original).

The mux is the one place that decides what each joint is commanded towards, so the command lifecycle lives
there: ``HOLD`` stops the joints where the pipeline has them (braking within the filter's bounds) and nothing
moves until ``RESUME`` or a new command; ``RESUME`` lets the held joints go back to their controllers' targets;
``CANCEL`` ends the current targets of the joints for good (a command that timed out, failed or stopped at
contact): they hold at ``target`` (or where they are, NaN) and only a new command moves them again.

Writers: the console (``hold``/``resume``, a ``goto ... wait`` that timed out), ``mds-ach hold``/``resume``,
the bridge (``/mds/hold``, ``/mds/resume``), the collision gate (an arm stopped at contact), user programs.
The mux reads every frame in order and acknowledges the newest ``seq`` it handled in ``mds-mux-state``.
Stdlib + ctypes only, so C clients and the console use it without numpy or rclpy.
"""

from __future__ import annotations

import ctypes
import math

from mds_ach.robot.msgs.legacy import MDS_JOINT_COUNT, Name30, _Packed

HOLD_HOLD = 1
"""Stop the joints where the pipeline has them; nothing moves until RESUME or a new command."""
HOLD_RESUME = 2
"""Release a HOLD: the joints go on to their controllers' (still live) targets."""
HOLD_CANCEL = 3
"""End the joints' targets: hold at ``target`` (NaN: where the reference is now) until a new command."""
HOLD_ACTIONS: dict[int, str] = {HOLD_HOLD: "hold", HOLD_RESUME: "resume", HOLD_CANCEL: "cancel"}
HOLD_REASON_SIZE = 64


class MDS_HOLD(_Packed):  # noqa: N801 - MDS struct naming
    """``mds-hold`` frame (packed).

    seq              the writer's request counter (the mux echoes the newest it handled)
    action           HOLD_HOLD / HOLD_RESUME / HOLD_CANCEL
    joints[address]  1 = the request applies to this joint; all 0 = every joint
    target[address]  CANCEL only: the position to hold, rad; NaN = where the joint's reference is now
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
