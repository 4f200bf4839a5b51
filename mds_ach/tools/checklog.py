"""``mds-ach check-log``: audit recorded CAN traffic against the invariants every target sent to a motor obeys.

The daemon is the last stage before the motors; a log of what really went on the bus (``daemon --can-log``,
``candump -l`` on the robot, the original MDS-Ach dumps) shows whether it kept its promises, whatever happened
upstream. Findings, each with the joint, the log time and the value against its bound:

* ``non-finite``: a NaN/Inf target, or a NaN/Inf float in any SET to a joint;
* ``limit``: a MOVETO (or SET_TARGET) target outside the joint's range (in counts, half a count of tolerance);
* ``address``: a frame that can move a joint (target, HOME) sent to an address that is not an enabled joint of
  the table, or broadcast to every node;
* ``no-position`` (only for a log of one whole daemon run, ``whole_run``): a target to a joint before any valid
  position reply of it, or before the first one after its count restarted -- the daemon never commands a joint
  whose position it does not know;
* ``silent`` (``whole_run`` too): a target to a joint that has not answered at all for longer than the stale
  window plus ``max_interval`` (slack for where the daemon and the log date a reply) -- the daemon sends a silent
  node nothing, since the target may never arrive and the node, once back, would jump to it;
* ``unreferenced``: a target to a joint after a ZERO_ENCODER, RESET or encoder SET to it and before its count reads
  the homed zero again (a valid reply within ``HOMED_TOLERANCE`` of count 0 after a HOME): its count restarted where
  the joint stood, so a target in counts is in a shifted frame and ``limit`` cannot judge it -- the daemon sends
  such a joint nothing until HOME (docs/reliability.md M2);
* ``speed``, ``acceleration``: :func:`mds_ach.robot.motion.check` on every target, per joint, exactly the definition
  the daemon's limiter enforces;
* ``collision`` (``--collisions``): the commanded pose after a batch of targets collides, with the collision
  gate's model and world file. A joint's entry is its latest target; before its first one, and after a HOME,
  RESET, ZERO_ENCODER or ENABLE (the node holds wherever that leaves it), its measured position. The homing
  search itself is not a target and is not checked.

Tracks. A joint's sequence of targets is checked against the track of its previous target. A re-seed starts a
track at the measured position, at rest (:meth:`mds_ach.robot.motion.Track.reseed`): at the joint's first valid
position reply; after a HOME, RESET, ZERO_ENCODER or encoder SET to it, at its first valid reply (the count
restarted: a reply from before the command is no start any more); after an ENABLE, at its latest valid reply
(the node holds where it is). Nothing else re-seeds: only these frames, which the log shows, are a reason to
restart; a node whose replies resume after a silence goes on from its last target, within the bounds (a restart
at the measured position would reverse a joint still moving there). Until the joint's next target the re-seed
follows its *latest* valid reply, as the daemon's track does: the daemon's first target after a re-seed states
that very position. An earlier reply is never a start: a joint that moved by itself (homing, moved by hand
while disabled) is no longer there. The first step after a re-seed passes if it is within bounds from the
measured position or from the last sent target (other software may not re-seed at all). In a whole daemon run
(``whole_run``) the last target is no start after any of those commands: the daemon then certainly restarts
from the measured position, and a target with no measured position to start from is a ``no-position``
violation.

Candidates that pass all stay in play (each is a history the daemon could have had); when none passes, the step
is a violation (against the candidate it breaks least) and the sequence goes on from that candidate, so every
offending step is reported once: a jump and the stop right after it are two. A reply is valid when the daemon
would take it as a position at all (:func:`mds_ach.nodes.daemon_loop.reply_in_range`: finite, within the joint's range
plus 5 % of it, at least 0.1 rad); anything else is ignored, as the daemon ignores it.

:func:`audit_frames` is the audit itself, on (time, frame) pairs of one daemon run; :func:`audit_file` feeds it
a log file, and the tests (``test/support/motion_audit.py``) the frames of a daemon they ran.

Recordings. A recording of ``mds-ach record --can-log`` (MCAP, told by its magic bytes) holds the daemon's CAN
frames on ``/can/frames`` with their direction: they are audited like the CAN log they came from.

Sent and received. A log that records direction (the daemon's ``--can-log``, python-can .asc/.blf/.trc, candump
with ``-x``: at least one frame marked Tx) tells the host's frames from the nodes': only frames the host sent
are host commands; a received frame is a node's reply when it has the replies' ID (0x10), else traffic of
another sender (counted as ``received_other``, never audited as the host's command). A log without direction
(``candump -l``, the original MDS-Ach dumps) is read by ID alone: 0x10 is a reply, anything else a command.

The bounds and the stale window are the same at every loop rate the daemon accepts (``motion.MAX_INTERVAL``,
``daemon_loop.STALE_AFTER``); a step is dated by its frame's stamp, which for the daemon's own log is the time the
daemon limited it for. The report shows the daemon period (the median interval of the broadcast position query,
which the daemon sends once per cycle, or ``--rate``) for information.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import can
import numpy as np

from mds_ach.argtypes import bounded, count, seconds
from mds_ach.bus import canio, mcb
from mds_ach.bus.mcb import Command, StateArg, TrajectoryMode
from mds_ach.kinematics import collision
from mds_ach.nodes.daemon_loop import HOMED_TOLERANCE, STALE_AFTER, reply_in_range
from mds_ach.paths import config_path
from mds_ach.record import canlog, recording
from mds_ach.robot import config, motion
from mds_ach.robot.config import ConfigError, JointConfig, JointTable
from mds_ach.robot.msgs import MDS_JOINT_COUNT

KINDS = ("non-finite", "limit", "address", "no-position", "silent", "unreferenced", "speed", "acceleration",
         "collision")
MOTION_KINDS = ("speed", "acceleration")
COUNT_TOLERANCE = 0.5  # counts: float32 rounding of a target at a limit is far below one encoder count
# Commands after which a node's count restarts or it holds where it is: the next valid reply re-seeds (HOME, a
# SET of TRAJECTORY_MODE, and encoder SETs are handled with the SETs).
_RESEED_COMMANDS = (Command.RESET, Command.ZERO_ENCODER, Command.ENABLE)


@dataclass(frozen=True)
class Finding:
    """One violation: what, where, when (s since the log's first frame) and how far past which bound."""

    kind: str
    time: float
    joint: str  # short name, or the address in hex when it is not a joint of the table
    value: float
    bound: float
    text: str

    def line(self) -> str:
        return f"t={self.time:10.4f} s  {self.kind:<12} {self.joint:<6} {self.text}"


@dataclass
class FileReport:
    """Everything the audit of one log found, and what it looked at."""

    path: str
    format: str = ""
    error: str = ""  # why the file could not be audited (exit status 2)
    warning: str = ""  # e.g. speed/acceleration not checked
    frames: int = 0
    start_stamp: float = math.nan  # time stamp of the first frame as the log records it
    duration: float = 0.0
    period: float | None = None
    period_source: str = ""
    stale_after: float | None = None
    bounds: motion.MotionBounds | None = None
    queries: int = 0
    targets: Counter = field(default_factory=Counter)  # short name -> MOVETO/SET_TARGET frames
    commands: Counter = field(default_factory=Counter)  # "HOME", "RESET", "SET TRAJECTORY_PERIOD", ...
    replies_valid: int = 0
    replies_ignored: int = 0  # non-finite or implausible positions
    replies_unknown: int = 0  # position replies from nodes not in the joint table
    other_replies: int = 0
    error_frames: int = 0
    other_frames: int = 0  # extended IDs, wrong lengths; with directions also the replies' ID sent by the host
    directions: bool = False  # the log marks which frames the host sent (Tx) and which it received (Rx)
    sent_frames: int = 0  # with directions: frames the host sent
    received_frames: int = 0  # with directions: frames the host received
    received_other: int = 0  # received frames with a command's ID: another sender's, not the host's commands
    reseeds: int = 0
    unseeded_targets: int = 0  # targets of a joint with no known position (and no earlier target to go on from)
    silent_targets: int = 0  # targets to a joint silent for longer than the stale window (they may not arrive)
    sent: dict[str, list[tuple[float, float]]] = field(default_factory=dict)  # (time, rad) per joint, if recorded
    poses_checked: int = 0
    findings: list[Finding] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.error and not self.findings

    def counts(self) -> Counter:
        return Counter(f.kind for f in self.findings)


@dataclass
class Report:
    files: list[FileReport]

    @property
    def findings(self) -> list[Finding]:
        return [f for r in self.files for f in r.findings]

    @property
    def exit_code(self) -> int:
        """2 if a file could not be audited (completely), else 1 for any violation, else 0."""
        if any(r.error for r in self.files):
            return 2
        return 1 if self.findings else 0


# --------------------------------------------------------------------------------------------- the audit


def scan(path: str | Path) -> tuple[float | None, int, bool]:
    """(median interval of the broadcast position queries or None below two, number of queries, whether the log
    records direction: at least one frame marked as sent by the host)."""
    times: list[float] = []
    directions = False
    for m in _read(path):
        directions = directions or not m.is_rx
        if _is_position_query(m):
            times.append(m.timestamp)
    intervals = [b - a for a, b in zip(times, times[1:], strict=False) if b > a]
    return (statistics.median(intervals) if intervals else None), len(times), directions


def _read(path: str | Path, torn: list[str] | None = None) -> Iterator[can.Message]:
    """``canio.read_log``, except that an incomplete last line (a recorder killed mid-write) ends the log, noted
    in ``torn``, instead of failing it."""
    try:
        yield from canio.read_log(path)
    except canio.TornLogError as exc:
        if torn is not None:
            torn.append(str(exc))


def _is_position_query(msg: Any) -> bool:
    data = msg.data
    return (msg.arbitration_id == mcb.BROADCAST_SID and not msg.is_extended_id and not msg.is_error_frame
            and len(data) == mcb.DLC and data[7] == Command.QUERY_STATE and data[6] == StateArg.ACTUAL_POSITION)


@dataclass
class _JointAudit:
    """Per joint: the candidate tracks of its last sent target, the pending re-seed, the replies."""

    cfg: JointConfig
    lo_counts: float
    hi_counts: float
    sent: list[motion.Track] = field(default_factory=list)  # histories of the targets sent so far
    seed: motion.Track | None = None  # since a re-seed, until the next target: the latest valid reply, at rest
    last_reply: float = -math.inf  # when the latest valid position reply came
    last_q: float = math.nan  # and what it said (rad)
    last_heard: float = -math.inf  # the latest finite position reply, valid or not (the daemon's last_heard)
    reseed_due: bool = False  # a command restarted the count: the next valid reply re-seeds
    restart: bool = False  # whole run, after a re-seed command: the last target is no start any more
    holding: bool = True  # no target since the start or a setup command: the node holds where it is
    unreferenced: str = ""  # the command that restarted its count away from the homed zero ("": referenced)
    homing: bool = False  # a HOME since: the next reply at the homed zero references the count again


class _Auditor:
    """Consumes one log's frames in order and fills a FileReport."""

    def __init__(self, table: JointTable, report: FileReport, model: Any | None, t0: float, whole_run: bool,
                 record: bool) -> None:
        self.table = table
        self.r = report
        self.bounds = report.bounds
        self.stale = report.stale_after if report.stale_after is not None else math.inf
        self.t0 = t0
        self.whole_run = whole_run
        self.record = record
        if record:
            report.sent = {j.short: [] for j in table}
        self.joints: dict[int, _JointAudit] = {}
        for j in table:
            a, b = j.to_counts(j.lower), j.to_counts(j.upper)
            self.joints[j.address] = _JointAudit(j, min(a, b), max(a, b))
        self.model = model
        self.pose = np.zeros(MDS_JOINT_COUNT)  # by address, like mds-ref-gated: the commanded pose for --collisions
        for j in table:
            self.pose[j.address] = j.home
        self.pose_dirty = False
        self.colliding: tuple[float, set[str], int, set[str]] | None = None  # start, pairs, batches, arms

    # ----- frames

    def frame(self, t: float, msg: Any) -> None:
        if msg.is_error_frame:
            self.r.error_frames += 1
            return
        if self.r.directions:
            if msg.is_rx:
                self.r.received_frames += 1
            else:
                self.r.sent_frames += 1
        data = bytes(msg.data)
        if msg.is_extended_id or msg.is_remote_frame or len(data) != mcb.DLC:
            self.r.other_frames += 1
            return
        if self.r.directions and msg.is_rx and msg.arbitration_id != mcb.HOST_SID:
            self.r.received_other += 1  # another sender's frame (a second host, a node on a wrong ID): not ours
            return
        if msg.arbitration_id == mcb.HOST_SID:
            if self.r.directions and not msg.is_rx:
                self.r.other_frames += 1  # the host never sends on the replies' ID
            else:
                self._reply(t, data)
            return
        frame = mcb.decode(msg.arbitration_id, data)
        if _is_position_query(msg):
            self.r.queries += 1
            self.end_batch(t)
            return
        self._command(t, frame)

    def _reply(self, t: float, data: bytes) -> None:
        pos = mcb.decode_position(data)
        if pos is None:
            self.r.other_replies += 1
            return
        address, counts = pos
        ja = self.joints.get(address)
        if ja is None:
            self.r.replies_unknown += 1
            return
        q = ja.cfg.to_joint(counts) if math.isfinite(counts) else math.nan
        if math.isfinite(q):
            ja.last_heard = t
        if not reply_in_range(ja.cfg, q):
            self.r.replies_ignored += 1
            return
        self.r.replies_valid += 1
        if ja.homing and abs(counts) * 2 * math.pi / ja.cfg.cpr <= HOMED_TOLERANCE:
            ja.unreferenced, ja.homing = "", False  # the node zeroed its count at the middle of its range
        if self.model is not None and ja.holding:
            self._set_pose(address, q)  # no target to it (yet, or since HOME...): it is commanded to stay there
        first = ja.last_reply == -math.inf
        if first or ja.reseed_due:  # the first reply, or the first after HOME/RESET/ZERO_ENCODER/ENABLE
            ja.reseed_due = False
            ja.seed = motion.Track(q, 0.0, t)
            self.r.reseeds += 1
        elif ja.seed is not None:
            ja.seed.reseed(q, t)  # until the next target: where the joint is now
        ja.last_reply, ja.last_q = t, q

    def _command(self, t: float, f: mcb.McbFrame) -> None:
        dest = f.arbitration_id
        if f.command == Command.SET:
            name = f"SET {_name(f.argument)}"
            if f.argument == StateArg.MOVETO_TARGET:
                self._target(t, dest, float(f.value))
                return
            self.r.commands[name] += 1
            if isinstance(f.value, float) and not math.isfinite(f.value) and dest in self.joints:
                self._find("non-finite", t, self._label(dest), f.value, math.nan, f"{name} {f.value}")
            if f.argument == StateArg.TRAJECTORY_MODE and f.value == TrajectoryMode.HOME:
                self.r.commands["HOME"] += 1
                self._moves(t, dest, "HOME")
                self._reseed_due(dest, count_restarts=True)
                self._reference(dest, "")
            elif f.argument == StateArg.ENCODER:
                self._reseed_due(dest, count_restarts=True)
                self._reference(dest, "SET ENCODER")
            return
        if f.command == Command.SET_TARGET:
            self._target(t, dest, float(f.value))
            return
        self.r.commands[_name(f.command)] += 1
        if f.command in _RESEED_COMMANDS:
            self._reseed_due(dest, count_restarts=f.command != Command.ENABLE)
        if f.command in (Command.RESET, Command.ZERO_ENCODER):
            self._reference(dest, _name(f.command))

    def _reference(self, dest: int, restarted_by: str) -> None:
        """A HOME (``restarted_by`` empty: referenced again once a reply reads the homed zero) or a command that
        restarted the count where the joint stood (unreferenced until then)."""
        for a in (self.joints if dest == mcb.BROADCAST_SID else [dest]):
            if a in self.joints:
                ja = self.joints[a]
                if restarted_by:
                    ja.unreferenced, ja.homing = restarted_by, False
                else:
                    ja.homing = bool(ja.unreferenced)

    def _reseed_due(self, dest: int, count_restarts: bool) -> None:
        """A re-seed command: the next valid reply re-seeds; in a whole run the daemon certainly restarts the
        joint where it is measured, so its last target is no start any more. A count that restarts (HOME, RESET,
        ZERO_ENCODER, encoder SET) voids the replies before the command; after ENABLE the node holds where it is,
        so the latest reply before the command is where it is until the next one comes."""
        for a in (self.joints if dest == mcb.BROADCAST_SID else [dest]):
            if a in self.joints:
                ja = self.joints[a]
                ja.reseed_due = ja.holding = True
                ja.restart |= self.whole_run
                known = not count_restarts and math.isfinite(ja.last_q)
                ja.seed = motion.Track(ja.last_q, 0.0, ja.last_reply) if known else None

    def _certain_silence(self) -> float:
        """A reply gap longer than this is a silence the daemon saw too (the stale window plus ``max_interval``
        of slack for where the daemon and the log date a reply)."""
        return self.stale + self.bounds.max_interval if self.bounds is not None else math.inf

    def _moves(self, t: float, dest: int, what: str) -> bool:
        """Is ``dest`` an enabled joint? Else an ``address`` finding for this motion frame."""
        ja = self.joints.get(dest)
        if ja is not None and ja.cfg.enabled:
            return True
        if dest == mcb.BROADCAST_SID:
            why = "broadcast: it would move every node"
        elif ja is None:
            why = "not a joint of the table"
        else:
            why = "disabled in the joint table"
        self._find("address", t, self._label(dest), math.nan, math.nan, f"{what} to 0x{dest:02X}: {why}")
        return False

    def _target(self, t: float, dest: int, counts: float) -> None:
        ja = self.joints.get(dest)
        label = self._label(dest)
        self.r.targets[label] += 1
        if not self._moves(t, dest, f"target {counts:.6g} counts") or ja is None:  # ja: _moves said it is a joint
            return
        if not math.isfinite(counts):
            self._find("non-finite", t, label, counts, math.nan, f"target {counts} counts")
            return
        cfg = ja.cfg
        q = cfg.to_joint(counts)
        if self.record:
            self.r.sent.setdefault(cfg.short, []).append((t, q))
        silence = t - ja.last_heard if math.isfinite(ja.last_heard) else 0.0
        if silence > self.stale:
            self.r.silent_targets += 1
            if self.whole_run and silence > self._certain_silence():
                self._find("silent", t, label, silence, self.stale,
                           f"target {q:.4f} rad to a joint silent for {silence:.3f} s (stale window "
                           f"{self.stale:.3f} s): it may never arrive, and the node, once back, would jump to it")
        if ja.seed is None and (not ja.sent or ja.restart):
            self.r.unseeded_targets += 1  # nothing known before it: its first step cannot be checked
            if self.whole_run:
                since = "since its count restarted" if ja.sent else "of the joint"
                self._find("no-position", t, label, q, math.nan, f"target {q:.4f} rad before any valid position "
                                                                 f"reply {since}")
        if ja.unreferenced:
            self._find("unreferenced", t, label, q, math.nan,
                       f"target {q:.4f} rad after {ja.unreferenced} restarted the joint's count and before a HOME "
                       "zeroed it at the middle of its range: the target's counts are in a shifted frame")
        if not ja.lo_counts - COUNT_TOLERANCE <= counts <= ja.hi_counts + COUNT_TOLERANCE:
            bound = cfg.upper if q > cfg.upper else cfg.lower
            self._find("limit", t, label, q, bound, f"target {q:.4f} rad ({counts:.1f} counts) outside "
                                                    f"[{cfg.lower:.4f}, {cfg.upper:.4f}]")
        if self.bounds is not None:
            self._motion(t, ja, q, self.bounds)
        ja.holding = False
        if self.model is not None:
            self._set_pose(dest, q)
            self.pose_dirty = True

    def _motion(self, t: float, ja: _JointAudit, q: float, bounds: motion.MotionBounds) -> None:
        candidates = ([] if ja.restart else ja.sent) + ([ja.seed] if ja.seed is not None else [])
        ja.seed, ja.restart = None, False
        if not candidates:  # nothing known before it (counted by _target): the sequence starts here
            ja.sent = [motion.Track(q, 0.0, t)]
            return
        results = [(track, motion.check(track, q, t, bounds)) for track in candidates]
        passing = [track for track, found in results if not found]
        if not passing:
            track, found = min(results, key=lambda r: max(v.value / v.bound for v in r[1]))
            for v in found:
                unit = "rad/s" if v.kind == "speed" else "rad/s^2"
                h = bounds.interval(t - track.t)
                self._find(v.kind, t, ja.cfg.short, v.value, v.bound,
                           f"{v.value:.3f} {unit} > {v.bound:g}: {track.q:.4f} -> {q:.4f} rad in "
                           f"{h * 1e3:.1f} ms (previous velocity {track.previous_velocity(t, bounds):.3f} rad/s)")
            passing = [track]  # the sequence goes on from there: each offending step is reported once
        tracks: list[motion.Track] = []
        for track in passing:
            track.advance(q, t, bounds)
            if not any(abs(track.v - other.v) < 1e-12 for other in tracks):
                tracks.append(track)
        ja.sent = tracks

    # ----- commanded pose (--collisions)

    def _set_pose(self, address: int, q: float) -> None:
        self.pose[address] = q  # addresses of the table are < MDS_JOINT_COUNT (config.validate)

    def end_batch(self, t: float) -> None:
        """After the targets of one cycle (the next position query, or the end of the log): check the pose."""
        if self.model is None or not self.pose_dirty:
            return
        self.pose_dirty = False
        self.r.poses_checked += 1
        result = self.model.check(self.model.q_from_ref(self.pose))
        if result.collides:
            pairs = {f"{c.a}/{c.b}" for c in result.contacts}
            if self.colliding is None:
                self.colliding = (t, pairs, 1, result.arms)
            else:
                start, seen, n, arms = self.colliding
                self.colliding = (start, seen | pairs, n + 1, arms | result.arms)
        elif self.colliding is not None:
            self._close_collision(t, self.colliding)

    def _close_collision(self, t: float, colliding: tuple[float, set[str], int, set[str]]) -> None:
        start, pairs, n, arms = colliding
        self.colliding = None
        self._find("collision", start, "+".join(sorted(arms)) or "pose", float(n), 0.0,
                   f"commanded pose collides for {n} batch(es) ({t - start:.3f} s): {', '.join(sorted(pairs))}")

    def finish(self, t: float) -> None:
        self.end_batch(t)
        if self.colliding is not None:
            self._close_collision(t, self.colliding)

    # ----- helpers

    def _label(self, address: int) -> str:
        ja = self.joints.get(address)
        return ja.cfg.short if ja is not None else f"0x{address:02X}"

    def _find(self, kind: str, t: float, joint: str, value: float, bound: float, text: str) -> None:
        self.r.findings.append(Finding(kind, t - self.t0, joint, value, bound, text))


def _name(code: int) -> str:
    return code.name if hasattr(code, "name") else f"0x{code:02X}"


def audit_frames(frames: Iterable[tuple[float, Any]], table: JointTable, bounds: motion.MotionBounds | None,
                 stale_after: float | None, *, model: Any | None = None, whole_run: bool = False,
                 record_targets: bool = False, report: FileReport | None = None,
                 directions: bool | None = None) -> FileReport:
    """Audit the frames (time in s, ``can.Message``) of one daemon run, host frames and node replies in order.

    ``bounds`` and ``stale_after`` are the daemon's (``None``: speed and acceleration are not checked, no joint is
    ever silent). ``directions``: the frames' ``is_rx`` tells what the host sent from what it received (None: so if
    any frame is marked sent). ``whole_run``: the frames start when the daemon started (its own ``--can-log``, a test's
    recorder), so a target before its joint's first position (``no-position``) or to a long silent joint
    (``silent``) is a violation instead of a count.
    ``record_targets`` keeps every target sent, per joint, in ``report.sent``. The findings go into ``report`` as
    they are found (a caller whose frames fail half-way keeps them); a new one if none is given.
    """
    report = report if report is not None else FileReport("")
    report.bounds, report.stale_after = bounds, stale_after
    if directions is None:
        frames = list(frames)
        directions = any(not msg.is_rx for _, msg in frames)
    report.directions = directions
    auditor: _Auditor | None = None
    t = 0.0
    for t, msg in frames:
        if auditor is None:
            report.start_stamp = t
            auditor = _Auditor(table, report, model, t, whole_run, record_targets)
        auditor.frame(t, msg)
        report.frames += 1
    if auditor is not None:
        auditor.finish(t)
        report.duration = t - report.start_stamp
    return report


def audit_file(path: str | Path, table: JointTable, *, rate: float | None = None,
               stale_after: float | None = None, model: Any | None = None, whole_run: bool = False) -> FileReport:
    """Audit one log (any format :func:`mds_ach.bus.canio.read_log` reads); never raises for a bad file."""
    report = FileReport(str(path))
    if recording.is_recording(path):
        return _audit_recording(path, table, report, rate=rate, stale_after=stale_after, model=model,
                                whole_run=whole_run)
    try:
        report.format = canio.log_format(path)
        period, n, directions = scan(path)
        if rate is not None:
            report.period, report.period_source = 1.0 / rate, f"--rate {rate:g} Hz"
        elif period is not None:
            report.period, report.period_source = period, f"inferred from {n} position queries (median interval)"
        stale = stale_after if stale_after is not None else STALE_AFTER
        torn: list[str] = []
        audit_frames(((msg.timestamp, msg) for msg in _read(path, torn)), table, table.motion_bounds(), stale,
                     model=model, whole_run=whole_run, report=report, directions=directions)
        if not report.frames:
            report.error = "no CAN frames in the file"
            return report
        if torn:
            report.warning = f"{torn[0]}: the frames before it are audited"
    except (canio.LogReadError, OSError) as exc:
        report.error = str(exc)
        return report
    return report


def _audit_recording(path: str | Path, table: JointTable, report: FileReport, *, rate: float | None,
                     stale_after: float | None, model: Any | None, whole_run: bool) -> FileReport:
    """``audit_file`` for a recording (``mds-ach record --can-log``): the daemon's CAN frames it holds."""
    report.format = "MCAP recording"
    try:
        frames, cut = canlog.recorded_frames(path)
    except recording.RecordingError as exc:
        report.error = str(exc)
        return report
    if not frames:
        report.error = (f"the recording has no CAN frames ({canlog.CAN_TOPIC}): record with 'mds-ach record "
                        "--can-log FILE' (the daemon's --can-log)")
        return report
    times = [m.timestamp for m in frames if _is_position_query(m)]
    gaps = [b - a for a, b in zip(times, times[1:], strict=False) if b > a]
    if rate is not None:
        report.period, report.period_source = 1.0 / rate, f"--rate {rate:g} Hz"
    elif gaps:
        report.period = statistics.median(gaps)
        report.period_source = f"inferred from {len(times)} position queries (median interval)"
    audit_frames(((m.timestamp, m) for m in frames), table, table.motion_bounds(),
                 stale_after if stale_after is not None else STALE_AFTER, model=model, whole_run=whole_run,
                 report=report, directions=any(not m.is_rx for m in frames))
    if cut:
        report.warning = f"{cut}: the frames before it are audited"
    return report


def audit(paths: Sequence[str | Path], table: JointTable, *, rate: float | None = None,
          stale_after: float | None = None, model: Any | None = None, whole_run: bool = False) -> Report:
    """Audit each log on its own (one daemon run per file: a restarted daemon re-seeds like a new log)."""
    return Report([audit_file(p, table, rate=rate, stale_after=stale_after, model=model, whole_run=whole_run)
                   for p in paths])


# --------------------------------------------------------------------------------------------- the report


def format_report(report: Report, table: JointTable, max_listed: int = 0) -> str:
    lines: list[str] = []
    for r in report.files:
        lines += _file_lines(r, max_listed)
    total = Counter(f.kind for f in report.findings)
    bad = [r for r in report.files if r.error]
    if total:
        kinds = ", ".join(f"{k} {total[k]}" for k in KINDS if total[k])
        lines.append(f"check-log: {sum(total.values())} violation(s) in {len(report.files)} file(s): {kinds}")
    elif not bad:
        lines.append(f"check-log: clean: {len(report.files)} file(s), no violation (joint table {table.robot})")
    if bad:
        lines.append(f"check-log: {len(bad)} file(s) not (completely) audited: "
                     + ", ".join(Path(r.path).name for r in bad))
    return "\n".join(lines)


def _file_lines(r: FileReport, max_listed: int) -> list[str]:
    start = ""
    if r.frames and r.start_stamp > 1e9:  # wall-clock stamps (the recorder, candump); ASC logs start at 0
        start = f", from {datetime.fromtimestamp(r.start_stamp, UTC):%Y-%m-%d %H:%M:%S.%f} UTC"
    out = [f"{r.path} ({r.format or 'unknown format'}): {r.frames} frames over {r.duration:.3f} s{start}"]
    b, stale = r.bounds, r.stale_after
    if b is not None and stale is not None:  # set together (audit_file)
        period = f"period {r.period * 1e3:.2f} ms {r.period_source}" if r.period is not None else "period unknown"
        out.append(f"  {period}; stale window {stale * 1e3:.1f} ms; bounds {b.max_velocity:g} rad/s, "
                   f"{b.max_acceleration:g} rad/s^2, steps count at most {b.max_interval * 1e3:.1f} ms")
    if r.frames and r.directions:
        out.append(f"  sent by the host {r.sent_frames}, received {r.received_frames} (of these {r.received_other} "
                   "from another sender with a command's ID: not the host's commands, not audited)")
    if r.frames:
        per_joint = " ".join(f"{j} {n}" for j, n in sorted(r.targets.items()))
        out.append(f"  targets: {sum(r.targets.values())}" + (f" ({per_joint})" if per_joint else ""))
        if r.commands:
            out.append("  commands: " + ", ".join(f"{k} {n}" for k, n in sorted(r.commands.items())))
        out.append(f"  position queries {r.queries}; position replies {r.replies_valid} valid, {r.replies_ignored} "
                   f"ignored (non-finite or beyond the range + 5 %, at least 0.1 rad), {r.replies_unknown} from nodes "
                   f"not in the table; other replies {r.other_replies}; "
                   f"error frames {r.error_frames}; re-seeds {r.reseeds}")
        if r.silent_targets:
            out.append(f"  {r.silent_targets} target(s) went to a joint silent for longer than the stale window: "
                       "they may never have arrived (a violation only with --whole-run; the step from the last "
                       "target is what is checked)")
        if r.unseeded_targets:
            out.append(f"  {r.unseeded_targets} target(s) came before any position of their joint: their first step "
                       "is not checked")
        if r.poses_checked:
            out.append(f"  commanded poses checked for collisions: {r.poses_checked}")
    if r.warning:
        out.append(f"  warning: {r.warning}")
    if r.error:
        out.append(f"  NOT AUDITED: {r.error}")
    counts = r.counts()
    if counts:
        per = []
        for kind in KINDS:
            if counts[kind]:
                joints = Counter(f.joint for f in r.findings if f.kind == kind)
                per.append(f"{kind} {counts[kind]} (" + " ".join(f"{j} {n}" for j, n in sorted(joints.items())) + ")")
        out.append("  violations: " + "; ".join(per))
        listed = r.findings if max_listed <= 0 else r.findings[:max_listed]
        out += ["    " + f.line() for f in listed]
        if len(listed) < len(r.findings):
            out.append(f"    ... and {len(r.findings) - len(listed)} more (--max 0 lists all)")
    elif r.frames and not r.error:
        out.append("  violations: none")
    return out


# --------------------------------------------------------------------------------------------- CLI


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Audit recorded CAN traffic (daemon --can-log, candump -l, python-can .asc/.blf/.csv/.log/.trc, "
                     "the original MDS-Ach text dumps, a recording of 'mds-ach record --can-log') against the safety "
                     "invariants: every target finite, inside "
                     "its joint's limits, to an enabled joint, within the speed and acceleration bounds of the "
                     "joint table (mds_ach.robot.motion); optionally no commanded collision. Exit status 0 clean, "
                     "1 violations, 2 a file could not be audited.")
    p.add_argument("files", nargs="+", metavar="FILE",
                   help="CAN logs or recordings (.mcap, their CAN frames); each is audited on its own")
    p.add_argument("--robot", help="robot variant of the joint table (default: $MDS_ACH_ROBOT, the saved choice, "
                                   "else 'default')")
    p.add_argument("--config", metavar="FILE", help="joint table YAML (default: the installed config/joints.yaml)")
    p.add_argument("--rate", type=bounded(0.0, 10_000.0, above=True, unit="Hz"), metavar="HZ",
                   help="daemon loop rate, for the report (default: inferred from the broadcast position queries); "
                        "the bounds and the stale window are the same at every rate the daemon accepts")
    p.add_argument("--stale-after", type=seconds(60.0), metavar="S",
                   help=f"reply gap after which a joint counts as silent (default {STALE_AFTER:g} s, as the daemon)")
    p.add_argument("--whole-run", action="store_true",
                   help="each log starts when the daemon started (its --can-log, or candump started before it): a "
                        "target to a joint before any position reply of it (no-position), or to a joint silent for "
                        "longer than the stale window (silent), is a violation")
    p.add_argument("--collisions", action="store_true",
                   help="also check every commanded pose with the collision gate's model (self and world)")
    p.add_argument("--world", metavar="FILE", help="world objects for --collisions (default: config/world.yaml)")
    p.add_argument("--collision-margin", type=bounded(0.0, 1.0, unit="m"), default=0.0, metavar="M",
                   help="clearance (m) below which a commanded pose counts as colliding (default 0: touching)")
    p.add_argument("--max", type=count(0, 1_000_000_000), default=0, metavar="N",
                   help="list at most N violations per file (default 0: all; the summary counts every one)")


def run(args: argparse.Namespace) -> int:
    if args.rate is not None and not (math.isfinite(args.rate) and args.rate > 0):
        print(f"mds-ach check-log: --rate must be > 0 Hz, got {args.rate}", file=sys.stderr)
        return 2
    if args.stale_after is not None and not (math.isfinite(args.stale_after) and args.stale_after > 0):
        print(f"mds-ach check-log: --stale-after must be > 0 s, got {args.stale_after}", file=sys.stderr)
        return 2
    try:
        table = config.load(args.robot, args.config)
        model = collision_model(args.world, args.collision_margin) if args.collisions else None
    except (ConfigError, OSError, ValueError) as exc:
        print(f"mds-ach check-log: {exc}", file=sys.stderr)
        return 2
    report = audit(args.files, table, rate=args.rate, stale_after=args.stale_after, model=model,
                   whole_run=args.whole_run)
    print(format_report(report, table, args.max))
    return report.exit_code


def collision_model(world: str | None = None, margin: float = 0.0) -> Any:
    """The collision gate's model (URDF, config/collision.yaml, the world file) with clearance ``margin``."""
    if not (math.isfinite(margin) and margin >= 0):
        raise ValueError(f"--collision-margin must be >= 0 m, got {margin}")
    path = config_path("collision.yaml")
    cfg = dict(collision.load_yaml(path)) if path.exists() else {}
    cfg["margin"] = margin
    return collision.load_model(config=cfg, world=world)


def main(argv: Iterable[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="mds-ach check-log")
    add_arguments(ap)
    return run(ap.parse_args(list(argv) if argv is not None else None))


if __name__ == "__main__":
    raise SystemExit(main())
