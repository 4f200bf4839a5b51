"""The daemon's collaborative mode: every batch of targets keeps the hands and elbows within the Cartesian bound.

``mds_ach.kinematics.cartesian`` defines the bound and how a batch's speed is measured; this module is the daemon's
side of it, kept apart from the loop (``DaemonLoop`` calls :meth:`CollaborativeGuard.plan` once per cycle and
:meth:`CollaborativeGuard.retime` for each planned joint):

1. ``plan``: at one instant, the joint limiter's step of every upper-body joint that is sent this cycle (the same
   ``motion.limit`` as always), turned into velocities, and the fraction ``lam`` towards the hardest braking the joint
   bounds allow that keeps the batch within the bound (``CartesianBound.scale``);
2. ``retime``: each joint's frames go out at their own moment (the daemon dates every MOVETO separately, see
   ``DaemonLoop._send``), so the planned *velocity* is carried to that moment -- the joint bounds hold at it (the
   acceleration box only widens with a later moment), the step never passes the goal unless braking requires it --
   and the batch's speed, which counts each joint's velocity over its own interval, is what was planned.

Switching modes never steps: switched on during a fast motion, the group brakes at the joint acceleration bound
(``lam`` = 1) until it is within the bound (``cartesian_braking`` counts those cycles, at most
``cartesian.ramp_time``); switched off, the joint limiter ramps up as from any slower motion.

The mode is logged for the CAN-log auditor (``ModeLog``, ``<can-log>.modes`` next to the daemon's ``--can-log``):
``mds-ach check-log`` then checks the bound on the batches sent in collaborative mode.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

from mds_ach.kinematics import cartesian
from mds_ach.robot import motion
from mds_ach.robot.config import JointConfig, JointTable

log = logging.getLogger("mds_ach.nodes.daemon")

MODES_SUFFIX = ".modes"  # the mode log next to a --can-log file


class CollaborativeGuard:
    """The collaborative mode's state and the per-cycle plan of the upper body's steps."""

    def __init__(self, table: JointTable, bounds: motion.MotionBounds, *, on: bool = False,
                 max_speed: float | None = None) -> None:
        self.bounds = bounds
        self.bound = cartesian.CartesianBound(table.collaborative_speed if max_speed is None else max_speed)
        self.on = on
        self.switched_at = -math.inf  # when collaborative mode was last switched on (loop clock)
        # The group in ``cartesian.JOINTS`` order by address; a joint the table does not have stays at 0 rad (None).
        self.slots: tuple[int | None, ...] = tuple(
            (table[short].address if _has(table, short) else None) for short in cartesian.JOINTS)
        self.addresses: tuple[int, ...] = tuple(a for a in self.slots if a is not None)
        self.members = frozenset(self.addresses)
        self.last = cartesian.Scaled(0.0, 0.0, 0.0, True)  # this cycle's plan (the status shows it)

    @property
    def max_speed(self) -> float:
        return self.bound.max_speed

    def switch(self, on: bool, now: float) -> bool:
        """Collaborative mode on or off; True if that changed it."""
        if on == self.on:
            return False
        self.on = on
        if on:
            self.switched_at = now
        return True

    def plan(self, tracks: Mapping[int, motion.Track], proposals: Mapping[int, float], t: float) -> dict[int, float]:
        """Velocities (rad/s, by address) for the joints in ``proposals`` (the limiter's targets at ``t``) that keep
        the batch within the bound; joints of the group not proposed stand still in it."""
        b = self.bounds
        a_max = motion.LIMIT_MARGIN * b.max_acceleration
        q, v_lim, brake = [], [], []
        h_max = 0.0
        for address in self.slots:
            track = tracks.get(address) if address is not None else None
            q.append(track.q if track is not None else 0.0)
            if address is None or track is None or address not in proposals:
                v_lim.append(0.0)
                brake.append(0.0)
                continue
            h = b.interval(t - track.t)
            if h <= 0:
                v_lim.append(0.0)
                brake.append(0.0)
                continue
            h_max = max(h_max, h)
            v_lim.append((proposals[address] - track.q) / h)
            brake.append(cartesian.brake_velocity(track.previous_velocity(t, b), a_max, h))
        self.last = self.bound.scale(q, v_lim, brake, h_max)
        lam = self.last.lam
        return {a: v + lam * (br - v) for a, v, br in zip(self.slots, v_lim, brake, strict=True)
                if a is not None and a in proposals}

    def retime(self, track: motion.Track, velocity: float, goal: float, t: float, cfg: JointConfig) -> float:
        """The target at ``t`` for a joint planned to move at ``velocity``: within the joint bounds at ``t``, never
        faster than it could still stop at ``goal`` unless braking within the bound requires it, inside the joint's
        limits."""
        b = self.bounds
        h = b.interval(t - track.t)
        if h <= 0:
            return track.q
        a_max = motion.LIMIT_MARGIN * b.max_acceleration
        v0 = track.previous_velocity(t, b)
        # As motion.limit: never a step from which the target could not stop at the goal (the plan's step was sized
        # for an earlier moment, a shorter interval); the acceleration bound wins.
        d = goal - track.q
        reach = motion._stop_speed(abs(d), h, a_max)  # noqa: SLF001 - the limiter's own rule, not a copy of it
        v = min(velocity, reach) if d >= 0 else max(velocity, -reach)
        v = min(max(v, v0 - a_max * h), v0 + a_max * h)
        return cfg.clamp(track.q + v * h)


def _has(table: JointTable, short: str) -> bool:
    try:
        table[short]
    except KeyError:
        return False
    return True


class ModeLog:
    """Appends the daemon's mode changes to ``<can-log>.modes``: one line ``<stamp> collaborative <mm/s>`` or
    ``<stamp> normal``, the stamp on the CAN log's clock, so ``mds-ach check-log`` knows which batches the Cartesian
    bound applies to. A mode change is an operator's act (rare): the line is written from a helper thread, never in
    the loop."""

    def __init__(self, path: str | Path, wall_offset: float) -> None:
        self.path = Path(str(path) + MODES_SUFFIX)
        self.wall_offset = wall_offset
        self.path.write_text("")  # one file per daemon run, like its --can-log
        self._lock = threading.Lock()

    def __call__(self, t: float, speed: float) -> None:
        line = (f"{t + self.wall_offset:.6f} collaborative {speed * 1e3:g}\n" if speed > 0
                else f"{t + self.wall_offset:.6f} normal\n")
        threading.Thread(target=self._append, args=(line,), name="mode-log", daemon=True).start()

    def _append(self, line: str) -> None:
        with self._lock:
            try:
                with self.path.open("a") as f:
                    f.write(line)
            except OSError as exc:
                log.error("mode log %s: %s", self.path, exc)


def read_modes(lines: Iterable[str], where: str = "") -> list[tuple[float, float]]:
    """(stamp, bound in m/s; 0 = normal) from a mode log's lines; a bad line is a ValueError naming it."""
    out = []
    for n, line in enumerate(lines, 1):
        parts = line.split()
        if not parts:
            continue
        try:
            stamp = float(parts[0])
            if parts[1:] == ["normal"]:
                out.append((stamp, 0.0))
            elif len(parts) == 3 and parts[1] == "collaborative":
                out.append((stamp, cartesian.validate_max_speed(float(parts[2]) / 1e3)))
            else:
                raise ValueError(line.strip())
        except (ValueError, IndexError):
            raise ValueError(f"{where}:{n}: not a mode line ('<stamp> normal' or '<stamp> collaborative <mm/s>'): "
                             f"{line.strip()!r}") from None
    return out


ModeSink = Callable[[float, float], None]
