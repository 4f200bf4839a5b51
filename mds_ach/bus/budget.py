"""The CAN budget of one daemon cycle: frames, bits, the bus load at a rate, the highest rate the bus carries.

Why: each cycle the daemon sends the original's 4-SET MOVETO sequence to every joint whose target changed
(``specs/mds-original.md`` §b.4) and one broadcast position query; every SET is ACKed and every node answers the
query. With many joints moving at a high rate that no longer fits the bus: frames queue, replies come a cycle
late, the transmit buffer fills. So the daemon says at start what its rate costs in the worst case (and
``--rate max`` picks the highest that fits), instead of it being discovered on the wire.

Worst case per cycle, every enabled joint sent a new target every cycle (§b.7's accounting, plus the warning):

* per joint: 4 SET (acceleration, MOVETO target, mode, period) + 4 ACK + 1 WARNING TRAJECTORY_BUFFER_EMPTY (a
  MOVETO that ends sends one: every MOVETO in the June 2015 captures did; at low speed each cycle's short move
  ends within the cycle, so a joint can send one every cycle);
* 1 broadcast ACTUAL_POSITION query + 1 reply per node on the bus: every node answers, enabled or not, including
  the nodes the anatomy does not list (``UNLISTED_NODES``).

Setup commands (enable, home, reset: one frame and one ACK per joint, on request) are occasional and not counted.

Bits per frame: **worst-case bit stuffing**, ``mcb.FRAME_BITS`` (135 for an 11-bit ID with 8 data bytes, the
interframe space included): the figure the daemon's bus load and the simulated bus's wire model use. Without
stuffing a frame is ``mcb.frame_bits`` less the stuffing, 111 bits (the lower bound §b.7 quotes). Load is judged
on the worst case: ``MAX_LOAD`` (60 %) of the bitrate at most, the headroom the original paper names and the level
``mds-ach status`` warns about.

Check by hand, the original's figure (§b.7: 13 joints, 48 nodes, no warning counted): 13 x 8 + 1 + 48 = 153
frames; x 135 bits x 10 Hz = 206 550 bit/s = 20.7 % of 1 Mbit/s (17.0 % at 111 bits): "about 17-21 %".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

from mds_ach.bus import mcb

MAX_LOAD = 0.60
"""The highest worst-case share of the bitrate a rate may use."""
SETS_PER_TARGET = 4  # mcb.encode_position_sequence: acceleration, MOVETO target, trajectory mode, period
ACKS_PER_TARGET = SETS_PER_TARGET  # every SET is ACKed (§b.4)
WARNINGS_PER_TARGET = 1  # TRAJECTORY_BUFFER_EMPTY when the MOVETO ends
UNLISTED_NODES = 5
"""Nodes that answer the broadcast on the MDS bus but are not in the anatomy: 0x44-0x47 and 0x58 (§b.7)."""
RATE_STEP = 0.1  # Hz: max_rate is rounded down to this
STUFF_FREE_BITS = 34 + 8 * mcb.DLC + 13  # the same frame with no stuff bit (111)


class _Table(Protocol):
    """What :meth:`CycleBudget.for_table` reads of a ``mds_ach.robot.config.JointTable`` (the bus layer does not
    import the robot layer)."""

    def __len__(self) -> int: ...
    @property
    def enabled(self) -> tuple[object, ...]: ...


@dataclass(frozen=True)
class CycleBudget:
    """The worst-case CAN traffic of one daemon cycle: ``joints`` enabled joints, ``nodes`` answering the query."""

    joints: int
    nodes: int
    bitrate: int
    frame_bits: int = mcb.FRAME_BITS
    warnings: int = WARNINGS_PER_TARGET
    """Done warnings per target (0: §b.7's accounting, which left them out)."""

    def __post_init__(self) -> None:
        if min(self.joints, self.nodes, self.warnings) < 0 or self.frame_bits <= 0:
            raise ValueError(f"joints, nodes and warnings must be >= 0 and frame bits > 0, got {self}")
        if self.bitrate <= 0:
            raise ValueError(f"the bitrate must be > 0, got {self.bitrate}")

    @classmethod
    def for_table(cls, table: _Table, bitrate: int, unlisted_nodes: int = UNLISTED_NODES) -> CycleBudget:
        """The budget of a joint table: its enabled joints move, all its nodes and ``unlisted_nodes`` answer."""
        return cls(len(table.enabled), len(table) + unlisted_nodes, bitrate)

    @property
    def per_joint(self) -> int:
        return SETS_PER_TARGET + ACKS_PER_TARGET + self.warnings

    @property
    def frames(self) -> int:
        """Frames per cycle, worst case."""
        return self.joints * self.per_joint + 1 + self.nodes

    @property
    def bits(self) -> int:
        """Wire bits per cycle, worst-case stuffing."""
        return self.frames * self.frame_bits

    def load(self, rate: float) -> float:
        """Worst-case share of the bitrate (0.6 = 60 %) at ``rate`` Hz."""
        return self.bits * rate / self.bitrate

    def max_rate(self) -> float:
        """The highest rate (rounded down to ``RATE_STEP``) whose worst-case load is at most ``MAX_LOAD``."""
        steps = math.floor(MAX_LOAD * self.bitrate / (self.bits * RATE_STEP) + 1e-9)
        rate = steps * RATE_STEP
        while rate > 0 and self.load(rate) > MAX_LOAD:  # float rounding of steps * RATE_STEP
            steps -= 1
            rate = steps * RATE_STEP
        return round(rate, 6)

    def accounting(self) -> str:
        """'17 joints x (4 SET + 4 ACK + 1 done warning) + 1 query + 48 replies = 202 frames x 135 bits'."""
        warning = f" + {self.warnings} done warning" if self.warnings else ""
        return (f"{self.joints} joints x ({SETS_PER_TARGET} SET + {ACKS_PER_TARGET} ACK{warning}) + 1 query + "
                f"{self.nodes} replies = {self.frames} frames x {self.frame_bits} bits")

    def problem(self, rate: float) -> str | None:
        """Why the bus cannot carry ``rate`` Hz (None: it can)."""
        if not (math.isfinite(rate) and rate > 0):
            return f"the loop rate must be a number > 0 Hz, got {rate}"
        if self.load(rate) <= MAX_LOAD:
            return None
        top = self.max_rate()
        advice = f"use --rate {top:g} or less (or --rate max)" if top > 0 else "no rate fits: enable fewer joints"
        return (f"{rate:g} Hz needs {100 * self.load(rate):.0f} % of the CAN bus ({self.bitrate} bit/s) in the worst "
                f"case ({self.accounting()} per cycle), more than {100 * MAX_LOAD:.0f} %: {advice}")

    def describe(self, rate: float) -> str:
        """The daemon's start-up line: the worst case at ``rate`` and the highest rate allowed."""
        best = self.frames * STUFF_FREE_BITS * rate / self.bitrate
        return (f"CAN budget at {rate:g} Hz: {100 * self.load(rate):.1f} % of {self.bitrate} bit/s worst case "
                f"({100 * best:.1f} % without bit stuffing); {self.accounting()} per cycle; max rate "
                f"{self.max_rate():g} Hz (<= {100 * MAX_LOAD:.0f} %)")
