"""The daemon's real-time loop: references in, MCB frames out, positions back, ``mds-state`` published.

One cycle (``DaemonLoop.cycle``), at an absolute-time schedule on its own thread:

1. setup commands queued from ``mds-cmd`` or the ROS service (enable, disable, home, reset, zero, reset bus);
2. newest ``mds-collide`` (copied into ``state.collide``) and newest ``mds-ref-gated`` -- nothing new means the
   previous reference holds (zero-order hold); NaN/Inf or an unknown mode refuses that joint's value;
3. per joint: clamp to the effective limits (URDF & joint table, ``mds_ach.kinematics.limits``), then the legacy
   mode (0 first-order filter with L giving 95 % of a step in 4.0 s at the loop rate, 1 pass-through, 2 compliant
   (follow the encoder), 3 encoder filter; 2 and 3 follow at most ``FOLLOW_SPEED`` and fault when the replies and
   the motion disagree, ``_follow``): the joint's *goal*;
4. for enabled joints, unless ``mds-collide`` says a collision is predicted for that arm (``_collision_held``):
   the goal through ``motion.limit`` at the moment the joint's frames go out, then, if the target (float32
   counts) changed, the 4-frame SET sequence (acceleration, MOVETO target, trajectory mode, period);
5. one broadcast ACTUAL_POSITION query; replies decoded in binary until every live node answered or the
   reply window closes; a node silent for ``stale_after`` (``STALE_AFTER``, 0.35 s at every rate) is stale
   (``state.active`` 0, flagged in ``mds-daemon-status``), never reported as fresh; an implausible reply is never
   taken as a position;
6. ``mds-state`` (legacy layout, CLOCK_MONOTONIC time) and ``mds-daemon-status``.

**The motion bounds hold on every path.** Each joint keeps a ``motion.Track`` of the last target it was sent
(the float32 counts converted back to rad, i.e. what a CAN log shows) and every new target is limited from it
(speed, acceleration, braking for the joint limits; ``mds_ach.robot.motion``). Whatever made the goal jump -- a mode
change, a stall of this loop, a collision hold released, bus-off, a restart, an upstream node that moved on --
the joint ramps. A joint that is not sent to keeps its track (by the definition its velocity becomes 0).
A step is dated by the moment its target was limited for; its MOVETO carries that very stamp in the CAN log
(``_send``), so the limiter and the auditor judge the same step. The track is *re-seeded* at the measured
position, at rest, only where the log shows why: when the daemon starts, and after HOME, RESET, ZERO_ENCODER and
ENABLE (their frames are on the bus): until the next MOVETO it follows the joint's trusted replies, and that
MOVETO states exactly where the joint is (a zero step), so the daemon and any observer of the log
(``mds-ach check-log``) restart from the same point. A silent node is sent nothing; when it answers again it goes
on from its last target, from rest, within the bounds: its replies lag a moving joint (the node kept going to the
last target meanwhile), so restarting from the measured position would reverse it. A joint whose position the
daemon never knew is not commanded. Targets that had to be limited are flagged (``JOINT_LIMITED``) and counted.

**The calibrated frame.** Limits, targets and ``mds-state`` are in the frame whose count 0 is the ROM middle, which
HOME establishes. ZERO_ENCODER and RESET restart a node's count where the joint stands: the joint is *unreferenced*
(``JOINT_UNREFERENCED``) -- no target, ``pos`` NaN -- until a HOME ends at rest with the count at 0 again.

**Position replies are validated**: one outside the joint's range (plus a margin) or implying a speed beyond
``REPLY_SPEED_FACTOR`` times the velocity bound is refused (``JOINT_BAD_REPLY``, counted); ``pos`` keeps the
last good value and the joint counts as not fresh until ``REPLIES_TO_TRUST`` consistent replies in a row. A
joint in mode 2 or 3 without a trusted, fresh position holds its last target.

``state.joint[a].active`` is 1 while the joint's position is fresh and trusted, ``pos`` is NaN until a first
reading arrived, ``vel`` is the finite difference of fresh readings, ``cur`` the last CURRENT reply (raw units),
``ref`` the target the joint is commanded to, ``ref_c_send`` the last one sent (float32 counts, as on the bus).
Setup commands (enable, reset, zero encoder, home) never move a joint by themselves except HOME: afterwards
the joint holds where it is until its reference on ``mds-ref-gated`` changes, and once its position is known the
daemon asks the pipeline to restart the joint's reference there (``joint_reseed`` in ``mds-daemon-status``;
``resetbus`` does the same for every joint).
"""

from __future__ import annotations

import ctypes
import gc
import logging
import math
import os
import queue
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import mds_ach as mds
from mds_ach import ach
from mds_ach.ach import glibc
from mds_ach.ach.glibc import sleep_until
from mds_ach.bus import budget, mcb
from mds_ach.bus.canio import CanIO
from mds_ach.bus.constants import (
    CAN_ERR_BUSOFF,
    CAN_ERR_CRTL,
    CAN_ERR_CRTL_ACTIVE,
    CAN_ERR_CRTL_PASSIVE,
    CAN_ERR_CRTL_WARNING,
    CAN_ERR_RESTARTED,
)
from mds_ach.bus.mcb import Response, StateArg
from mds_ach.kinematics import limits as effective_limits
from mds_ach.kinematics.cartesian import brake_velocity
from mds_ach.kinematics.cartesian import ramp_time as cartesian_ramp_time
from mds_ach.kinematics.limits import EffectiveLimits
from mds_ach.nodes import filters
from mds_ach.nodes.collaborative import CollaborativeGuard, ModeSink
from mds_ach.nodes.estop import BRAKE_TIMEOUT, REST_SPEED, SETTLE_TIMEOUT, EStopState, Latch
from mds_ach.ratelog import RateLimitedLog, logger_fn
from mds_ach.robot import access as channel_access
from mds_ach.robot import contracts, motion
from mds_ach.robot.channels import StructChannel, replaced
from mds_ach.robot.config import JointConfig, JointTable
from mds_ach.robot.joints import BY_SHORT, LEFT_ARM, RIGHT_ARM
from mds_ach.robot.msgs import MDS_CMD, MDS_COLLIDE, MDS_REF, MDS_STATE
from mds_ach.robot.msgs import daemon_status as ds

log = logging.getLogger("mds_ach.nodes.daemon")

HOMING_TIMEOUT = 60.0  # s: stop waiting for a homing joint to settle
HOMED_TOLERANCE = 0.01  # rad: at rest after HOME the count reads this close to 0 (the ROM middle, joint side)
COMMAND_NAMES = {mds.MDS_CMD_ENABLE: "enable", mds.MDS_CMD_DISABLE: "disable", mds.MDS_CMD_HOME: "home",
                 mds.MDS_CMD_RESET: "reset", mds.MDS_CMD_ZERO_ENCODER: "zero", mds.MDS_CMD_RESET_BUS: "resetbus"}
_F32 = struct.Struct("<f")


def f32(value: float) -> float:
    """The value as the float32 that goes on the wire (what decides whether a target 'changed')."""
    return _F32.unpack(_F32.pack(value))[0]


def late_send_tolerance(bounds: motion.MotionBounds, period: float) -> float:
    """How late (s) a MOVETO may go out after the time its step was limited for.

    Sent late by ``d``, a step of speed ``v`` planned over ``h`` shows as ``v h / (h + d)``: its acceleration is off
    by at most ``v_max d / h^2``. Half of the limiter's acceleration margin (``1 - LIMIT_MARGIN``) may go to that, at
    the loop period (2 ms at 10 Hz with the default bounds); at least 0.2 ms (what one send costs under load).
    """
    share = 0.5 * (1.0 - motion.LIMIT_MARGIN) * bounds.max_acceleration * period * period / bounds.max_velocity
    return max(share, 2e-4)


# A node silent this long is stale (state.active 0, sent nothing): 3.5 periods of the original's 10 Hz, at every
# rate -- a fraction of a period's jitter at 100 Hz must not turn into a silence.
STALE_AFTER = 0.35  # s
PARAM_PERIOD = 1.0  # s
WINDOW_STATS_PERIOD = 0.5  # s between refreshes of mds-daemon-status's window statistics (``_publish_status``)
"""``mds-param`` is put again this often: achd (golems' and ours by default) sends a pulling station only frames
written after it connected, and a station without ``mds-param`` has no joint names."""
STALL_PERIODS = 2.0  # a cycle that starts more than this many periods after the previous one: the loop stalled
# Position replies: a reply further than REPLY_RANGE_MARGIN of the joint's range (at least REPLY_RANGE_MIN) beyond
# its limits, or implying more than REPLY_SPEED_FACTOR times the velocity bound since the last good reply (plus
# REPLY_SLACK for encoder noise and time-stamp jitter), cannot be right: no node moves its joint like that.
REPLY_RANGE_MARGIN = 0.05
REPLY_RANGE_MIN = 0.1  # rad
REPLY_SPEED_FACTOR = 4.0
REPLY_SLACK = 0.05  # rad
REPLIES_TO_TRUST = 3  # consistent replies in a row before a joint's position is trusted again
# Modes 2 and 3 follow the reported position. A wrong but plausible reply (two boards on one address, an encoder
# that slipped) would be followed, the joint driven after it, the next reply as wrong again: a runaway in bounded
# steps. So the target follows the reported position at most FOLLOW_SPEED, and a chase that runs away is a fault
# that holds the joint (``JointRuntime.follow_fault``): while the reported position is more than FOLLOW_GAP ahead
# of the target chasing it, the two must not move on together in that direction by FOLLOW_FAULT_TRAVEL -- a joint
# pushed and held stands still while its target comes; one that moves with the target it is ahead of is driven by
# that target, so it is not where the replies say. What a runaway moves the joint before the fault:
# FOLLOW_FAULT_TRAVEL plus the node's lag behind its target (FOLLOW_RUNAWAY_BOUND at the default bounds and 10 Hz;
# test_feedback_fault.py measures it).
FOLLOW_SPEED = 0.5  # rad/s (at most the velocity bound); a hand moving a joint faster is followed this fast
FOLLOW_GAP = 0.1  # rad (at least 1.5 cycles' follow)
FOLLOW_FAULT_TRAVEL = 0.1  # rad
FOLLOW_RUNAWAY_BOUND = 0.3  # rad at 10 Hz (0.25 measured); add a cycle's follow at lower rates
# An offset below FOLLOW_GAP looks like a hand moving the joint at up to FOLLOW_GAP per cycle; but a push ends (the
# reported position comes to rest: within FOLLOW_SETTLED for FOLLOW_REST_TIME, at least 2.5 periods) and an offset
# fed back never does: a target that followed FOLLOW_DRIFT one way while the reply never rested faults too (a joint
# moves at most FOLLOW_DRIFT plus the node's lag on such an offset).
FOLLOW_SETTLED = 0.002  # rad
FOLLOW_REST_TIME = 0.2  # s
FOLLOW_DRIFT = 0.5  # rad
LIMIT_TOLERANCE = 1e-9  # rad: a target further than this from the goal counts as limited
OTHER_THREADS_NICE = -10  # the daemon's other threads, when the loop is real-time (glibc.renice_other_threads)
LOOP_THREAD_NAME = "mds-daemon-loop"  # the loop thread's kernel name (ps -L, /proc/PID/task/TID/comm; 15 bytes max)
# What running without a real-time priority means, said once at start (docs/operator.md, "Real-time priority").
WITHOUT_RT = ("under CPU load the loop may stall, seconds on a busy machine (mds-state, /joint_states and "
              "trajectories pause; `stalls` in mds-ach status); the bus stays safe: nothing is sent late (a target "
              "later than late_send_tolerance is withheld) and the joints ramp after a stall")
RT_HOWTO = ("allowed for root, with CAP_SYS_NICE, or with an rtprio limit (/etc/security/limits.conf: "
            "'USER - rtprio 99', 'USER - memlock unlimited', 'USER - nice -10'; docs/operator.md, "
            "\"Real-time priority\")")

_LEFT_PARTS = (mds.COLLIDE_L_HAND, mds.COLLIDE_L_SHOULDER, mds.COLLIDE_L_FOREARM, mds.COLLIDE_L_ELBOW,
               mds.COLLIDE_L_WRIST)
_RIGHT_PARTS = (mds.COLLIDE_R_HAND, mds.COLLIDE_R_SHOULDER, mds.COLLIDE_R_FOREARM, mds.COLLIDE_R_ELBOW,
                mds.COLLIDE_R_WRIST)
_LEFT_ARM_ADDRESSES = frozenset(BY_SHORT[n].address for n in LEFT_ARM)
_RIGHT_ARM_ADDRESSES = frozenset(BY_SHORT[n].address for n in RIGHT_ARM)


def reply_in_range(cfg: JointConfig, q: float) -> bool:
    """Can a position reply of ``q`` rad be right at all: finite and within the joint's range plus the margin? The
    daemon refuses anything else as a position; ``mds-ach check-log`` ignores it by the very same rule."""
    margin = max(REPLY_RANGE_MARGIN * (cfg.upper - cfg.lower), REPLY_RANGE_MIN)
    return math.isfinite(q) and cfg.lower - margin <= q <= cfg.upper + margin


# --- channels --------------------------------------------------------------------------------------------


MAX_RATE_HZ = 1000.0  # the fastest loop the daemon accepts (the slowest: motion.MIN_RATE_HZ)


def rate_problem(rate_hz: float) -> str:
    """Why the daemon refuses a loop of ``rate_hz`` ('' if it does not). Slower than ``motion.MIN_RATE_HZ``, each
    target would carry a large part of a move (at 1 Hz a 1.45 rad move was one target): the bounds are defined for
    that rate and faster."""
    if math.isfinite(rate_hz) and motion.MIN_RATE_HZ <= rate_hz <= MAX_RATE_HZ:
        return ""
    return (f"loop rate must be {motion.MIN_RATE_HZ:g} to {MAX_RATE_HZ:g} Hz, got {rate_hz:g} Hz (below "
            f"{motion.MIN_RATE_HZ:g} Hz each target would carry a large part of a move)")


def lock_timeout_for(rate_hz: float) -> float:
    """How long the loop waits at most for a channel's lock: a tenth of its period, at most 5 ms. A process that
    holds a lock longer (stopped, or stuck inside a put) costs the loop that one read or write, never a cycle."""
    return min(0.005, 0.1 / rate_hz) if rate_hz > 0 else 0.005  # (a bad rate is refused by DaemonLoop)


DAEMON_INPUT = mds.MDS_CHAN_DAEMON_INPUT_NAME

# The daemon's role for each channel it uses; the structs and geometry come from the contracts registry, and
# test_contracts checks these are exactly the channels that name the daemon as a writer or reader.
DAEMON_ROLES: dict[str, str] = {
    "ref": DAEMON_INPUT,
    "state": mds.MDS_CHAN_STATE_NAME,
    "collide": mds.MDS_CHAN_COLLIDE_NAME,
    "cmd": mds.MDS_CHAN_BOARD_CMD_NAME,
    "status": mds.MDS_CHAN_DAEMON_STATUS_NAME,
    "param": mds.MDS_CHAN_PARAM_NAME,
    "limits": mds.MDS_CHAN_LIMITS_NAME,
}


@dataclass
class DaemonChannels:
    """The Ach channels the daemon reads and writes (created if missing): ``DAEMON_ROLES``."""

    ref: StructChannel
    state: StructChannel
    collide: StructChannel
    cmd: ach.Channel  # raw (see open)
    status: StructChannel
    param: StructChannel
    limits: StructChannel

    @classmethod
    def open(cls, lock_timeout: float | None = lock_timeout_for(1.0 / mds.MDS_LOOP_PERIOD)) -> DaemonChannels:
        """Open (create) every channel; each get and put waits at most ``lock_timeout`` s for the channel lock
        (``lock_timeout_for`` the loop's rate; None: as long as it takes)."""
        opened: dict[str, Any] = {}
        try:
            for key, name in DAEMON_ROLES.items():
                if key == "cmd":  # raw: the loop counts and reports wrong-sized commands itself
                    opened[key] = cls.open_raw(name, lock_timeout)
                else:
                    opened[key] = StructChannel.of(name, lock_timeout=lock_timeout)
        except Exception:
            for ch in opened.values():
                ch.close()
            raise
        return cls(**opened)

    @staticmethod
    def open_raw(name: str, lock_timeout: float | None, create: bool = True) -> ach.Channel:
        """A raw handle on channel ``name`` (its contract's geometry), trusted as ``StructChannel`` requires."""
        c = contracts.contract(name)
        channel = ach.Channel(name, c.frame_count, c.frame_size, create=create, lock_timeout=lock_timeout)
        if channel_access.enforced():  # as StructChannel does for the others
            try:
                channel_access.require_trusted(channel)
            except BaseException:
                channel.close()
                raise
        return channel

    def reopen_cmd(self) -> bool:
        """Re-open ``mds-cmd`` if ``mds-ach repair`` re-created it (the StructChannels re-open themselves); True if
        it did."""
        if not replaced(self.cmd):
            return False
        try:
            new = self.open_raw(self.cmd.name, self.cmd.lock_timeout, create=False)
        except (ach.AchException, OSError, ValueError):
            return False
        old, self.cmd = self.cmd, new
        old.close()
        return True

    def close(self) -> None:
        for ch in (self.ref, self.state, self.collide, self.cmd, self.status, self.param, self.limits):
            ch.close()


class SecondWriterCheck:
    """Notices a second writer of the daemon's input (only the collision gate may write ``mds-ref-gated``).

    Ach does not record who wrote a frame, but the gate puts its ``mds-collide`` report right before each
    reference (the hold hand-off, docs/reliability.md G3), and more reports on their own. So between two looks
    the input gains at most as many frames as ``mds-collide`` did, plus one (a report counted at the previous
    look whose reference came after it). More is frames somebody else put: a tool or client (or a bridge with
    ``allow_ungated``) writing what the daemon executes. ``poll`` returns how many (0: none). A channel
    re-created or repaired (its sequence numbers start again) starts a new count."""

    def __init__(self, ref: StructChannel, collide: StructChannel) -> None:
        self._ref, self._collide = ref, collide  # StructChannels: .channel changes when a re-created file is re-opened
        self._last: tuple[int, int] | None = None
        self._carry = 0  # reports of the previous interval still without their reference (0 or 1)

    def poll(self) -> int:
        try:
            now = (self._ref.channel.last_seq, self._collide.channel.last_seq)  # the reference first, as the loop reads
        except Exception:  # a broken channel is reported by the reads themselves
            return 0
        last, self._last = self._last, now
        if last is None or now[0] < last[0] or now[1] < last[1]:
            self._carry = 0
            return 0
        refs, reports = now[0] - last[0], now[1] - last[1]
        allowed = reports + self._carry
        self._carry = min(1, max(0, allowed - refs))
        return max(0, refs - allowed)


# --- per-joint runtime state ---------------------------------------------------------------------------


@dataclass
class JointRuntime:
    """What the loop knows about one configured joint between cycles."""

    cfg: JointConfig
    ref_r: float  # last accepted reference from mds-ref-gated (joint rad)
    goal: float  # the reference after the joint's mode (clamped): what the limiter steers towards
    track: motion.Track  # the last target sent (float32 counts, as the log shows it): the limiter's state
    ref: float  # the target commanded now (full precision; state.ref)
    mode: int = mds.MDS_REF_MODE_REF
    enabled: bool = True  # commands are sent (config enabled and not disabled at run time)
    pos: float = math.nan  # the last trusted position
    vel: float = 0.0
    cur: float = 0.0
    ref_c: float = 0.0
    last_reply: float = -math.inf  # monotonic time of the last trusted position reply
    last_heard: float = -math.inf  # ... of the last position reply of any kind (staleness)
    trusted: bool = True  # False after an implausible reply, until REPLIES_TO_TRUST consistent ones
    suspect: tuple[float, float] | None = None  # (q, t) of the last in-range reply while not trusted
    consistent: int = 0  # consistent replies in a row while not trusted
    reseed: bool = True  # the track follows trusted replies until a MOVETO states that position
    resume_at: float = -math.inf  # after a MOVETO that reached the interface late: no target before this time
    pipeline_reseed: bool = False  # ask the pipeline to restart the joint's reference where it is, once known
    goal_prev: float = math.nan  # the goal when the previous target was computed, and when: the goal's velocity
    goal_t: float = -math.inf
    sent_counts: float | None = None  # float32 counts of the last MOVETO that went out completely
    ref_c_send: float = math.nan
    ack_due: float = math.inf  # MOVETO ACK expected before this time
    hold: float | None = None  # after a setup command: hold until ref_r differs from this
    flags: int = 0
    homing_since: float | None = None
    # False after ZERO_ENCODER / RESET (or a HOME that did not settle): the count no longer has its calibrated zero
    # at the ROM middle, so targets and replies would be in a shifted frame. No target, no position until HOME.
    referenced: bool = True
    chase: tuple[float, float, float] | None = None  # mode 2/3 at a chase's start: (reported position, target, gap)
    drift: tuple[float, float] | None = None  # mode 2/3: (target, direction) of a follow since the reply last rested
    rest: tuple[float, float] | None = None  # mode 2/3: (reported position, since when) it stays within FOLLOW_SETTLED
    follow_fault: bool = False  # mode 2/3 holds: its replies and its motion disagree (cleared by ENABLE or HOME)


@dataclass
class Command:
    """A setup command for the loop; ``done`` is set with ``result``/``message`` when handled."""

    code: int
    address: int = 0
    value: float = 0.0
    seq: int = 0
    done: threading.Event = field(default_factory=threading.Event)
    result: int = ds.CMD_OK
    message: str = ""


class Stats:
    """Loop timing over a sliding window of cycles (ring buffers; the first cycle has no period)."""

    def __init__(self, window: int) -> None:
        self.window = window
        self.period_err = np.zeros(window)
        self.wake = np.zeros(window)
        self.cpu = np.zeros(window)
        self.load = np.zeros(window)
        self.n = 0  # cycles recorded
        self.n_period = 0  # period errors recorded

    def add(self, period_err: float | None, wake: float, cpu: float, load: float) -> None:
        i = self.n % self.window
        self.wake[i], self.cpu[i], self.load[i] = wake, cpu, load
        self.n += 1
        if period_err is not None:
            self.period_err[self.n_period % self.window] = period_err
            self.n_period += 1

    def view(self, a: np.ndarray) -> np.ndarray:
        return a[: min(self.n_period if a is self.period_err else self.n, self.window)]


# --- the loop ----------------------------------------------------------------------------------------------


class DaemonLoop:
    """The MDS driver loop; ``cycle()`` is one period, ``run()`` the scheduled thread body."""

    def __init__(
        self,
        table: JointTable,
        io: CanIO,
        channels: DaemonChannels,
        *,
        rate_hz: float = 1.0 / mds.MDS_LOOP_PERIOD,
        reply_wait: float | None = None,
        stale_after: float | None = None,
        filter_length: float | None = None,
        collide_gate: bool = True,
        nocan: bool = False,
        rt_priority: int = 0,
        clock: Callable[[], float] = time.monotonic,
        limits: EffectiveLimits | None = None,
        estop_latch: Path | None = None,
    ) -> None:
        """``estop_latch``: the file that keeps an e-stop latched across restarts (the daemon passes
        ``estop.default_latch_path()``; None: in memory only)."""
        problem = rate_problem(rate_hz)
        if problem:
            raise ValueError(problem)
        # The one limit authority (issue #17): URDF & joint table, published on mds-limits at start and the
        # range every target is clamped to here, so the daemon clamps exactly what every entry point refuses.
        self.limits = effective_limits.compute(table) if limits is None else limits
        self.physical: dict[int, JointConfig] = {j.address: j for j in table}  # the ROM: replies are judged on it
        table = effective_limits.narrow_table(table, self.limits)
        self.table = table
        self.io = io
        self.ch = channels
        self.rate = rate_hz
        self.period = 1.0 / rate_hz
        self.reply_wait = self.period * 0.5 if reply_wait is None else reply_wait
        self.stale_after = STALE_AFTER if stale_after is None else stale_after
        self.ack_timeout = max(2.5 * self.period, 0.05)
        self.L = filters.filter_length(rate_hz) if filter_length is None else filter_length
        self.bounds = table.motion_bounds()
        self.collide_gate = collide_gate
        self.nocan = nocan
        self.rt_priority = rt_priority
        self.clock = clock
        io.clock = clock  # what went out is stamped on the loop's clock (see ``_send``)
        # The longest a MOVETO may go out after the time it was limited for (see ``_send``).
        self.late_send = late_send_tolerance(self.bounds, self.period)
        self.follow_step = min(FOLLOW_SPEED, self.bounds.max_velocity) * self.period  # rad per cycle (modes 2, 3)
        self.follow_gap = max(FOLLOW_GAP, 1.5 * self.follow_step)
        self.joints: dict[int, JointRuntime] = {
            j.address: JointRuntime(j, ref_r=j.home, goal=j.home, track=motion.Track(j.home), ref=j.home,
                                    enabled=j.enabled)
            for j in table
        }
        self._fixed_frames = {
            j.address: (mcb.encode_set_acceleration(j.address, table.accel_counts(j)),
                        mcb.encode_trajectory_mode(j.address, mcb.TrajectoryMode.MOVETO),
                        mcb.encode_trajectory_period(j.address, table.trajectory_period)) for j in table}
        self.state = MDS_STATE()
        table.fill_state(self.state)
        self.collide = MDS_COLLIDE()
        self.status = ds.MDS_DAEMON_STATUS(version=ds.DAEMON_STATUS_VERSION, pid=os.getpid())
        self.status.rate_hz, self.status.bitrate, self.status.nocan = rate_hz, io.bitrate, int(nocan)
        self.status.stale_after, self.status.filter_length = self.stale_after, self.L
        self.status.max_velocity, self.status.max_acceleration = self.bounds.max_velocity, self.bounds.max_acceleration
        self.status.max_interval = self.bounds.max_interval
        # Collaborative mode (issue #31): the hands' and elbows' Cartesian speed, on the same tracks.
        self.collab = CollaborativeGuard(table, self.bounds, on=table.collaborative)
        self.mode_log: ModeSink | None = None  # the daemon's --can-log gets the mode changes (ModeLog)
        self.status.collaborative, self.status.collaborative_speed = int(self.collab.on), self.collab.max_speed
        self.estop = EStopState(Latch(estop_latch))  # the category-1 e-stop (mds_ach.nodes.estop)
        self.status.estop = self.estop.state
        self.stats = Stats(max(50, min(2000, int(rate_hz * 10))))
        self._stats_every = max(1, round(rate_hz * WINDOW_STATS_PERIOD))  # cycles between window statistics
        self.commands: queue.SimpleQueue[Command] = queue.SimpleQueue()
        self._cmd_buf = bytearray(max(ctypes.sizeof(MDS_CMD), channels.cmd.data_size))
        self.bus_state = ds.BUS_STATE_ACTIVE
        self.unknown_addresses: set[int] = set()
        self.cycle_count = 0
        self._last_start: float | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()  # guards snapshot() against the loop thread
        self._snapshot = ds.MDS_DAEMON_STATUS()
        self._warned: set[str] = set()
        self._ref_unreadable = False  # the last read of mds-ref-gated failed (e.g. left corrupt by a dead writer)
        self._writers = SecondWriterCheck(channels.ref, channels.collide)
        self._warnings = RateLimitedLog(logger_fn(log))  # repeats counted, summarized every 5 s
        self._answered: set[int] = set()
        self._first_reply: dict[int, tuple[float, float]] = {}  # address -> (q, t) of its first reply to the query
        self.start_time = clock()
        self.status.start_time = self.start_time
        self._param = self.table.to_param()  # the joint table does not change while the daemon runs
        self._param_at = -math.inf

    # --- start-up --------------------------------------------------------------------------------------

    def start_up(self, listen: float = 2.0, queries: int = 8) -> int:
        """Publish ``mds-param`` and ``mds-limits``, read where the robot is and start the reference there (no step).

        Joints that answer start at their measured position (their tracks are re-seeded there); the others
        show the configured home pose and get no target until they answer. It asks ``queries`` times within
        ``listen`` s and returns as soon as every joint answered (under CPU load replies come late: a short window
        made a joint that was merely slow show home and then jump to where it is). No motion frame is sent until a
        reference changes. Old frames on ``mds-ref-gated``/``mds-cmd`` are skipped. Returns how many joints answered.
        """
        self._put(self.ch.param, self._param)
        self._param_at = self.clock()
        self._put(self.ch.limits, self.limits.to_msg(now=self.clock()))
        self._log_mode(self.clock())
        for ch in (self.ch.ref, self.ch.cmd):
            try:
                ch.flush()
            except Exception as exc:  # a corrupt channel: reported on every read later
                self._channel_error(getattr(ch, "name", "?"), exc)
        for _ in range(max(1, queries)):
            self.io.send(mcb.encode_query_positions())
            deadline = self.clock() + listen / max(1, queries)
            while self.clock() < deadline:
                msg = self.io.recv(max(0.0, deadline - self.clock()))
                if msg is not None:
                    self._handle(msg, self.clock())
                if all(math.isfinite(jr.pos) for jr in self.joints.values()):
                    break
            if all(math.isfinite(jr.pos) for jr in self.joints.values()):
                break
        if self.estop.found_at_start:
            self.estop.since = self.status.estop_time = self.clock()
            log.error("e-stop latched (%s): every drive gets DISABLE; nothing moves until `mds-ach estop reset`, "
                      "then `mds-ach enable all`", self.estop.latch.path)
            self.estop.pending_disable = {jr.cfg.address for jr in self.joints.values() if jr.cfg.enabled}
            self._estop_disable()
        answered = 0
        for jr in self.joints.values():
            if math.isfinite(jr.pos):
                jr.ref_r = jr.goal = jr.pos  # hold here until mds-ref-gated says otherwise
                answered += 1
            jr.ref_c_send = jr.ref
        self._fill_state(self.clock())
        self.state.time = time.monotonic()
        self._put(self.ch.state, self.state)
        if answered == 0:
            log.warning("no joint answered the position query; starting from the configured home pose")
        else:
            missing = [jr.cfg.short for jr in self.joints.values() if not math.isfinite(jr.pos)]
            log.info("start-up: %d of %d joints answered%s", answered, len(self.joints),
                     f" (silent: {', '.join(missing)})" if missing else "")
        return answered

    # --- thread ------------------------------------------------------------------------------------------

    def start(self) -> None:
        self._thread = threading.Thread(target=self.run, name="mds-daemon-loop", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _go_realtime(self) -> None:
        """Ask for ``rt_priority`` (SCHED_FIFO) for this thread only and, once granted, lock the process's memory;
        record the outcome in ``mds-daemon-status`` and say it once. Under CPU load a normal-priority loop waits
        behind every busy process (seconds, measured with 3 CPU hogs); a SCHED_FIFO one runs first. It never
        busy-waits (``sleep_until``), and the threads it creates start at normal priority (SCHED_RESET_ON_FORK).
        The other threads (ROS executor, DDS) stay at normal scheduling with nice -10: they share the interpreter
        lock with the loop, and one preempted while holding it stalled the loop (about 4 times as often at nice 0,
        100 Hz beside 3 CPU hogs)."""
        problems = glibc.tune_thread(self.rt_priority, name=LOOP_THREAD_NAME)
        refused = [p for p in problems if p.startswith("SCHED_FIFO")]
        for problem in problems:
            if problem not in refused:
                log.warning("loop thread: %s", problem)
        try:
            policy, priority = glibc.thread_scheduling()
        except OSError:
            policy, priority = 0, 0
        self.status.loop_policy, self.status.loop_priority = policy, priority
        if policy not in ds.REALTIME_POLICIES:
            if self.rt_priority <= 0:
                log.info("loop thread: real-time priority off (rt_priority 0): %s", WITHOUT_RT)
            else:
                log.warning("loop thread runs WITHOUT a real-time priority (%s): %s. Real-time scheduling is %s",
                            refused[0].split(";")[0] if refused else f"SCHED_FIFO {self.rt_priority} not granted",
                            WITHOUT_RT, RT_HOWTO)
            return
        locked = glibc.lock_memory()
        self.status.memory_locked = int(locked is None)
        reniced = glibc.renice_other_threads(OTHER_THREADS_NICE)
        log.info("loop thread: %s %d%s%s", ds.LOOP_POLICY_NAMES.get(policy, policy), priority,
                 ", memory locked (mlockall)" if locked is None else
                 f"; memory not locked ({locked}): a page fault may still delay a cycle",
                 f"; the other threads at nice {OTHER_THREADS_NICE}" if reniced is None else
                 f"; the other threads at their nice value ({reniced}): one preempted while it holds Python's "
                 "interpreter lock delays the loop longer")

    def run(self) -> None:
        """Absolute-time schedule: deadlines at start + k*period; a missed deadline is an overrun and the
        schedule skips to the next future slot (never a burst of catch-up cycles)."""
        self._go_realtime()
        # Everything allocated so far lives for the whole run: keep it out of the cyclic GC's full passes,
        # whose pauses would otherwise land in the loop.
        gc.collect()
        gc.freeze()
        next_deadline = self.clock()
        try:
            while not self._stop.is_set():
                sleep_until(next_deadline)
                start = self.clock()
                self.cycle(deadline=next_deadline, start=start)
                next_deadline += self.period
                now = self.clock()
                if now > next_deadline:
                    missed = math.ceil((now - next_deadline) / self.period)
                    self.status.overruns += 1
                    next_deadline += missed * self.period
        except Exception:
            log.exception("daemon loop stopped by an internal error")
            raise

    def submit(self, code: int, address: int = 0, value: float = 0.0, seq: int = 0) -> Command:
        """Queue a setup command for the next cycle (thread-safe); wait on ``.done`` for the result."""
        cmd = Command(code, address, value, seq)
        self.commands.put(cmd)
        return cmd

    def snapshot(self) -> ds.MDS_DAEMON_STATUS:
        """A consistent copy of the last published status (for the diagnostics publisher thread)."""
        with self._lock:
            return ds.MDS_DAEMON_STATUS.from_buffer_copy(self._snapshot)

    # --- one cycle ---------------------------------------------------------------------------------------

    def cycle(self, deadline: float | None = None, start: float | None = None) -> None:
        start = self.clock() if start is None else start
        deadline = start if deadline is None else deadline
        cpu0 = time.thread_time()
        self.io.counters.take_bits()  # bus load counts the frames sent and received during this cycle
        if self._last_start is not None and start - self._last_start > STALL_PERIODS * self.period:
            self._stalled(start - self._last_start)
        self._read_commands()
        self._run_commands(start)
        # The reference first, then the collision report: the gate publishes a hold's report before the held
        # reference, so a held reference read here always comes with its hold (the arm is withheld, never braked
        # past the point where the gate stopped it).
        ref = self._latest(self.ch.ref)  # a corrupt or silent channel means no new reference: hold
        collide = self._latest(self.ch.collide)
        if collide is not None:
            self.collide = collide
            ctypes.memmove(ctypes.addressof(self.state.collide), ctypes.addressof(collide), ctypes.sizeof(collide))
        foreign = self._writers.poll()
        if foreign:
            self._warn_rate("second-writer", f"{DAEMON_INPUT}: {foreign} frame(s) not put by the collision gate "
                                             "(no mds-collide report before them): another process writes the "
                                             "daemon's input; only the gate may (legacy clients write "
                                             f"{mds.MDS_CHAN_REF_NAME}, the mux's 'direct' input)")
        if self.ch.ref.bad_frames:
            self._warn_once("ref-size", f"{self.ch.ref.name}: frames of the wrong size ignored (MDS_REF is "
                                        f"{ctypes.sizeof(MDS_REF)} bytes)")
        if ref is not None:
            self.status.refs_received += 1
            if self._ref_unreadable:
                self._resume_ref()
            self._accept_ref(ref)
        self._drain(start)  # late replies and ACKs of the previous cycle
        self._check_acks(start)
        self._update_goals(start)
        self._send_targets()
        self._query(start)
        now = self.clock()
        self._fill_state(now)
        self.state.time = time.monotonic()
        self._put(self.ch.state, self.state)
        if start - self._param_at >= PARAM_PERIOD:  # the same table again, for stations that connected since
            self._put(self.ch.param, self._param)
            self._param_at = start
        self._publish_status(start, deadline, cpu0)

    def _latest(self, channel):
        """Newest new frame of an input channel; a broken channel (e.g. a writer killed mid-put) is reported,
        never allowed to stop the loop: it reads as 'nothing new'."""
        try:
            return channel.latest()
        except Exception as exc:
            if channel is self.ch.ref:
                self._ref_unreadable = True
            self._channel_error(channel.name, exc)
            return None

    def _resume_ref(self) -> None:
        """The reference input is readable again after an outage (e.g. repaired after a writer died mid-put).
        Upstream kept moving while the daemon held: the limiter ramps every joint to the new reference."""
        self._ref_unreadable = False
        log.warning(f"{self.ch.ref.name} readable again: ramping to its reference within the motion bounds")

    def _stalled(self, gap: float) -> None:
        """This loop did not run for ``gap`` s (a suspended process, a starved CPU): say so (every stall of 0.5 s
        or more, shorter ones at most every 5 s). The joints were not sent anything meanwhile, so the limiter
        starts every target from rest where it was."""
        self.status.stalls += 1
        self.status.stall_max = max(self.status.stall_max, gap)
        text = (f"control loop stalled: {gap:.3f} s between two cycles (period {self.period:.3f} s, "
                f"{self.status.stalls} stalls so far); targets ramp from where they were")
        if gap >= 0.5:
            log.warning(text)
        else:
            self._warn_rate("stall", text)

    def _put(self, channel, frame) -> None:
        try:
            channel.put(frame)
        except Exception as exc:
            self._channel_error(channel.name, exc)

    def _channel_error(self, name: str, exc: Exception) -> None:
        if isinstance(exc, ach.AchException) and exc.status == ach.ACH_LOCKED:  # skipped, not broken
            self.status.lock_timeouts += 1
            self._warn_rate(f"lock-{name}", f"channel {name}: {exc}; skipped this cycle ({self.status.lock_timeouts} "
                                            "so far; `mds-ach repair --check` names the holder)")
            return
        self.status.channel_errors += 1
        self._warn_rate(f"channel-{name}", f"channel {name}: {exc} (`mds-ach repair` fixes a corrupt channel)")

    def _read_commands(self) -> None:
        """Every new mds-cmd frame in order (not just the newest: two quick commands must both count)."""
        for _ in range(mds.CHANNEL_FRAME_COUNT):
            try:
                status, size = self.ch.cmd.get(self._cmd_buf)
            except ach.AchException as exc:
                if self.ch.reopen_cmd():  # re-created by `mds-ach repair`: read the new file from the next cycle
                    log.warning(f"{mds.MDS_CHAN_BOARD_CMD_NAME} was re-created: re-opened it, commands are read again")
                else:
                    self._channel_error(mds.MDS_CHAN_BOARD_CMD_NAME, exc)
                return
            if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
                return
            if size != ctypes.sizeof(MDS_CMD):
                self._warn_once(f"cmd-size-{size}", f"mds-cmd: ignored a {size}-byte frame (MDS_CMD is "
                                                    f"{ctypes.sizeof(MDS_CMD)} bytes)")
                continue
            c = MDS_CMD.from_buffer_copy(self._cmd_buf[:size])
            self.commands.put(Command(c.cmd, c.address, c.value, c.seq))

    def _run_commands(self, now: float) -> None:
        while True:
            try:
                cmd = self.commands.get_nowait()
            except queue.Empty:
                return
            try:
                cmd.result, cmd.message = self._execute(cmd, now)
            except Exception as exc:  # a bad command must never stop the loop
                cmd.result, cmd.message = ds.CMD_FAILED, f"internal error: {exc}"
                log.exception("command %s failed", cmd)
            level = logging.INFO if cmd.result == ds.CMD_OK else logging.WARNING
            log.log(level, "command %s: %s", COMMAND_NAMES.get(cmd.code, cmd.code), cmd.message)
            self.status.cmd_seq, self.status.cmd_result = cmd.seq, cmd.result
            cmd.done.set()

    def _execute(self, cmd: Command, now: float) -> tuple[int, str]:
        if cmd.code == mds.MDS_CMD_MODE:
            return self._switch_mode(cmd, now)
        if cmd.code in (mds.MDS_CMD_ESTOP, mds.MDS_CMD_ESTOP_RESET):
            return self._estop_command(cmd, now)
        if self.estop.active and cmd.code in (mds.MDS_CMD_ENABLE, mds.MDS_CMD_HOME, mds.MDS_CMD_RESET,
                                              mds.MDS_CMD_ZERO_ENCODER):
            return ds.CMD_REFUSED, (f"{COMMAND_NAMES.get(cmd.code, cmd.code)} refused: the e-stop is latched "
                                    "(`mds-ach estop reset` first)")
        if cmd.code == mds.MDS_CMD_RESET_BUS:
            self.io.reopen()
            self.status.bus_resets += 1
            self.bus_state = ds.BUS_STATE_ACTIVE
            for jr in self.joints.values():
                # Frames may have been lost while the bus was down: send the current (limited) target again,
                # and let the pipeline restart where the joints stand instead of where it got to meanwhile.
                jr.sent_counts = None
                jr.pipeline_reseed = jr.enabled
            return ds.CMD_OK, f"CAN bus re-opened ({self.io.description})"
        if cmd.code not in COMMAND_NAMES:
            return ds.CMD_REFUSED, f"unknown command code {cmd.code}"
        if cmd.address == 0:
            targets = [jr for jr in self.joints.values() if jr.cfg.enabled]
        else:
            one = self.joints.get(cmd.address)
            if one is None:
                return ds.CMD_REFUSED, f"no joint at address 0x{cmd.address:02X}"
            if not one.cfg.enabled:
                return ds.CMD_REFUSED, f"{one.cfg.short} is disabled in the joint table: no frames go to it"
            targets = [one]
        build = {mds.MDS_CMD_ENABLE: mcb.encode_enable, mds.MDS_CMD_DISABLE: mcb.encode_disable,
                 mds.MDS_CMD_HOME: mcb.encode_home, mds.MDS_CMD_RESET: mcb.encode_reset,
                 mds.MDS_CMD_ZERO_ENCODER: mcb.encode_zero_encoder}[cmd.code]
        failed = [jr.cfg.short for jr in targets if not self.io.send(build(jr.cfg.address))]
        for jr in targets:
            if cmd.code == mds.MDS_CMD_DISABLE:
                jr.enabled = False
            else:
                jr.enabled = True
                # Hold where the joint is until its reference changes (see module doc); HOME moves it itself.
                # The next target starts from where the joint is then, and so does the pipeline's reference.
                jr.hold = jr.ref_r
                jr.sent_counts = None
                jr.ack_due = math.inf
                jr.reseed = jr.pipeline_reseed = True
                if cmd.code in (mds.MDS_CMD_RESET, mds.MDS_CMD_ZERO_ENCODER, mds.MDS_CMD_HOME):
                    # The count restarts: old readings are void.
                    jr.pos, jr.last_reply, jr.last_heard = math.nan, -math.inf, -math.inf
                    jr.trusted, jr.suspect, jr.consistent = True, None, 0
                    if cmd.code != mds.MDS_CMD_HOME:
                        self._unreference(jr, COMMAND_NAMES[cmd.code])
                elif math.isfinite(jr.pos) and jr.referenced:
                    # ENABLE: the node holds where it is, which is the latest trusted reply, not the last target
                    # (a disabled joint may have been moved by hand). A target in this very cycle starts there.
                    jr.track.reseed(jr.pos, jr.last_reply)
                jr.homing_since = now if cmd.code == mds.MDS_CMD_HOME else None
                if cmd.code in (mds.MDS_CMD_ENABLE, mds.MDS_CMD_HOME) and jr.follow_fault:
                    log.info("%s: follow fault cleared by %s", jr.cfg.short, COMMAND_NAMES[cmd.code])
                    jr.follow_fault = False
                jr.chase = jr.drift = None
        names = ", ".join(jr.cfg.short for jr in targets)
        if failed:
            return ds.CMD_FAILED, f"{COMMAND_NAMES[cmd.code]} not sent to {', '.join(failed)}: " \
                                  f"{self.io.counters.last_error}"
        return ds.CMD_OK, f"{COMMAND_NAMES[cmd.code]} sent to {names}"

    def _unreference(self, jr: JointRuntime, why: str) -> None:
        """The joint's count lost its calibrated zero (docs/reliability.md M2): it gets no target and shows no
        position until HOME re-establishes the frame. The node restarted its count at 0 where the joint stood; the
        daemon does not know that count exactly (the last reply is up to a period old and the joint may have been
        moving), and a frame off by any amount would move the limits and the collision model with it."""
        if jr.referenced:
            log.warning("%s: %s restarted the encoder count: the joint is unreferenced (no targets, no position) "
                        "until `home %s`", jr.cfg.short, why, jr.cfg.short)
        jr.referenced = False

    def _accept_ref(self, ref: MDS_REF) -> None:
        for a, jr in self.joints.items():
            entry = ref.joint[a]
            value, mode = entry.ref, entry.mode
            if not math.isfinite(value) or mode not in (0, 1, 2, 3):
                if not jr.flags & ds.JOINT_REFUSED:
                    self.status.refs_refused += 1
                    what = f"mode {mode}" if math.isfinite(value) else f"value {value}"
                    self._warn_rate(f"refuse-{a}", f"{DAEMON_INPUT}: {jr.cfg.short} {what} refused; holding "
                                                    f"{jr.ref_r:.4f}")
                jr.flags |= ds.JOINT_REFUSED
                continue
            jr.flags &= ~ds.JOINT_REFUSED
            if value != jr.ref_r and not jr.cfg.within_limits(value):
                self.status.refs_clamped += 1
                self._warn_rate(f"clamp-{a}", f"{DAEMON_INPUT}: {jr.cfg.short} {value:.4f} outside "
                                              f"[{jr.cfg.lower:.4f}, {jr.cfg.upper:.4f}]: clamped")
            jr.ref_r, jr.mode = value, mode

    def _update_goals(self, now: float) -> None:
        """Each joint's goal: its reference clamped to the limits, through its mode. A joint in mode 2 or 3
        without a trusted, fresh position holds its last target."""
        for jr in self.joints.values():
            cfg = jr.cfg
            jr.flags &= ~(ds.JOINT_CLAMPED | ds.JOINT_MOVING | ds.JOINT_LIMITED | ds.JOINT_SLOWED)
            if not cfg.within_limits(jr.ref_r):
                jr.flags |= ds.JOINT_CLAMPED
            if jr.hold is not None:
                if jr.ref_r == jr.hold:
                    continue
                jr.hold = None
            desired = cfg.clamp(jr.ref_r)
            known = self._known(jr, now)
            if jr.mode == mds.MDS_REF_MODE_REF:
                goal = desired
            elif jr.mode == mds.MDS_REF_MODE_REF_FILTER:
                goal = filters.ema_step(jr.goal, desired, self.L)
            else:  # MDS_REF_MODE_COMPLIANT, MDS_REF_MODE_ENC_FILTER
                goal = self._follow(jr, desired, known, now)
            if jr.mode not in (mds.MDS_REF_MODE_COMPLIANT, mds.MDS_REF_MODE_ENC_FILTER):
                jr.chase = jr.drift = None
            jr.goal = cfg.clamp(goal)

    def _follow(self, jr: JointRuntime, desired: float, known: bool, now: float) -> float:
        """Mode 2 (compliant) or 3 (encoder filter): the goal from the reported position, which the target follows
        at most ``follow_step`` per cycle; a chase that does not close faults (see FOLLOW_*). Holds the last target
        without a trusted position or after a fault."""
        held = jr.track.q
        if not known or jr.follow_fault:
            jr.chase = jr.drift = jr.rest = None
            return held
        gap = jr.pos - held
        sign = 1.0 if gap > 0 else -1.0
        if jr.rest is None or abs(jr.pos - jr.rest[0]) > FOLLOW_SETTLED:
            jr.rest = (jr.pos, now)  # the reported position moved: it rests from here, if it stays
        if now - jr.rest[1] >= max(FOLLOW_REST_TIME, 2.5 * self.period) or (
                jr.drift is not None and sign != jr.drift[1] and abs(gap) > 0.5 * self.follow_gap):
            jr.drift = None  # at rest (a push ended), or clearly behind its target: no drift
        elif jr.drift is None:
            jr.drift = (held, sign) if abs(gap) > FOLLOW_SETTLED else None
        elif (held - jr.drift[0]) * jr.drift[1] >= FOLLOW_DRIFT:
            self._follow_fault(jr, f"its target followed the reported position {FOLLOW_DRIFT:g} rad one way and that "
                                   "never came to rest: a push ends, an offset fed back does not")
            return held
        if abs(gap) <= self.follow_gap:
            jr.chase = None
        elif jr.chase is None or (gap > 0) != (jr.chase[2] > 0):
            jr.chase = (jr.pos, held, gap)
        else:
            ran = min((jr.pos - jr.chase[0]) * sign, (held - jr.chase[1]) * sign)  # both moved on, together
            if ran >= FOLLOW_FAULT_TRAVEL:
                self._follow_fault(jr, f"the reported position stays {abs(gap):.3f} rad ahead of the target chasing "
                                       f"it and moved on with it {ran:.3f} rad: the joint moves with its target, not "
                                       "where the replies say")
                return held
        followed = held + min(max(gap, -self.follow_step), self.follow_step)
        if jr.mode == mds.MDS_REF_MODE_COMPLIANT:
            return followed
        return filters.enc_filter_step(followed, desired, self.L)

    def _follow_fault(self, jr: JointRuntime, why: str) -> None:
        """Stop feeding a mode 2/3 joint's replies back: it holds its last target (modes 0/1 still move it) until
        ENABLE or HOME. Logged once per fault, flagged in ``mds-daemon-status`` (JOINT_FOLLOW_FAULT)."""
        jr.chase = jr.drift = None
        if not jr.follow_fault:
            jr.follow_fault = True
            log.error("%s: follow fault (mode %d): %s; holding at %.4f rad until `enable %s` or `home %s`",
                      jr.cfg.short, jr.mode, why, jr.track.q, jr.cfg.short, jr.cfg.short)

    def _known(self, jr: JointRuntime, now: float) -> bool:
        """Is the joint's position trusted, fresh and in the calibrated frame (``state.active``)?"""
        return jr.referenced and self._reading(jr, now)

    def _reading(self, jr: JointRuntime, now: float) -> bool:
        """Are the joint's replies trusted and fresh, in whatever frame its count is (a homing joint's)?"""
        return jr.trusted and math.isfinite(jr.pos) and now - jr.last_reply <= self.stale_after

    def _collision_held(self) -> frozenset[int] | None:
        """Joints not to command while ``mds-collide`` reports a predicted collision (``isCollide == 1``).

        Like the original, held targets go out as soon as the collision clears. Unlike the original, only the
        arm whose parts are flagged is held, so the gate's per-arm hold is not turned into a whole-robot stop;
        a report that flags no part (e.g. an external legacy checker) holds every joint. ``isCollide == 2`` is
        the gate's logged expert override and holds nothing. ``None`` means hold everything.
        """
        c = self.collide
        if not self.collide_gate or c.isCollide != 1:
            return frozenset()
        held: set[int] = set()
        if any(c.joint[i].isCollide for i in _LEFT_PARTS):
            held.update(_LEFT_ARM_ADDRESSES)
        if any(c.joint[i].isCollide for i in _RIGHT_PARTS):
            held.update(_RIGHT_ARM_ADDRESSES)
        return frozenset(held) if held else None

    def _send_targets(self) -> None:
        if self.estop.active:
            self._estop_cycle()
            return  # nothing else moves while the e-stop is latched
        held = self._collision_held()
        if held is None or held:
            self.status.collision_holds += 1
            if held is None:
                return
        if self.bus_state == ds.BUS_STATE_BUS_OFF:
            return  # nothing gets through; `mds-ach resetbus` re-opens the bus
        planned = self._cartesian_plan(held)
        for a, jr in self.joints.items():
            t = self.clock()  # the limiter counts the time up to these very frames
            if not self._sendable(a, jr, held, t):
                continue
            if jr.reseed:
                if not self._known(jr, t):
                    continue  # never command a joint from a position the daemon does not know
                # The first target after a re-seed states where the joint is (a zero step), and only once the goal
                # is elsewhere; the modes (mode 0's filter too) and the ramp start from there with the next cycle.
                q = jr.cfg.clamp(jr.track.q)
                if f32(jr.cfg.to_counts(q)) == f32(jr.cfg.to_counts(jr.goal)):
                    continue
                jr.goal = jr.goal_prev = q
                jr.goal_t = t
            elif a in planned:
                q = self.collab.retime(jr.track, planned[a], jr.goal, t, jr.cfg)
            elif self.collab.on and a in self.collab.members:
                continue  # it became sendable after the plan (its resume time passed): planned next cycle
            else:
                q = self._limited(jr, t)
            self._send(a, jr, q, t)

    def _sendable(self, a: int, jr: JointRuntime, held: frozenset[int], t: float) -> bool:
        """May the joint be sent a target at ``t``?"""
        if not jr.enabled or not jr.referenced or jr.hold is not None or jr.homing_since is not None or a in held:
            return False  # (an unreferenced joint's target would be in a shifted frame: nothing until HOME)
        if t - jr.last_heard > self.stale_after:
            return False  # a silent node gets nothing: when it answers again, it goes on from its last target
        return t >= jr.resume_at  # else its last MOVETO reached the interface late (``_send``)

    def _cartesian_plan(self, held: frozenset[int]) -> dict[int, float]:
        """Collaborative mode: the velocities of this cycle's upper-body steps that keep the hands and elbows within
        the Cartesian bound (``CollaborativeGuard.plan``); empty in normal mode. The joints' own limiter runs here,
        at one instant for the group, and each planned joint is sent at that velocity (``retime``)."""
        if not self.collab.on:
            return {}
        t = self.clock()
        proposals: dict[int, float] = {}
        tracks: dict[int, motion.Track] = {}
        for a in self.collab.addresses:
            jr = self.joints.get(a)
            if jr is None:
                continue
            tracks[a] = jr.track
            if self._sendable(a, jr, held, t) and not jr.reseed:
                proposals[a] = self._limited(jr, t)
        planned = self.collab.plan(tracks, proposals, t)
        scaled = self.collab.last
        st = self.status
        st.cartesian_speed = scaled.speed
        if scaled.lam > 0:
            st.cartesian_slowed += 1
            for a in proposals:
                self.joints[a].flags |= ds.JOINT_SLOWED
        if not scaled.within:
            st.cartesian_braking += 1
            if t - self.collab.switched_at > self.collab_ramp:
                self._warn_rate("cartesian", f"collaborative mode: the hands/elbows at {scaled.speed * 1e3:.0f} mm/s "
                                             f"> {self.collab.max_speed * 1e3:.0f} mm/s even braking at the joint "
                                             "bounds")
        else:
            st.cartesian_speed_max = max(st.cartesian_speed_max, scaled.speed)
        return planned

    @property
    def collab_ramp(self) -> float:
        b = self.bounds
        return cartesian_ramp_time(b.max_velocity, b.max_acceleration, b.max_interval)

    def _switch_mode(self, cmd: Command, now: float) -> tuple[int, str]:
        """MDS_CMD_MODE: value 1 collaborative, 0 normal. Never a step: the joints ramp into the new bound."""
        if cmd.value not in (0.0, 1.0):
            return ds.CMD_REFUSED, f"mode {cmd.value:g}: use 1 (collaborative) or 0 (normal)"
        on = cmd.value == 1.0
        changed = self.collab.switch(on, now)
        self.status.collaborative = int(on)
        if changed and on:
            self.status.cartesian_speed_max = 0.0
        if changed:
            self._log_mode(now)
        bound = f"hands and elbows <= {self.collab.max_speed * 1e3:.0f} mm/s"
        what = f"collaborative ({bound})" if on else "normal"
        return ds.CMD_OK, f"mode {what}" + ("" if changed else " (already)")

    def _estop_command(self, cmd: Command, now: float) -> tuple[int, str]:
        """MDS_CMD_ESTOP: latch and stop (category 1); MDS_CMD_ESTOP_RESET: clear a latch whose stop is complete."""
        e = self.estop
        if cmd.code == mds.MDS_CMD_ESTOP:
            if not e.trigger(now, "mds-cmd" if cmd.seq else "input"):
                return ds.CMD_OK, f"e-stop already latched ({ds.ESTOP_NAMES[e.state]})"
            self.status.estop, self.status.estop_time = e.state, now
            log.error("E-STOP: every joint brakes at the motion bounds, then every drive gets DISABLE")
            return ds.CMD_OK, "e-stop latched: braking, then DISABLE"
        if e.state == ds.ESTOP_OFF:
            return ds.CMD_OK, "e-stop reset: it was not latched"
        if e.state == ds.ESTOP_STOPPING:
            return ds.CMD_REFUSED, "e-stop reset refused: the stop is not complete yet (the drives are not disabled)"
        e.latch.clear()
        e.state = ds.ESTOP_OFF
        self.status.estop = e.state
        return ds.CMD_OK, "e-stop reset: the drives stay disabled until `mds-ach enable all` (each joint restarts " \
                          "where it stands)"

    def _estop_cycle(self) -> None:
        """One cycle of a latched e-stop: brake every joint the daemon commands as hard as the acceleration bound
        allows (its track: audited like every target), then, once the targets stand still and the joints settled
        (at most ``SETTLE_TIMEOUT``, all in all ``BRAKE_TIMEOUT``), DISABLE every drive."""
        e = self.estop
        if e.state == ds.ESTOP_STOPPED:
            return
        b = self.bounds
        a_max = motion.LIMIT_MARGIN * b.max_acceleration
        if self.bus_state != ds.BUS_STATE_BUS_OFF and not e.pending_disable:
            for a, jr in self.joints.items():
                if not jr.enabled or not jr.referenced or jr.reseed or jr.homing_since is not None:
                    continue  # (never sent since a re-seed: nothing to brake; homing: DISABLE stops it)
                t = self.clock()
                if t - jr.last_heard > self.stale_after or t < jr.resume_at:
                    continue
                h = b.interval(t - jr.track.t)
                v0 = jr.track.previous_velocity(t, b)
                if v0 == 0.0 or h <= 0:
                    continue
                q = jr.cfg.clamp(jr.track.q + brake_velocity(v0, a_max, h) * h)
                jr.goal = jr.goal_prev = q
                self._send(a, jr, q, t)
        now = self.clock()
        commanded = [jr for jr in self.joints.values() if jr.enabled and jr.referenced]
        if any(jr.track.previous_velocity(now, b) != 0.0 for jr in commanded) and now - e.since < BRAKE_TIMEOUT:
            return
        if e.at_rest_since is None:
            e.at_rest_since = now
        settled = all(abs(jr.vel) < REST_SPEED for jr in commanded if self._known(jr, now))
        if not e.pending_disable and (settled or now - e.at_rest_since >= SETTLE_TIMEOUT
                                      or now - e.since >= BRAKE_TIMEOUT):
            e.pending_disable = {a for a, jr in self.joints.items() if jr.cfg.enabled}
        if e.pending_disable:
            self._estop_disable()

    def _estop_disable(self) -> None:
        """DISABLE (MCB command 0x1A) to every drive still pending; ESTOP_STOPPED once all went out."""
        e = self.estop
        for a in sorted(e.pending_disable):
            if self.io.send(mcb.encode_disable(a)):
                e.pending_disable.discard(a)
                jr = self.joints[a]
                jr.enabled = False
                jr.hold = jr.ref_r  # (an ENABLE after the reset re-seeds it where it stands)
        if not e.pending_disable:
            e.state = ds.ESTOP_STOPPED
            self.status.estop = e.state
            log.error("E-STOP: every drive disabled %.3f s after the e-stop; nothing moves until `mds-ach estop "
                      "reset`, then `mds-ach enable all`", self.clock() - e.since)

    def _log_mode(self, now: float) -> None:
        if self.mode_log is not None:
            self.mode_log(now, self.collab.max_speed if self.collab.on else 0.0)

    def _limited(self, jr: JointRuntime, t: float) -> float:
        """The joint's goal through the motion bounds from its track, at time ``t``; counted when it differs."""
        cfg = jr.cfg
        dt = t - jr.goal_t
        goal_velocity = (jr.goal - jr.goal_prev) / dt if 0 < dt <= self.bounds.max_interval else 0.0
        jr.goal_prev, jr.goal_t = jr.goal, t
        q = motion.limit(jr.track, jr.goal, t, self.bounds, desired_velocity=goal_velocity, lower=cfg.lower,
                         upper=cfg.upper)
        q = cfg.clamp(q)  # never needed with regular cycles: the limiter brakes for the limits itself
        if abs(q - jr.goal) > LIMIT_TOLERANCE:
            jr.flags |= ds.JOINT_LIMITED
            self.status.targets_limited += 1
            self.status.joint_limited[cfg.address] += 1
        return q

    def _send(self, a: int, jr: JointRuntime, q: float, t: float) -> None:
        """The 4-frame SET sequence for target ``q`` (limited for time ``t``) if its float32 counts changed (or a
        re-send is due).

        A step's time is ``t``, the moment its target was limited for: the track records the MOVETO at ``t`` and the
        CAN log stamps it with ``t`` (``CanIO.send(at=t)``), so the daemon and the auditor judge the same step with
        the same numbers at every rate, whatever the jitter. The frame must reach the interface within ``late_send``
        of ``t``: a MOVETO that would go out later (this thread was preempted or stopped meanwhile) is not sent (its
        step was sized for a moment long past; the next cycle limits afresh). The frame may still have reached the
        wire as late as the send returned (preempted inside it): ``_rest_after`` holds the joint's next target back
        just long enough that its step, counted from this stamp, never reaches the wire faster than the bound.
        """
        jr.ref = q
        c32 = f32(jr.cfg.to_counts(q))
        if c32 == jr.sent_counts and not jr.reseed:
            return
        accel, mode, period = self._fixed_frames[a]
        # The original daemon's sequence (mcb.encode_position_sequence), three of its frames precomputed.
        moveto = mcb.encode_moveto(a, c32)
        for frame in (accel, moveto, mode, period):
            if frame is moveto and self.clock() - t > self.late_send:
                self._late_send(jr, self.clock() - t)
                return
            if not self.io.send(frame, at=t if frame is moveto else None):
                return  # counted as a tx error; the target goes out again next cycle
            if frame is moveto:  # it is on the bus (and in the log): this is what the node was told
                sent = jr.cfg.to_joint(c32)
                jr.track.advance(sent, t, self.bounds)
                jr.reseed = False
                jr.ref_c_send = sent
                jr.ack_due = self.io.last_sent + self.ack_timeout
                jr.flags |= ds.JOINT_MOVING
                self._rest_after(jr, t)
        jr.sent_counts = c32

    def _late_send(self, jr: JointRuntime, late: float) -> None:
        """A target withheld because this thread was held up between limiting it and sending it."""
        jr.ref = jr.track.q  # the joint is still told the last target (the state shows what was sent)
        self.status.stalls += 1
        self._warn_rate("late-send", f"{jr.cfg.short}: target withheld, {1e3 * late:.1f} ms late (the loop was "
                                     f"preempted between limiting and sending it); the next cycle limits it afresh")

    def _rest_after(self, jr: JointRuntime, t: float) -> None:
        """After a MOVETO stamped ``t`` whose send returned ``d`` s later (it reached the wire somewhere between):
        the joint's next target waits until its step cannot reach the wire faster than the velocity bound.

        The limiter moves at most ``LIMIT_MARGIN * v_max`` over the logged interval ``h`` (up to ``max_interval``),
        and the wire spacing is at least ``h - d``: waiting until ``h >= d / (1 - LIMIT_MARGIN)`` keeps it within
        ``v_max`` (a send of d = 1 ms waits 10 ms: no cost at 100 Hz and below). A longer wait is cut short once the
        logged interval exceeds ``max_interval`` (the next step starts from rest: at most ``S0`` =
        ``LIMIT_MARGIN * min(v_max, a_max * max_interval) * max_interval``) and the wire spacing is ``S0 / v_max``.
        """
        b, sent = self.bounds, self.io.last_sent
        d = max(sent - t, 0.0)
        from_rest = motion.LIMIT_MARGIN * min(b.max_velocity, b.max_acceleration * b.max_interval) * b.max_interval
        jr.resume_at = min(t + d / (1.0 - motion.LIMIT_MARGIN),
                           max(t + b.max_interval + 1e-6, sent + from_rest / b.max_velocity))
        if d > self.late_send:
            self.status.stalls += 1
            self._warn_rate("slow-send", f"{jr.cfg.short}: a target took {1e3 * d:.1f} ms to reach the interface (the "
                                         f"loop was preempted inside the send); its next target waits "
                                         f"{1e3 * (jr.resume_at - sent):.0f} ms so it cannot reach the wire too soon")

    def _check_acks(self, now: float) -> None:
        for jr in self.joints.values():
            if now > jr.ack_due:
                jr.ack_due = math.inf
                jr.sent_counts = None  # send the target again
                self.status.acks_missing += 1

    def _query(self, start: float) -> None:
        # Stale joints are not waited for (their replies are still taken when they come); when every joint
        # is silent the whole window is used, in case the robot just came back.
        expected = {a for a, jr in self.joints.items() if start - jr.last_heard <= self.stale_after}
        expected = expected or set(self.joints)
        self.status.replies_expected = len(expected)
        self._answered = set()
        self._first_reply.clear()  # (late replies of the previous query count as its own, see _second_reply)
        if not self.io.send(mcb.encode_query_positions()):
            self.status.replies_received = 0
            return
        deadline = start + self.reply_wait
        # The replies trickle in one frame time apart. Waking for each as it comes was ~20 wake-ups a cycle, a
        # quarter of the daemon's CPU at rest. Instead the loop takes what is there and, while replies are missing,
        # sleeps until the earliest moment they can all be in: each needs its bits on the wire, even without a stuff
        # bit. The cycle ends at most a frame time later (the state is published once every reply is in), after a few
        # wake-ups.
        # (A test's simulated clock moves only inside recv: there the loop waits in recv as before.)
        batched = self.clock is time.monotonic
        frame_min = budget.STUFF_FREE_BITS / self.io.bitrate
        while not expected <= self._answered:
            remaining = deadline - self.clock()
            if remaining <= 0:
                break
            msg = self.io.recv(0.0 if batched else remaining)
            if msg is not None:
                self._handle(msg, self.clock())
            elif not batched:
                break
            else:
                sleep_until(min(self.clock() + len(expected - self._answered) * frame_min, deadline))
        self.status.replies_received = len(self._answered)

    def _drain(self, now: float) -> None:
        """Frames that arrived since the last reply window, each dated by its receive timestamp."""
        self._answered = set()
        wall = time.time()
        for _ in range(10_000):
            msg = self.io.recv(0)
            if msg is None:
                return
            waited = min(max(0.0, wall - msg.timestamp), self.period) if msg.timestamp else 0.0
            self._handle(msg, now - waited)

    def _handle(self, msg, now: float) -> None:
        """One received frame: positions, ACKs, node errors, bus errors, junk -- each counted."""
        if msg.is_error_frame:
            self._bus_error(msg)
            return
        if msg.is_extended_id or msg.is_remote_frame or msg.dlc != mcb.DLC or len(msg.data) != mcb.DLC:
            self.status.malformed_frames += 1
            self._warn_rate("malformed", f"malformed frame ignored: {msg}")
            return
        if msg.arbitration_id != mcb.HOST_SID:
            self.status.unknown_node_frames += 1  # another host's traffic, or a node on a wrong ID
            return
        pos = mcb.decode_position(msg.data)
        if pos is not None:
            address, counts = pos
            jr = self.joints.get(address)
            if jr is None:
                self._unknown(address)
                return
            if not math.isfinite(counts):
                self.status.malformed_frames += 1
                return
            self._answered.add(address)
            q = jr.cfg.to_joint(counts)
            if self._second_reply(jr, q, now):
                return
            self._position_reply(jr, q, now)
            return
        data = msg.data
        if data[7] == Response.ACK:  # fast path: the 4 ACKs of every SET sequence
            jr = self.joints.get(data[4] | data[5] << 8)
            if jr is not None:
                if data[6] == mcb.Command.SET and data[3] == StateArg.MOVETO_TARGET:
                    jr.ack_due = math.inf
                return
        frame = mcb.decode(msg.arbitration_id, data)
        jr = self.joints.get(frame.address)
        if jr is None:
            self._unknown(frame.address)
            return
        if frame.command == Response.STATE:
            if frame.argument == StateArg.CURRENT:
                jr.cur = float(frame.value)
            elif frame.argument == StateArg.DESIRED_POSITION and math.isfinite(frame.value):
                jr.ref_c = jr.cfg.to_joint(frame.value)
        elif frame.command in (Response.WARNING, Response.ERROR):
            if frame.command == Response.WARNING and frame.argument == mcb.ErrorCode.TRAJECTORY_BUFFER_EMPTY:
                return  # the node finished its move: normal
            self.status.node_errors += 1
            self._warn_rate(f"node-{frame.address}", f"{jr.cfg.short}: {frame}")

    def _position_reply(self, jr: JointRuntime, q: float, now: float) -> None:
        """Take a position reply as the joint's position only if it is plausible (see REPLY_*): in range and
        consistent with the last good reply. After an implausible one, REPLIES_TO_TRUST in-range replies in a
        row, each consistent with the one before, make the position trusted again. Replies after a silence
        longer than ``stale_after`` (a node back online) do not re-seed the track: the node kept going to its last
        target meanwhile, and its next target starts from there (``_send_targets``)."""
        jr.last_heard = now
        cfg = jr.cfg
        in_range = reply_in_range(self.physical[cfg.address], q)  # where the joint can be, not where it is sent

        def near(q0: float, t0: float) -> bool:
            return abs(q - q0) <= REPLY_SPEED_FACTOR * self.bounds.max_velocity * max(now - t0, 0.0) + REPLY_SLACK

        good = in_range and (not math.isfinite(jr.pos) or near(jr.pos, jr.last_reply))
        if jr.trusted and not good:
            self._bad_reply(jr, q, in_range)
            jr.trusted, jr.suspect, jr.consistent = False, (q, now) if in_range else None, int(in_range)
            return
        if not jr.trusted:
            chain = in_range and jr.suspect is not None and near(*jr.suspect)
            if not (good or chain):
                self._bad_reply(jr, q, in_range)
            jr.suspect, jr.consistent = (q, now) if in_range else None, jr.consistent + 1 if chain else int(in_range)
            if jr.consistent < REPLIES_TO_TRUST:
                return
            jr.trusted, jr.vel = True, 0.0
            log.info("%s: %d consistent position replies (%.4f rad): position trusted again", cfg.short,
                     REPLIES_TO_TRUST, q)
        elif math.isfinite(jr.pos) and now > jr.last_reply and now - jr.last_reply <= self.stale_after:
            jr.vel = (q - jr.pos) / (now - jr.last_reply)
        else:
            jr.vel = 0.0
        jr.pos, jr.last_reply = q, now
        if jr.reseed and jr.referenced:  # (an unreferenced reading is in a shifted frame: never a target)
            jr.track.reseed(q, now)
            jr.ref, jr.goal, jr.goal_t = q, cfg.clamp(q), -math.inf

    def _second_reply(self, jr: JointRuntime, q: float, now: float) -> bool:
        """Is this a second in-range position reply to one query that disagrees with the first (two nodes on one
        address, or one answering twice with different counts)? Then neither is a position: the joint is not trusted
        until REPLIES_TO_TRUST consistent replies (which two such nodes never give: each query resets the count), so
        a mode 2/3 joint holds. A late reply of the previous query may come with this query's: they differ by what
        the joint moves in a period. (A reply out of range is refused as such by ``_position_reply``.)"""
        if not reply_in_range(self.physical[jr.cfg.address], q):
            return False
        first = self._first_reply.get(jr.cfg.address)
        if first is None:
            self._first_reply[jr.cfg.address] = (q, now)
            return False
        if abs(q - first[0]) <= REPLY_SLACK + self.bounds.max_velocity * (self.period + abs(now - first[1])):
            return False
        self.status.bad_replies += 1
        self.status.joint_bad_replies[jr.cfg.address] += 1
        self._warn_rate(f"two-replies-{jr.cfg.address}",
                        f"{jr.cfg.short}: two different position replies to one query ({first[0]:.4f} and {q:.4f} "
                        f"rad): two nodes on one address? Position not trusted")
        jr.trusted, jr.suspect, jr.consistent = False, None, 0
        return True

    def _bad_reply(self, jr: JointRuntime, q: float, in_range: bool) -> None:
        """Count an implausible reply; warn (rate-limited) when it costs the joint its trusted position."""
        self.status.bad_replies += 1
        self.status.joint_bad_replies[jr.cfg.address] += 1
        if jr.trusted:
            why = "outside its range" if not in_range else "an impossible jump"
            self._warn_rate(f"bad-reply-{jr.cfg.address}",
                            f"{jr.cfg.short}: position reply {q:.4f} rad is {why} (last good {jr.pos:.4f} rad): "
                            f"ignored; not trusted until {REPLIES_TO_TRUST} consistent replies (mode 2/3 holds)")

    def _unknown(self, address: int) -> None:
        self.status.unknown_node_frames += 1
        if address not in self.unknown_addresses:
            self.unknown_addresses.add(address)
            log.warning("frames from node 0x%02X, which is not in the joint table (counted, ignored)", address)

    def _bus_error(self, msg) -> None:
        err = msg.arbitration_id
        status = msg.data[1] if len(msg.data) > 1 else 0
        if err & CAN_ERR_BUSOFF:
            if self.bus_state != ds.BUS_STATE_BUS_OFF:
                self.status.bus_off_count += 1
                log.error("CAN bus-off: nothing reaches the robot until `mds-ach resetbus`")
            self.bus_state = ds.BUS_STATE_BUS_OFF
        elif err & CAN_ERR_RESTARTED:
            self.bus_state = ds.BUS_STATE_ACTIVE
            log.info("CAN controller restarted")
        elif err & CAN_ERR_CRTL and status & CAN_ERR_CRTL_ACTIVE:
            if self.bus_state == ds.BUS_STATE_PASSIVE:
                self.bus_state = ds.BUS_STATE_ACTIVE
                log.info("CAN controller back to error-active")
        elif err & CAN_ERR_CRTL and status & (CAN_ERR_CRTL_PASSIVE | CAN_ERR_CRTL_WARNING):
            if self.bus_state == ds.BUS_STATE_ACTIVE:
                self.bus_state = ds.BUS_STATE_PASSIVE
                self._warn_rate("passive", f"CAN controller error-passive/warning (status 0x{status:02X})")

    # --- publishing -----------------------------------------------------------------------------------------

    def _fill_state(self, now: float) -> None:
        stale = 0
        for a, jr in self.joints.items():
            s = self.state.joint[a]
            fresh = self._known(jr, now)
            heard = now - jr.last_heard <= self.stale_after
            if jr.homing_since is not None and now - jr.homing_since > 1.0:
                counts_per_cycle = abs(jr.vel) * self.period * jr.cfg.cpr / (2 * math.pi)
                settled = self._reading(jr, now) and counts_per_cycle < 2.0
                # HOME ends with the count zeroed at the ROM middle: that reading, at rest, is the calibrated frame.
                if settled and abs(jr.cfg.direction * jr.pos + jr.cfg.offset) <= HOMED_TOLERANCE:
                    jr.homing_since = None  # settled: hold there (jr.hold) until the reference changes
                    if not jr.referenced:
                        log.info("%s: homed: the encoder count is referenced again", jr.cfg.short)
                    jr.referenced = True
                    fresh = self._known(jr, now)
                elif now - jr.homing_since > HOMING_TIMEOUT:
                    jr.homing_since = None
                    if jr.referenced:
                        log.warning("%s: HOME did not end at the zeroed middle of the range in %.0f s: the joint is "
                                    "unreferenced until a HOME that does", jr.cfg.short, HOMING_TIMEOUT)
                    jr.referenced = False  # the search may have stopped anywhere: the count's zero is unknown
            if jr.pipeline_reseed and fresh and jr.homing_since is None:
                jr.pipeline_reseed = False
                self.status.joint_reseed[a] += 1  # the pipeline restarts this joint at s.pos below
                log.info("%s: the pipeline's reference restarts where the joint is (%.4f rad)", jr.cfg.short, jr.pos)
            s.ref_r, s.ref, s.ref_c_send, s.ref_c = jr.ref_r, jr.ref, jr.ref_c_send, jr.ref_c
            # An unreferenced reading is in a shifted frame: never shown as a position (the gate, IK, viewer use it).
            s.pos, s.vel, s.cur = (jr.pos if jr.referenced else math.nan), (jr.vel if fresh else 0.0), jr.cur
            s.enabled, s.active = int(jr.enabled), int(fresh)
            flags = jr.flags & (ds.JOINT_CLAMPED | ds.JOINT_REFUSED | ds.JOINT_MOVING | ds.JOINT_LIMITED
                                | ds.JOINT_SLOWED)
            flags |= ds.JOINT_CONFIGURED | (ds.JOINT_ENABLED if jr.enabled else 0)
            flags |= ds.JOINT_FRESH if fresh else 0 if heard else ds.JOINT_STALE
            flags |= 0 if jr.trusted else ds.JOINT_BAD_REPLY
            flags |= 0 if jr.referenced else ds.JOINT_UNREFERENCED
            flags |= ds.JOINT_FOLLOW_FAULT if jr.follow_fault else 0
            self.status.joint_flags[a] = flags
            self.status.joint_age[a] = now - jr.last_heard if math.isfinite(jr.last_heard) else -1.0
            if not heard and jr.enabled:
                stale += 1
        self.status.stale_count = stale

    def _publish_status(self, start: float, deadline: float, cpu0: float) -> None:
        st = self.status
        now = self.clock()
        period_err = None if self._last_start is None else (start - self._last_start) - self.period
        self._last_start = start
        load = 100.0 * self.io.counters.bits / (self.io.bitrate * self.period)
        self.stats.add(period_err, start - deadline, time.thread_time() - cpu0, load)
        self.cycle_count += 1
        st.cycle, st.time = self.cycle_count, time.monotonic()
        st.period_error, st.cycle_time = period_err or 0.0, now - start
        st.cycle_time_max = max(st.cycle_time_max, st.cycle_time)
        errs = self.stats.view(self.stats.period_err)
        st.bus_load = load
        # Window statistics (10 s windows) every WINDOW_STATS_PERIOD: numpy's percentile, max and means over the
        # windows cost ~0.3 ms, a sixth of a 10 Hz cycle at rest; the per-cycle values stay current, and a worst
        # value stays in its window for 10 s, so no refresh misses it.
        if self.cycle_count % self._stats_every == 0 or self.stats.n < 3:
            if errs.size:
                abs_errs = np.abs(errs)
                st.period_error_p50, st.period_error_p99 = np.percentile(abs_errs, [50, 99])
                st.period_error_max = float(abs_errs.max())
                st.measured_rate_hz = 1.0 / (self.period + float(errs.mean()))
            st.wake_latency_max = float(self.stats.view(self.stats.wake).max())
            st.cpu_per_cycle = float(self.stats.view(self.stats.cpu).mean())
            st.bus_load_avg = float(self.stats.view(self.stats.load).mean())
        c = self.io.counters
        st.tx_frames, st.rx_frames, st.tx_errors, st.rx_errors = c.tx_frames, c.rx_frames, c.tx_errors, c.rx_errors
        st.error_frames = c.error_frames
        if self.bus_state != ds.BUS_STATE_BUS_OFF and self.io.state.name == "ERROR":
            st.bus_off_count += 1
            self.bus_state = ds.BUS_STATE_BUS_OFF
            log.error("CAN interface reports bus-off: nothing reaches the robot until `mds-ach resetbus`")
        st.bus_state = self.bus_state
        self._put(self.ch.status, st)
        with self._lock:
            ctypes.memmove(ctypes.addressof(self._snapshot), ctypes.addressof(st), ctypes.sizeof(st))

    def _warn_once(self, key: str, text: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            log.warning(text)

    def _warn_rate(self, key: str, text: str, every: float = 5.0) -> None:
        """At most one warning per ``every`` seconds per key, the repeats counted in it (a flood must neither
        stall the loop nor fill the log: mds_ach.ratelog)."""
        self._warnings(key, text, every=every)
