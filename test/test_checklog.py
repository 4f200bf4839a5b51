"""``mds-ach check-log``: the CAN-log safety auditor, on real captures and on written logs with known violations.

The synthetic logs are real files in every format the daemon records (python-can writers) and in candump's
format, with frames built by the MCB codec exactly as the daemon sends and receives them: per cycle the 4-frame
SET sequence of each changed joint, the broadcast position query, every node's position reply.
"""

from __future__ import annotations

import math
import struct
import subprocess
from pathlib import Path

import can
import numpy as np
import pytest
from support import VENV_BIN

from mds_ach.bus import canio, mcb
from mds_ach.nodes import daemon_loop
from mds_ach.robot import config, motion
from mds_ach.tools import checklog

TABLE = config.load("default")
REAL_LOGS = "mds-reference/can/logs"
T0 = 1_764_000_000.0  # wall-clock stamps, as the daemon's recorder writes them


class LogBuilder:
    """A daemon's traffic, cycle by cycle: targets (rad), the broadcast query, replies (rad) from every node.

    ``ramp`` sends what a correct daemon sends: each joint's targets come from ``motion.limit`` on a track that
    starts at the joint's last reply, at rest. An explicit target (``cycle``) restarts that joint's track at rest
    there (as the auditor does after a violation)."""

    def __init__(self, period: float = 0.1, pose: dict[str, float] | None = None) -> None:
        self.period = period
        self.t = T0
        self.frames: list[tuple[float, mcb.RawFrame]] = []
        self.pos = {j.short: j.home for j in TABLE}
        self.pos.update(pose or {})
        self.silent: set[str] = set()  # joints that do not answer
        self.tracks: dict[str, motion.Track] = {}
        self.last_reply = T0
        self.foreign: set[int] = set()  # indices of frames another sender put on the bus (the host received them)

    def raw(self, raw: mcb.RawFrame, dt: float = 0.0) -> None:
        self.frames.append((self.t + dt, raw))

    def target(self, short: str, q: float) -> None:
        """The daemon's 4-frame SET sequence; the MOVETO carries any float32, NaN included (which the encoder,
        rightly, refuses to build)."""
        j = TABLE[short]
        word, = struct.unpack("<I", struct.pack("<f", j.to_counts(q)))
        moveto = mcb.RawFrame(j.address, mcb.pack(mcb.Command.SET, mcb.StateArg.MOVETO_TARGET, word))
        frames = [mcb.encode_set_acceleration(j.address, TABLE.accel_counts(j)), moveto,
                  mcb.encode_trajectory_mode(j.address), mcb.encode_trajectory_period(j.address)]
        for k, f in enumerate(frames):
            self.raw(f, 1e-4 * k)

    def cycle(self, targets: dict[str, float] | None = None, replies: dict[str, float] | None = None) -> None:
        """One period: the targets, the query 1 ms later, replies 2 ms later (ideal tracking unless ``replies``)."""
        for short, q in (targets or {}).items():
            self.target(short, q)
            self.tracks[short] = motion.Track(q, 0.0, self.t)
        self.raw(mcb.encode_query_positions(), 0.001)
        for short, q in (targets or {}).items():
            self.pos[short] = q
        self.pos.update(replies or {})
        for j in TABLE:
            if j.short not in self.silent:
                counts = j.to_counts(self.pos[j.short])
                self.raw(mcb.encode_state_reply(j.address, mcb.StateArg.ACTUAL_POSITION, counts), 0.002)
        self.last_reply = self.t + 0.002
        self.t += self.period

    def ramp(self, goals: dict[str, float], seconds: float) -> None:
        """Move joints towards ``goals`` with the daemon's own limiter (what a correct daemon sends)."""
        bounds = TABLE.motion_bounds()
        for s in goals:
            self.tracks.setdefault(s, motion.Track(self.pos[s], 0.0, self.last_reply))
        for _ in range(round(seconds / self.period)):
            for s, goal in goals.items():
                q = motion.limit(self.tracks[s], goal, self.t, bounds)
                self.tracks[s].advance(q, self.t, bounds)
                self.target(s, q)
                self.pos[s] = q
            self.cycle()

    def received(self, raw: mcb.RawFrame, dt: float = 0.0) -> None:
        """A frame another sender put on the bus, which the host received."""
        self.foreign.add(len(self.frames))
        self.raw(raw, dt)

    def write(self, path: Path, directions: bool = False) -> Path:
        """The frames with python-can's default direction (received), or as the daemon records them: what the
        host sent as Tx, the nodes' replies and ``received`` frames as Rx."""
        writer = can.Logger(str(path))
        for k, (t, f) in enumerate(self.frames):
            rx = not directions or f.arbitration_id == mcb.HOST_SID or k in self.foreign
            writer.on_message_received(can.Message(timestamp=t, arbitration_id=f.arbitration_id, data=f.data,
                                                   is_extended_id=False, is_rx=rx))
        writer.stop()
        return path

    def write_candump(self, path: Path) -> Path:
        """As ``candump -l can0`` writes (no direction flag)."""
        path.write_text("".join(f"({t:.6f}) can0 {f.arbitration_id:03X}#{f.data.hex().upper()}\n"
                                for t, f in self.frames))
        return path


def audit(path: Path, **kw) -> checklog.FileReport:
    return checklog.audit_file(path, TABLE, **kw)


def found(report: checklog.FileReport) -> set[tuple[str, str, float]]:
    """(kind, joint, time to 10 ms) of every finding: the first frame of a log is 1 ms after its first cycle."""
    return {(f.kind, f.joint, round(f.time, 2)) for f in report.findings}


def found_kinds(r: checklog.FileReport) -> set[tuple[str, str]]:
    return {(f.kind, f.joint) for f in r.findings}


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(VENV_BIN / "mds-ach"), "check-log", *map(str, args)], capture_output=True, text=True,
                          timeout=120)


# --------------------------------------------------------------------------------------------- clean logs


@pytest.mark.parametrize("period", [0.1, 0.01])
def test_a_limited_ramp_is_clean(tmp_path: Path, period: float) -> None:
    b = LogBuilder(period)
    b.cycle()
    b.ramp({"LSP": 0.5, "LEP": -2.0, "NKY": 0.3}, 2.5)
    b.ramp({"LSP": -1.0, "LEP": -0.5, "NKY": -0.3}, 3.0)
    r = audit(b.write(tmp_path / "ramp.asc"))
    assert r.ok, checklog.format_report(checklog.Report([r]), TABLE)
    assert r.period == pytest.approx(period, rel=1e-3) and "inferred from" in r.period_source
    assert r.targets["LSP"] > 10 and r.targets["LEP"] > 10 and r.unseeded_targets == 0
    assert r.replies_valid == len(TABLE) * r.queries and r.reseeds == len(TABLE)


# --------------------------------------------------------------------------------------------- violations


def violating_log() -> LogBuilder:
    """A jump, an over-acceleration, a NaN, an out-of-limit target and targets to an unknown and a disabled node,
    each at a known time (s from the first cycle); everything else moves within the bounds."""
    rep_upper = TABLE["REP"].upper
    b = LogBuilder(0.1, pose={"REP": rep_upper - 0.005})
    b.cycle()
    b.ramp({"LSP": -0.45}, 1.9)  # t = 0.1 .. 1.9 s: standing
    b.cycle({"LSP": -0.45 + 0.5})  # t = 2.0: a 0.5 rad jump from rest: speed and acceleration
    b.ramp({"LSP": b.pos["LSP"]}, 0.4)
    b.ramp({"LEP": -2.4}, 0.5)  # t = 2.5 .. 2.9: LEP accelerates within the bounds to 1.8 rad/s (negative)
    b.cycle({"LEP": b.pos["LEP"] + 0.05})  # t = 3.0: reversed to +0.5 rad/s in 0.1 s: acceleration only
    b.ramp({"LEP": b.pos["LEP"]}, 0.9)
    b.target("RSP", math.nan)  # t = 4.0: NaN
    b.cycle()
    b.ramp({"LSP": b.pos["LSP"]}, 0.9)
    b.cycle({"REP": rep_upper + 0.02})  # t = 5.0: past the upper limit, in a small step
    b.ramp({"LSP": b.pos["LSP"]}, 0.9)
    b.raw(mcb.RawFrame(0x70, mcb.encode_moveto(0x70, 100.0).data))  # t = 6.0: no such node
    b.raw(mcb.encode_moveto(TABLE["LYY"].address, 0.0), 0.0005)  # disabled in the joint table
    b.raw(mcb.RawFrame(mcb.BROADCAST_SID, mcb.encode_moveto(0x30, 0.0).data), 0.0007)  # every node
    b.cycle()
    b.ramp({"LSP": b.pos["LSP"]}, 0.5)
    return b


EXPECTED = {("speed", "LSP", 2.0), ("acceleration", "LSP", 2.0), ("acceleration", "LSP", 2.1),  # jump, stop
            ("acceleration", "LEP", 3.0),
            ("non-finite", "RSP", 4.0), ("limit", "REP", 5.0), ("address", "0x70", 6.0), ("address", "LYY", 6.0),
            ("address", "0x11", 6.0)}


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".csv", ".log", ".trc", "candump"])
def test_each_violation_is_reported_with_its_joint_time_and_kind(tmp_path: Path, suffix: str) -> None:
    b = violating_log()
    path = b.write_candump(tmp_path / "candump-2026-11-24_120000.log") if suffix == "candump" else \
        b.write(tmp_path / f"bad{suffix}")
    r = audit(path)
    assert not r.error, r.error
    assert found(r) == EXPECTED, checklog.format_report(checklog.Report([r]), TABLE)
    by = {(f.kind, f.joint): f for f in r.findings}
    assert by[("speed", "LSP")].value == pytest.approx(0.5 / 0.1, rel=1e-3) and by[("speed", "LSP")].bound == 2.0
    assert by[("acceleration", "LEP")].value == pytest.approx((0.5 + 1.8) / 0.1, rel=1e-2)
    assert by[("limit", "REP")].bound == TABLE["REP"].upper
    assert "disabled" in by[("address", "LYY")].text and "broadcast" in by[("address", "0x11")].text


def test_the_report_and_exit_status(tmp_path: Path) -> None:
    bad = violating_log().write(tmp_path / "bad.asc")
    clean = LogBuilder()
    clean.cycle()
    clean.ramp({"RSP": 0.3}, 2.0)
    good = clean.write(tmp_path / "good.asc")
    out = cli(good)
    assert out.returncode == 0 and "check-log: clean" in out.stdout, out.stdout + out.stderr
    out = cli(good, bad)
    assert out.returncode == 1, out.stdout + out.stderr
    text = out.stdout
    assert "violations: none" in text and "9 violation(s) in 2 file(s)" in text
    assert "speed 1 (LSP 1); acceleration 3 (LEP 1 LSP 2)" in text
    assert "t=    1.9991 s  speed        LSP    5.000 rad/s > 2: -0.4500 -> 0.0500 rad in 100.0 ms" in text
    assert "period 100.00 ms inferred from" in text
    assert cli("--max", "2", bad).stdout.count("t=") == 2


# --------------------------------------------------------------------------------------------- re-seeds


def _standing(gap: bool = False, home: bool = False, bogus: bool = False) -> LogBuilder:
    """LSP stands at -0.45 and is sent there; then its replies say -0.05 (after a silent gap, after a HOME, or, with
    ``bogus``, +5 rad off, once) and the next target goes to -0.05 in one 0.4 rad step."""
    b = LogBuilder(0.1)
    b.ramp({"LSP": -0.45}, 1.0)
    if gap:
        b.silent.add("LSP")
        for _ in range(5):  # 0.5 s > the 0.35 s stale window
            b.cycle()
        b.silent.clear()
    if home:
        b.raw(mcb.encode_home(TABLE["LSP"].address))
    if bogus:
        b.cycle(replies={"LSP": -0.05 + 5.0})
        b.silent.add("LSP")
    b.cycle(replies={"LSP": -0.05})
    b.cycle({"LSP": -0.05})
    return b


def test_a_re_seed_lets_the_next_step_start_from_the_measured_position(tmp_path: Path) -> None:
    r = audit(_standing(home=True).write(tmp_path / "reseed.asc"))
    assert r.ok, checklog.format_report(checklog.Report([r]), TABLE)
    assert r.commands["HOME"] == 1
    # The same replies without the HOME are a joint that moved by itself: the step is a jump; so they are after a
    # silence (nothing on the bus says why the joint should restart elsewhere).
    for how in ({}, {"gap": True}):
        r = audit(_standing(**how).write(tmp_path / "no-reseed.asc"))
        assert found_kinds(r) == {("speed", "LSP"), ("acceleration", "LSP")}


def _moving_then_silent(restate: bool) -> LogBuilder:
    """RSP cruises up at the limiter's speed, its replies lagging the targets by 0.3 rad (the node's own trajectory
    follows them); its replies stop for 0.5 s, longer than the stale window, during which it is sent nothing; then
    they resume, still lagging. The next target restates the measured position (``restate``) or goes on from the
    last target."""
    b = LogBuilder(0.1)
    b.cycle()
    b.ramp({"RSP": -0.2}, 0.1)  # the track starts at the first reply
    bounds = TABLE.motion_bounds()
    track = b.tracks["RSP"]
    for _ in range(6):
        q = motion.limit(track, 0.6, b.t, bounds)
        track.advance(q, b.t, bounds)
        b.target("RSP", q)
        b.cycle(replies={"RSP": q - 0.3})
    last = track.q
    b.silent.add("RSP")
    for _ in range(5):
        b.cycle()
    b.silent.clear()
    b.cycle(replies={"RSP": last - 0.3})
    if restate:
        b.cycle({"RSP": last - 0.3})
    else:
        b.target("RSP", motion.limit(track, 0.6, b.t, bounds))
        b.cycle()
    return b


def test_a_silence_is_no_restart_a_target_that_reverses_a_moving_joint_is_a_violation(tmp_path: Path) -> None:
    """Issue #25 item 4: a node whose replies pause for longer than the stale window keeps going to its last target;
    a daemon that restarted it at the measured position (0.3 rad behind, where the replies lag) reversed it, and the
    auditor let it pass as a re-seed. Only HOME, RESET, ZERO_ENCODER and ENABLE (frames on the bus) restart a
    track now: restating the lagging position is a violation, going on from the last target is clean."""
    reverse = _moving_then_silent(restate=True).write(tmp_path / "reverse.asc")
    on = _moving_then_silent(restate=False).write(tmp_path / "on.asc")
    for whole_run in (False, True):
        r = audit(reverse, whole_run=whole_run)
        assert ("acceleration", "RSP") in found_kinds(r) and r.reseeds == len(TABLE), r.findings
        r = audit(on, whole_run=whole_run)
        assert r.ok, checklog.format_report(checklog.Report([r]), TABLE)


@pytest.mark.parametrize("command", [mcb.Command.ZERO_ENCODER, mcb.Command.RESET])
def test_targets_after_an_encoder_restart_are_unreferenced_until_home(tmp_path: Path, command: int) -> None:
    """Issue #25 item 1: LSP at -0.9, ZERO_ENCODER (or RESET): its count restarts there, so its replies read the
    homed zero's angle (-0.45) and a target in counts is in a shifted frame -- -1.85, inside the limits in counts, is
    really -2.30. Every target until a HOME zeroed the count at the middle is ``unreferenced``; after it, none."""
    lsp = TABLE["LSP"]
    zero = lsp.to_joint(0.0)
    b = LogBuilder(0.1, pose={"LSP": -0.9})
    b.cycle()
    b.raw(mcb.encode_command(lsp.address, command))
    b.cycle(replies={"LSP": zero})
    b.cycle(replies={"LSP": zero})
    b.ramp({"LSP": zero - 0.2}, 0.5)  # "goto -1.85" as the shifted frame sees it
    r = audit(b.write(tmp_path / "zeroed.asc"))
    kinds = found_kinds(r)
    assert kinds == {("unreferenced", "LSP")}, checklog.format_report(checklog.Report([r]), TABLE)
    assert command.name in r.findings[0].text
    b.raw(mcb.encode_home(lsp.address))
    for q in (zero - 0.5, zero + 0.2):  # homing in the old frame, then the count zeroed at the middle
        b.cycle(replies={"LSP": q})
    b.cycle(replies={"LSP": zero})
    before = len(r.findings)
    b.ramp({"LSP": zero - 0.2}, 0.5)
    r = audit(b.write(tmp_path / "homed.asc"))
    assert len(r.findings) == before and found_kinds(r) == {("unreferenced", "LSP")}


def test_after_home_a_step_counts_from_the_latest_reply_not_the_first(tmp_path: Path) -> None:
    """HOME moves the joint by itself: the first reply after it is a point the homing passed, not where the joint
    is. The daemon's re-seed follows every reply up to its next target, so a target back to that first reply is a
    0.3 rad jump from where the joint stands (it used to pass: the first reply was a candidate start too)."""
    for target, clean in ((0.4, True), (0.1, False)):
        b = LogBuilder(0.1)
        b.ramp({"LSP": -0.45}, 1.0)
        b.raw(mcb.encode_home(TABLE["LSP"].address))
        for q in (0.1, 0.25, 0.4):  # homing, by itself
            b.cycle(replies={"LSP": q})
        b.cycle({"LSP": target})
        r = audit(b.write(tmp_path / f"home-{target}.asc"))
        assert r.ok if clean else found_kinds(r) == {("speed", "LSP"), ("acceleration", "LSP")}


def test_a_reply_from_before_a_home_is_no_start_after_it(tmp_path: Path) -> None:
    """A node back online (at -0.05, moved by hand) goes on from its last target; then HOME restarts its count, and
    a target before any reply after it may only continue from the last target, not from that older reply."""
    b = LogBuilder(0.1)
    b.ramp({"LSP": -0.45}, 1.0)
    b.silent.add("LSP")
    for _ in range(5):
        b.cycle()
    b.silent.clear()
    b.cycle(replies={"LSP": -0.05})
    b.raw(mcb.encode_home(TABLE["LSP"].address))
    b.target("LSP", -0.05)
    b.cycle()
    r = audit(b.write(tmp_path / "home.asc"))
    assert found_kinds(r) == {("speed", "LSP"), ("acceleration", "LSP")}


def test_a_reply_counts_exactly_when_the_daemon_takes_it(tmp_path: Path) -> None:
    """The auditor ignores a position reply by the daemon's own rule (daemon_loop.reply_in_range: the range plus 5 %
    of it, at least 0.1 rad), so it re-seeds where the daemon does. LSR's margin is 0.138 rad."""
    lsr = TABLE["LSR"]
    margin = max(daemon_loop.REPLY_RANGE_MARGIN * (lsr.upper - lsr.lower), daemon_loop.REPLY_RANGE_MIN)
    inside, outside = lsr.upper + margin - 0.01, lsr.upper + margin + 0.01
    assert margin > 0.11 and daemon_loop.reply_in_range(lsr, inside) and not daemon_loop.reply_in_range(lsr, outside)
    b = LogBuilder(0.1)
    b.cycle(replies={"LSR": inside})
    b.cycle(replies={"LSR": outside})
    r = audit(b.write(tmp_path / "replies.asc"))
    assert r.replies_ignored == 1 and r.replies_valid == 2 * len(TABLE) - 1


def test_a_target_before_any_position_is_a_violation_of_a_whole_run(tmp_path: Path) -> None:
    """A log that starts with the daemon (``--whole-run``, the tests' recorders, bench.adversary): the daemon never
    commands a joint whose position it does not know, so such a target is a ``no-position`` violation; in a log
    that may start mid-run it is only counted."""
    b = LogBuilder(0.1)
    b.cycle({"LSP": -0.45})  # before the first replies
    b.ramp({"LSP": -0.45}, 0.5)
    path = b.write(tmp_path / "early.asc")
    r = audit(path)
    assert r.ok and r.unseeded_targets == 1
    r = audit(path, whole_run=True)
    assert found(r) == {("no-position", "LSP", 0.0)} and r.unseeded_targets == 1
    out = cli("--whole-run", path)
    assert out.returncode == 1 and "no-position 1 (LSP 1)" in out.stdout, out.stdout


def test_in_a_whole_run_a_home_or_enable_ends_the_old_track_and_a_silence_does_not(tmp_path: Path) -> None:
    """In a log of one whole daemon run a HOME or an ENABLE certainly made the daemon restart the joint where it
    is: its next target may not go on from the last one. A silence does not: LSP is silent for 0.6 s and comes back
    0.4 rad away (moved by hand); its next target goes on 0.05 rad from the last one, within the bounds (the daemon
    never restarts a joint at a reply: its targets ramp from where they were). After a HOME, a target before any
    reply is one to a position nobody knows.
    Disabled and moved by hand to -0.05, then enabled, the node holds at -0.05: a target at -0.4 right after the
    ENABLE is a jump, one at -0.05 is not. Each log is clean when it may come from other software (not a whole
    run)."""
    back = LogBuilder(0.1)
    back.cycle()
    back.ramp({"LSP": -0.45}, 1.0)
    back.silent.add("LSP")
    for _ in range(6):
        back.cycle()
    back.silent.clear()
    back.cycle(replies={"LSP": -0.05})
    back.cycle({"LSP": -0.4})
    home = LogBuilder(0.1)
    home.cycle()
    home.ramp({"LSP": -0.45}, 1.0)
    home.raw(mcb.encode_home(TABLE["LSP"].address))
    home.cycle({"LSP": -0.45})
    enabled = {}
    for target in (-0.4, -0.05):
        b = enabled[target] = LogBuilder(0.1)
        b.cycle()
        b.ramp({"LSP": -0.45}, 1.0)
        b.raw(mcb.encode_disable(TABLE["LSP"].address))
        b.cycle(replies={"LSP": -0.05})
        b.raw(mcb.encode_enable(TABLE["LSP"].address))
        b.target("LSP", target)
        b.cycle()
    cases = ((back, set()), (home, {"no-position"}),
             (enabled[-0.4], {"speed", "acceleration"}), (enabled[-0.05], set()))
    for k, (b, kinds) in enumerate(cases):
        path = b.write(tmp_path / f"case{k}.asc")
        assert audit(path).ok
        r = audit(path, whole_run=True)
        assert found_kinds(r) == {(kind, "LSP") for kind in kinds}, (k, r.findings)


def test_targets_to_a_silent_joint_are_counted_and_in_a_whole_run_violations(tmp_path: Path) -> None:
    """Targets to a joint silent for longer than the stale window may never arrive: counted; in a whole daemon run
    (where the daemon sends a silent node nothing) a violation once the silence is longer than the stale window
    plus max_interval (0.35 + 0.15 s here: slack for where the daemon and the log date a reply)."""
    b = LogBuilder(0.1)
    b.cycle()
    b.ramp({"LSP": -0.45}, 1.0)
    b.silent.add("LSP")
    b.ramp({"LSP": -0.2}, 1.0)  # 10 targets, 0.098 .. 0.998 s after the last reply
    path = b.write(tmp_path / "silent.asc")
    r = audit(path)
    assert r.ok and r.silent_targets == 7
    assert "7 target(s) went to a joint silent" in checklog.format_report(checklog.Report([r]), TABLE)
    r = audit(path, whole_run=True)
    assert [(f.kind, f.joint, round(f.value, 3)) for f in r.findings] == [
        ("silent", "LSP", round(0.098 + 0.1 * k, 3)) for k in range(5, 10)]


def test_implausible_replies_are_ignored_and_never_re_seed(tmp_path: Path) -> None:
    r = audit(_standing(gap=True, bogus=True).write(tmp_path / "bogus.asc"))
    assert r.replies_ignored == 1
    assert found_kinds(r) == {("speed", "LSP"), ("acceleration", "LSP")}


# --------------------------------------------------------------------------------------------- sent, received


@pytest.mark.parametrize("suffix", [".asc", ".blf", ".log", ".trc"])
def test_frames_received_from_another_sender_are_not_host_commands(tmp_path: Path, suffix: str) -> None:
    """Issue #25 item 9: in a log that records direction (the daemon's --can-log, candump -x), only frames the host
    sent are host commands. Another sender's MOVETO to LEP (a second host, a node on a wrong ID), received by the
    host, is counted apart and never audited as the host's target (it was: a 0.5 rad jump by the daemon). The same
    frame in a log without direction is read by ID, as before: a violation."""
    b = LogBuilder(0.1)
    b.cycle()
    b.ramp({"LEP": -1.2}, 1.0)
    b.received(mcb.encode_moveto(TABLE["LEP"].address, TABLE["LEP"].to_counts(-0.7)), 0.005)
    b.received(mcb.encode_home(TABLE["LSP"].address), 0.006)
    b.ramp({"LEP": -1.2}, 0.5)
    r = audit(b.write(tmp_path / f"dir{suffix}", directions=True))
    assert r.ok and r.directions, checklog.format_report(checklog.Report([r]), TABLE)
    assert r.received_other == 2 and r.targets["LEP"] == 15 and r.commands["HOME"] == 0
    assert r.sent_frames + r.received_frames == r.frames and r.received_frames == r.replies_valid + 2
    assert "from another sender with a command's ID" in checklog.format_report(checklog.Report([r]), TABLE)
    r = audit(b.write(tmp_path / f"nodir{suffix}"))
    assert not r.directions and found_kinds(r) == {("speed", "LEP"), ("acceleration", "LEP")}
    assert r.commands["HOME"] == 1


# --------------------------------------------------------------------------------------------- period


def test_the_bounds_are_the_same_at_every_rate(tmp_path: Path) -> None:
    """Issue #25 item 5: a step counts at most motion.MAX_INTERVAL and a joint is silent after
    daemon_loop.STALE_AFTER, whatever the daemon's rate (inferred or --rate, which only labels the report): an
    inferred period that jitter made a little longer or shorter no longer moves the audit's bounds away from the
    daemon's."""
    b = LogBuilder(0.1)
    b.cycle()
    b.ramp({"LSP": 0.0}, 1.0)
    path = b.write(tmp_path / "ramp.asc")
    for rate in (None, 10.0, 100.0):
        r = audit(path, rate=rate)
        assert r.ok and r.bounds == TABLE.motion_bounds() and r.stale_after == daemon_loop.STALE_AFTER
        assert r.bounds.max_interval == motion.MAX_INTERVAL == pytest.approx(0.15)
    fast = audit(path, rate=100.0)
    assert fast.period == 0.01 and fast.period_source == "--rate 100 Hz"


def test_without_a_period_the_motion_is_still_audited(tmp_path: Path) -> None:
    b = LogBuilder()
    b.cycle()
    b.target("LSP", TABLE["LSP"].home + 0.4)  # 0.4 rad, 0.1 s after the reply
    path = b.write(tmp_path / "one-query.asc")
    r = audit(path)
    assert r.period is None and found_kinds(r) == {("speed", "LSP"), ("acceleration", "LSP")}
    out = cli(path)
    assert out.returncode == 1 and "period unknown" in out.stdout, out.stdout


# --------------------------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("name,content,message", [
    ("junk.asc", b"hello\nworld\n", "no CAN frames"),
    ("empty.log", b"", "no CAN frames"),
    ("capture.pcap", b"\xd4\xc3\xb2\xa1" + bytes(20), "unknown log format"),
    ("torn.csv", b"timestamp,arbitration_id,extended,remote,error,dlc,data\n1.0,0x4c,0,0,0,8,AAIDBAUGBwg=\n2.0,0x4\n"
                 b"3.0,0x4c,0,0,0,8,AAIDBAUGBwg=\n", "damaged after frame 1"),
])
def test_unreadable_logs_exit_2_naming_the_file(tmp_path: Path, name: str, content: bytes, message: str) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    r = audit(path)
    assert message in r.error and (name in r.error or message == "no CAN frames")
    clean = LogBuilder()
    clean.cycle()
    clean.cycle()
    out = cli(clean.write(tmp_path / "fine.asc"), path, tmp_path / "missing.asc")
    assert out.returncode == 2
    assert "fine.asc" in out.stdout and "violations: none" in out.stdout and "missing.asc" in out.stdout
    assert f"2 file(s) not (completely) audited: {name}, missing.asc" in out.stdout


def test_a_log_cut_off_mid_line_is_audited_up_to_there(tmp_path: Path) -> None:
    """A daemon SIGKILLed while its recorder writes leaves a torn last line: a warning, not an unreadable log."""
    data = violating_log().write(tmp_path / "bad.log").read_bytes()
    (tmp_path / "cut.log").write_bytes(data[:data.rindex(b"\n", 0, -1) + 6])  # "(1764" of the last line
    r = audit(tmp_path / "cut.log")
    assert not r.error and "last line is incomplete" in r.warning and found(r) == EXPECTED
    lines = data.decode().splitlines()
    lines[len(lines) // 2] = "(garbage"
    (tmp_path / "middle.log").write_text("\n".join(lines) + "\n")
    r = audit(tmp_path / "middle.log")
    assert "damaged after frame" in r.error


def test_bad_options_exit_2(tmp_path: Path) -> None:
    assert cli("--rate", "0", tmp_path / "x.asc").returncode == 2
    out = cli("--robot", "nobody", tmp_path / "x.asc")
    assert out.returncode == 2 and "unknown robot" in out.stderr
    listed = subprocess.run([str(VENV_BIN / "mds-ach"), "--help"], capture_output=True, text=True, timeout=60)
    assert "check-log" in listed.stdout
    helped = cli("--help")
    assert helped.returncode == 0 and helped.stdout.startswith("usage: mds-ach check-log")


# --------------------------------------------------------------------------------------------- real captures


SPEEDS = {"mds-LEB.-45-0deg.r2": 5.25, "mds-LEB.0--45deg.r2": 9.21, "mds-LEB.0-30deg.r2": 3.51, "mds-LEB.0deg": 3.46,
          "mds-LEB.30-0deg.r2": 3.46, "mds-LEB.30deg": 3.51, "mds-nky.0deg": 2.91, "mds-nky.25deg": 2.91}  # rad/s


def test_the_real_captures_decode_and_what_they_contain(shared_dir: Path) -> None:
    """The June 2015 captures of the original daemon (ms time stamps): every frame decodes; each holds one
    captured MOVETO (LEP for the LEB runs, NKY for the neck runs), inside the joint's limits. Each MOVETO is one
    25-45 degree step: at the original 10 Hz loop that is 2.9-9.2 rad/s, far over the 2 rad/s bound (the original
    relied on the MCB's own trajectory to ramp). The step counts from the latest position reply before it, over at
    most motion.MAX_INTERVAL whatever the cadence of the queries (one every ~5 s there): each capture's step is a
    violation (before #25 a step counted 1.5 inferred periods, 7.5 s there, and only the one whose reply came
    85 ms before it showed)."""
    files = sorted((shared_dir / REAL_LOGS).iterdir())
    assert len(files) == 8
    replies = 0
    for path in files:
        assert canio.log_format(path) == canio.MDS_DUMP
        r = audit(path)
        replies += r.replies_valid + r.replies_ignored + r.replies_unknown
        joint = "NKY" if "nky" in path.name else "LEP"
        assert dict(r.targets) == {joint: 1} and r.replies_ignored == 0
        assert found_kinds(r) == {("speed", joint), ("acceleration", joint)}
        speed = SPEEDS[path.name]
        assert [round(f.value, 2) for f in r.findings if f.kind == "speed"] == [speed]
        assert r.commands["SET TRAJECTORY_ACCELERATION"] == 1 and r.commands["SET TRAJECTORY_PERIOD"] == 1
        assert not r.error and not r.directions  # the dumps do not say who sent a frame: read by ID
        if path.name == "mds-nky.0deg":  # one position query only: no period, the same bounds
            assert r.period is None
        else:
            assert 4.0 < r.period < 8.0
        at_10hz = audit(path, rate=10.0)
        assert found_kinds(at_10hz) == {("speed", joint), ("acceleration", joint)}, at_10hz.findings
        assert all(2.9 <= f.value <= 9.3 for f in at_10hz.findings if f.kind == "speed")
    assert replies == 2408  # every ACTUAL_POSITION line of the captures (test_mcb counts the same)


def test_replay_reads_the_real_captures(shared_dir: Path) -> None:
    bus = canio.ReplayBus(path=str(shared_dir / REAL_LOGS / "mds-nky.25deg"), speed=0)
    try:
        assert len(bus.frames) > 100 and all(m.arbitration_id == mcb.HOST_SID for m in bus.frames)
    finally:
        bus.shutdown()


# --------------------------------------------------------------------------------------------- collisions


def test_collisions_of_the_commanded_pose(tmp_path: Path) -> None:
    """Both hands commanded to the same point (a limited ramp, so nothing else is wrong): the commanded pose
    collides from some batch on, reported once, with the hands' pair, until the arms are sent apart again."""
    from mds_ach import ik

    home = {"RSP": -0.445, "RSR": -1.18, "REP": -1.25, "RSY": 0.15, "LSP": -0.45, "LSR": 1.2, "LEP": -1.25,
            "LSY": -0.25, "LWR": -0.28}
    goals: dict[str, float] = {}
    for arm, names in (("left", ("LSP", "LSR", "LSY", "LEP", "LWY", "LWR")),
                       ("right", ("RSP", "RSR", "RSY", "REP", "RWY", "RWR"))):
        res = ik.solve([0.40, 0.0, -0.10], "p-x p-y p-z", arm, np.array([home.get(n, 0.0) for n in names]))
        assert res.success, res.message
        goals.update(dict(zip(names, (float(v) for v in res.q), strict=True)))
    b = LogBuilder(0.1, pose=home)
    b.cycle()
    b.ramp(goals, 4.0)
    b.ramp(home, 4.0)
    path = b.write(tmp_path / "hands.asc")
    assert audit(path).ok  # no model: nothing else is wrong
    r = audit(path, model=checklog.collision_model())
    assert [f.kind for f in r.findings] == ["collision"], r.findings
    f = r.findings[0]
    assert f.joint == "left+right" and "left_hand_link/right_hand_link" in f.text
    assert 0.2 < f.time < 1.5 and f.value >= 10 and r.poses_checked >= 70  # joints arrive at their own pace
    out = cli("--collisions", path)
    assert out.returncode == 1 and "collision 1" in out.stdout

