"""The tests' check of recorded CAN traffic against the daemon's motion bounds (``mds_ach.robot.motion``).

Every MOVETO target a joint was sent is checked with ``motion.check`` against the previous one; the track
restarts at the measured position (at rest) when a re-seed is due: the joint's first valid position reply, a
HOME, RESET, ZERO_ENCODER or ENABLE frame to it, or valid replies resuming after a silence longer than the
stale window. At the first MOVETO after a re-seed a step within the bounds from either the last target or the
measured position is accepted. ``first_reply`` chooses which reply re-seeds: the first one after the trigger,
or the latest one before that MOVETO (the two agree while the joint stands still; only the latest is right for
a joint that moved by itself meanwhile, e.g. while homing). ``mds-ach check-log`` is the operators' tool for
the same audit; this is the tests' independent, minimal version.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import can

from mds_ach.bus import mcb
from mds_ach.bus.mcb import Command, StateArg, TrajectoryMode
from mds_ach.robot.config import JointTable
from mds_ach.robot.motion import MotionBounds, Track, check

RESEED_COMMANDS = (Command.RESET, Command.ZERO_ENCODER, Command.ENABLE)


@dataclass
class _Joint:
    track: Track | None = None  # the last target sent
    measured: Track | None = None  # where a pending re-seed restarts the track
    pending: bool = True
    last_valid: float = -math.inf
    targets: list[tuple[float, float]] = field(default_factory=list)


@dataclass
class Audit:
    """The result: every violation as a line, and the targets each joint was sent (t, rad)."""

    violations: list[str]
    targets: dict[str, list[tuple[float, float]]]

    def steps(self, short: str) -> list[float]:
        """|q_i - q_{i-1}| of the joint's targets."""
        qs = [q for _, q in self.targets.get(short, [])]
        return [abs(b - a) for a, b in zip(qs, qs[1:], strict=False)]


def audit(frames: Iterable[tuple[float, can.Message]], table: JointTable, bounds: MotionBounds, stale_after: float,
          first_reply: bool = False) -> Audit:
    """Check ``frames`` (time, message) of one daemon run, host frames and node replies in order."""
    joints: dict[int, _Joint] = {j.address: _Joint() for j in table}
    violations: list[str] = []
    for t, msg in frames:
        if msg.is_error_frame or msg.is_extended_id or len(msg.data) != mcb.DLC:
            continue
        data = bytes(msg.data)
        if msg.arbitration_id == mcb.HOST_SID:
            pos = mcb.decode_position(data)
            if pos is None or pos[0] not in joints:
                continue
            cfg, state = table[pos[0]], joints[pos[0]]
            q = cfg.to_joint(pos[1])
            margin = max(0.05 * (cfg.upper - cfg.lower), 0.1)
            if not (math.isfinite(q) and cfg.lower - margin <= q <= cfg.upper + margin):
                continue
            if t - state.last_valid > stale_after:
                state.pending, state.measured = True, None
            state.last_valid = t
            if state.pending and (state.measured is None or not first_reply):
                state.measured = Track(q, 0.0, t)
            continue
        frame = mcb.decode(msg.arbitration_id, data)
        state = joints.get(frame.arbitration_id)
        if state is None:
            continue
        cfg = table[frame.arbitration_id]
        home = frame.command == Command.SET and frame.argument == StateArg.TRAJECTORY_MODE and \
            frame.value == TrajectoryMode.HOME
        if home or frame.command in RESEED_COMMANDS:
            state.pending, state.measured = True, None
            continue
        if not (frame.command == Command.SET and frame.argument == StateArg.MOVETO_TARGET):
            continue
        q = cfg.to_joint(frame.value)
        state.targets.append((t, q))
        candidates = [c for c in (state.measured if state.pending else None, state.track) if c is not None]
        if not candidates:
            violations.append(f"{cfg.short} t={t:.3f}: MOVETO {q:.4f} before any position reply")
            state.track = Track(q, 0.0, t)
            continue
        results = [(c, check(c, q, t, bounds)) for c in candidates]
        passing = [c for c, problems in results if not problems]
        if not passing:
            c, problems = results[-1]
            violations += [f"{cfg.short} t={t:.3f}: {c.q:.4f} -> {q:.4f}: {p.kind} {p.value:.3f} > {p.bound:g}"
                           for p in problems]
        base = passing[0] if passing else candidates[-1]
        track = Track(base.q, base.v, base.t)
        track.advance(q, t, bounds)
        state.track, state.pending, state.measured = track, False, None
    return Audit(violations, {table[a].short: s.targets for a, s in joints.items()})


def read_log(path: str) -> list[tuple[float, can.Message]]:
    """A daemon's ``--can-log`` file as (time stamp, message) pairs."""
    return [(msg.timestamp, msg) for msg in can.LogReader(path)]


class MemoryLog:
    """A ``CanIO`` recorder that keeps every frame in memory, stamped by ``clock`` (the tests' simulated time)."""

    def __init__(self, clock) -> None:
        self.clock = clock
        self.frames: list[tuple[float, can.Message]] = []

    def __call__(self, msg: can.Message) -> None:
        self.frames.append((self.clock(), msg))

    def close(self) -> None:
        pass
