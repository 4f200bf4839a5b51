"""The tests' view of ``mds-ach check-log`` (``mds_ach.tools.checklog.audit_frames``) on one daemon run they recorded.

The contract is defined once, in ``mds_ach.tools.checklog``: every target finite, inside its joint's limits, to an
enabled joint, within the motion bounds (``mds_ach.robot.motion``) from the previous target or, after a re-seed, from
the latest valid position reply. A test records a whole daemon run from its start, so a target before its joint's
first position is a violation too (``whole_run``). This module only adapts: the frames of a ``MemoryLog`` or a
log file in, the violations as lines and the targets each joint was sent out.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import can

from mds_ach.robot.config import JointTable
from mds_ach.robot.motion import MotionBounds
from mds_ach.tools import checklog


@dataclass
class Audit:
    """The result: every violation as a line, and the targets each joint was sent (t, rad)."""

    violations: list[str]
    targets: dict[str, list[tuple[float, float]]]

    def steps(self, short: str) -> list[float]:
        """|q_i - q_{i-1}| of the joint's targets."""
        qs = [q for _, q in self.targets.get(short, [])]
        return [abs(b - a) for a, b in zip(qs, qs[1:], strict=False)]


def audit(frames: Iterable[tuple[float, can.Message]], table: JointTable, bounds: MotionBounds,
          stale_after: float) -> Audit:
    """Check ``frames`` (time, message) of one whole daemon run with the daemon's bounds and stale window."""
    report = checklog.audit_frames(frames, table, bounds, stale_after, whole_run=True, record_targets=True)
    return Audit([f.line() for f in report.findings], report.sent)


def read_log(path: str) -> list[tuple[float, can.Message]]:
    """A daemon's ``--can-log`` file as (time stamp, message) pairs (a torn last line, a SIGKILLed recorder's,
    is skipped)."""
    return [(msg.timestamp, msg) for msg in can.LogReader(path)]


class MemoryLog:
    """A ``CanIO`` recorder that keeps every frame in memory, stamped by ``clock`` (the tests' simulated time) as the
    daemon's ``--can-log`` stamps it: a sent frame with the stamp ``CanIO.send`` gave it (``wall_offset``: the
    interface's wall-clock offset, taken off again), a received one when it arrived."""

    def __init__(self, clock: Callable[[], float], wall_offset: float) -> None:
        self.clock = clock
        self.wall_offset = wall_offset
        self.frames: list[tuple[float, can.Message]] = []

    def __call__(self, msg: can.Message) -> None:
        self.frames.append((self.clock() if msg.is_rx else msg.timestamp - self.wall_offset, msg))

    def close(self) -> None:
        pass
