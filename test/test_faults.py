"""Fault injection on the simulated robot: crashed writers, CAN faults, killed nodes.

1. **A writer killed inside a put.** A child process runs the real ``ach.Channel.put``, is stopped by a line
   tracer at a chosen point of the update and SIGKILLed there, so the channel is left exactly as libach leaves
   it (``dirty`` = 1, the mutex owner dead): every handle in every process gets ``ACH_CORRUPT``. ``mds-ach
   repair`` reports it, repairs it in place (frames that are complete survive, nothing half written is ever
   returned), open handles work again, and the other channels are not touched.
2. **CAN faults** on the daemon loop (simulated clock and bus) while the arms move: a silent node, error frames,
   bus-off, garbled frames. Each is flagged in ``mds-daemon-status``, recovers, and every MOVETO that reaches the
   bus is inside the joint's limits and obeys the motion bounds (``motion_audit``).
3. **The running system** (daemon --nocan, mux, filter, collision gate, IK, bridge; each its own process):
   SIGKILL each node while the arms move. The daemon holds the last safe reference, the state stream goes on,
   and restarting the node resumes the motion without a jump. A writer killed inside a put on a pipeline
   channel is reported and repaired with ``mds-ach repair`` while everything keeps running. Every daemon's CAN
   log obeys the motion bounds.
4. **A client holding a channel lock** (stopped inside a get): the daemon skips and counts, never stalls.
"""

from __future__ import annotations

import ctypes
import math
import os
import select
import signal
import struct
import subprocess
import sys
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from conftest import VENV_BIN, in_netns, remove_mds_channels, wait_for
from motion_audit import MemoryLog, audit, read_log

import mds_ach as mds
from mds_ach import ach
from mds_ach.ach import repair
from mds_ach.bus import canio, mcb
from mds_ach.bus.constants import (
    CAN_ERR_BUSERROR,
    CAN_ERR_CRTL,
    CAN_ERR_CRTL_ACTIVE,
    CAN_ERR_CRTL_RX_PASSIVE,
    CAN_ERR_CRTL_TX_WARNING,
    CAN_ERR_PROT,
)
from mds_ach.bus.mcb import Command, StateArg
from mds_ach.bus.simbus import ManualClock, SimNetwork
from mds_ach.nodes.daemon_loop import DaemonChannels, DaemonLoop
from mds_ach.robot import access as channel_access
from mds_ach.robot import config
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import MDS_CMD, MDS_REF, MDS_STATE
from mds_ach.robot.msgs import daemon_status as ds

TABLE = config.load("default")


# ============================================================================================ 1. crashed writers

TEST_CHANNEL = "test-faults"


def payload(seq: int) -> bytes:
    """Frame ``seq`` of a test writer: seq, length, CRC32 and a seq-dependent pattern; sizes vary so the data
    ring wraps. ``check_payload`` recognises any complete frame and refuses a torn one."""
    size = 64 + (seq * 37) % 160
    body = bytes((seq * 7 + i) & 0xFF for i in range(size - 16))
    head = struct.pack("<QI", seq, size)
    return head + struct.pack("<I", zlib.crc32(head + body)) + body


def check_payload(frame: bytes) -> int:
    """The frame's seq if it is a complete ``payload``; AssertionError otherwise."""
    assert len(frame) >= 16, f"torn frame of {len(frame)} bytes"
    seq, size = struct.unpack_from("<QI", frame)
    crc, = struct.unpack_from("<I", frame, 12)
    assert size == len(frame) and frame == payload(seq), f"torn or corrupt frame (seq {seq}, {len(frame)} bytes)"
    assert zlib.crc32(frame[:12] + frame[16:]) == crc
    return seq


STUCK_WRITER = """
import inspect, sys, time
from mds_ach import ach
from test_faults import payload

name, before, marker = sys.argv[1], int(sys.argv[2]), sys.argv[3]
ch = ach.Channel(name, create=False, fast=False)  # the pure-Python put, so a trace can stop it half-way
for seq in range(1, before + 1):
    ch.put(payload(seq))
lines, first = inspect.getsourcelines(ach.Channel._write_locked)
stop = first + next(i for i, text in enumerate(lines) if marker in text)
code = ach.Channel._write_locked.__code__

def local(frame, event, arg):
    if event == "line" and frame.f_lineno == stop:
        print("stuck", flush=True)
        time.sleep(600)
    return local

sys.settrace(lambda frame, event, arg: local if frame.f_code is code else None)
ch.put(payload(before + 1))
print("finished", flush=True)
"""

# Points inside ach.Channel._write_locked (the line about to run when the writer dies) and the frames a repair
# keeps. The writer has put frames 1..6 into 4 slots (3..6 live) and dies putting frame 7, which evicts frame 3.
PUT_STAGES: dict[str, tuple[str, list[int]]] = {
    "dirty set": ("ix = self._ix", [3, 4, 5, 6]),
    "evicting the oldest frame": ("data_free += q[e]", [3, 4, 5, 6]),
    "copying the data": ("self._mv[start:start + n] = src", [4, 5, 6]),
    "data copied": ("seq = last + 1", [4, 5, 6]),
    "last_seq bumped": ("q[e] = n", [4, 5, 6]),
    "index entry half written": ("q[e + 2] = seq", [4, 5, 6]),
    "entry written, heads not moved": ("q[Q_DATA_HEAD] = (data_head + n) % dsize", [4, 5, 6, 7]),
    "data head moved, index head not": ("q[Q_INDEX_HEAD] = (index_head + 1) % cnt", [4, 5, 6]),
}


class StuckWriter:
    """A child process that puts ``before`` frames, then stops inside the next put at ``marker`` (holding the
    lock). ``kill()`` SIGKILLs it there: a writer that died mid-put."""

    def __init__(self, name: str, before: int, marker: str) -> None:
        env = dict(os.environ, PYTHONPATH=f"{Path(__file__).parent}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
        self.proc = subprocess.Popen([sys.executable, "-c", STUCK_WRITER, name, str(before), marker], env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], 60)
        line = self.proc.stdout.readline().strip() if ready else ""
        if line != "stuck":
            self.proc.kill()
            raise AssertionError(f"the writer did not stop inside put (printed {line!r}):\n{self.proc.stderr.read()}")

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)
        self.proc.stdout.close()
        self.proc.stderr.close()


def test_writer_killed_holding_the_lock_before_marking_dirty_harms_nothing(clean_shm: None) -> None:
    """Like libach: the next locker recovers the mutex (EOWNERDEAD), and a clean channel carries on."""
    ach.create(TEST_CHANNEL, 4, 256)
    StuckWriter(TEST_CHANNEL, before=6, marker="self._i32[self._i_dirty] = 1").kill()
    with ach.Channel(TEST_CHANNEL, create=False) as ch:
        assert [check_payload(f) for f in read_all(ch)] == [3, 4, 5, 6]
        ch.put(payload(7))
    report = repair.repair(TEST_CHANNEL)
    assert report.ok and report.action == ""


WAITER = """
from mds_ach import ach
c = ach.Channel("test-faults", create=False)
c.flush()
print("waiting", flush=True)
c.get(bytearray(256), wait=True)
"""
WRITER = """
from mds_ach import ach
c = ach.Channel("test-faults", create=False)
for _ in range(3):
    c.put(b"x" * 10)
"""


def test_reader_killed_while_waiting_does_not_wedge_the_writers(clean_shm: None) -> None:
    """Any node blocked in ``get(wait=True)`` may be SIGKILLed (that is what this module does to every node). The
    channel must stay usable: later writers must not hang. glibc's process-shared condvar is not robust: a waiter
    killed inside ``pthread_cond_(timed)wait`` keeps a group reference forever and the next
    ``pthread_cond_broadcast`` waits for it to drop, i.e. forever. Waiting through the condvar is therefore not
    safe for readers that can be killed (e.g. wait on a futex keyed on last_seq, which the kernel cleans up)."""
    ach.create(TEST_CHANNEL, 4, 256)
    for trial in range(10):
        waiter = subprocess.Popen([sys.executable, "-c", WAITER], stdout=subprocess.PIPE, text=True)
        assert waiter.stdout.readline().strip() == "waiting"
        time.sleep(0.05)  # inside the wait
        waiter.kill()
        waiter.wait(10)
        waiter.stdout.close()
        writer = subprocess.Popen([sys.executable, "-c", WRITER])
        try:
            writer.wait(10)
        except subprocess.TimeoutExpired:
            writer.kill()
            writer.wait(10)
            raise AssertionError(f"trial {trial}: a writer hangs in put() after a reader was killed while waiting "
                                 "(pthread_cond_broadcast waits for the dead waiter)") from None
        assert writer.returncode == 0


def read_all(ch: ach.Channel) -> list[bytes]:
    """Every frame the handle has not seen yet, in order."""
    frames = []
    buf = bytearray(ch.data_size)
    while True:
        status, size = ch.get(buf)
        if status == ach.ACH_STALE_FRAMES:
            return frames
        assert status in (ach.ACH_OK, ach.ACH_MISSED_FRAME), ach.result_string(status)
        frames.append(bytes(buf[:size]))


def mds_ach_cli(*args: str, timeout: float = 60.0, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([str(VENV_BIN / "mds-ach"), *args], capture_output=True, text=True, timeout=timeout,
                          env=env)


@pytest.mark.parametrize("stage", list(PUT_STAGES))
def test_writer_killed_inside_a_put_is_reported_and_repaired_in_place(clean_shm: None, stage: str) -> None:
    ach.create(TEST_CHANNEL, 4, 256)
    reader = ach.Channel(TEST_CHANNEL, create=False)
    assert [check_payload(f) for f in read_all(reader)] == []
    marker, survivors = PUT_STAGES[stage]
    writer = StuckWriter(TEST_CHANNEL, before=6, marker=marker)  # 6 > 4 frames: the index is full
    writer.kill()

    # Exactly as libach: dirty stays 1 and every get/put in every process says ACH_CORRUPT.
    with open(ach.shm_path(TEST_CHANNEL), "rb") as f:
        assert ach.parse_image(f.read()).dirty == 1
    late = ach.Channel(TEST_CHANNEL, create=False)
    for handle in (reader, late):
        assert handle.get_status(bytearray(256))[0] == ach.ACH_CORRUPT
        assert handle.put_status(payload(99)) == ach.ACH_CORRUPT
    report = repair.check(TEST_CHANNEL)
    assert report.state == repair.CORRUPT and "died inside a put" in report.detail

    fixed = repair.repair(TEST_CHANNEL)
    assert fixed.ok and fixed.action == "repaired", fixed.line()
    assert repair.check(TEST_CHANNEL).ok
    # Only complete frames survive, in order: at most the interrupted one and the one it evicted are lost.
    assert [check_payload(f) for f in read_all(reader)] == survivors
    assert fixed.kept == len(survivors)
    for seq in range(50, 62):  # a new writer (the old handle) wraps the ring a few times: nothing goes wrong
        late.put(payload(seq))
        got = [check_payload(f) for f in read_all(reader)]
        assert got == [seq]
    assert [check_payload(f) for f in read_all(late)][-1] == 61
    reader.close()
    late.close()


def without_sync(name: str) -> bytes:
    """The channel file with the mutex and condvar masked: glibc leaves robust-list pointers in an unlocked
    mutex, so a lock/unlock pair changes those bytes without changing anything Ach means."""
    data = bytearray(Path(ach.shm_path(name)).read_bytes())
    layout = ach.native_layout()
    data[layout.mutex:layout.dirty] = bytes(layout.dirty - layout.mutex)
    return bytes(data)


def test_repair_leaves_healthy_channels_byte_identical(clean_shm: None) -> None:
    names = list(mds.ALL_CHANNELS)
    for name in names:  # as 'mds-ach make' does (mds-ref 0640: a looser one is reported unsafe)
        ach.create(name, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE, mode=channel_access.channel_mode(name))
    with ach.Channel(mds.MDS_CHAN_STATE_NAME, create=False) as st, \
            ach.Channel(mds.MDS_CHAN_REF_NAME, create=False) as ref:
        for k in range(13):
            st.put(bytes([k]) * ctypes.sizeof(MDS_STATE))
            ref.put(bytes([k]) * ctypes.sizeof(MDS_REF))
    writer = StuckWriter(mds.MDS_CHAN_REF_FILTER_NAME, before=3, marker=PUT_STAGES["copying the data"][0])
    writer.kill()
    before = {n: without_sync(n) for n in names if n != mds.MDS_CHAN_REF_FILTER_NAME}

    check = mds_ach_cli("repair", "--check")
    assert check.returncode == 1, check.stdout + check.stderr
    corrupt = [line.split()[0] for line in check.stderr.splitlines() if "corrupt" in line]
    assert corrupt == [mds.MDS_CHAN_REF_FILTER_NAME], check.stderr
    fixed = mds_ach_cli("repair")
    assert fixed.returncode == 0, fixed.stdout + fixed.stderr
    assert "repaired in place" in fixed.stdout and mds.MDS_CHAN_REF_FILTER_NAME in fixed.stdout
    assert mds_ach_cli("repair", "--check", "-q").returncode == 0
    after = {n: without_sync(n) for n in before}
    assert after == before  # the healthy channels were looked at under their lock, never written


def test_channel_held_by_a_live_stuck_process_is_reported_not_broken(clean_shm: None) -> None:
    ach.create(TEST_CHANNEL, 4, 256)
    writer = StuckWriter(TEST_CHANNEL, before=2, marker=PUT_STAGES["data copied"][0])
    try:
        report = repair.repair(TEST_CHANNEL, timeout=0.3)
        assert report.state == repair.LOCKED and f"pid {writer.proc.pid}" in report.detail, report.line()
        cli = mds_ach_cli("repair", "--timeout", "0.3", TEST_CHANNEL)
        assert cli.returncode == 1 and "locked" in cli.stderr
    finally:
        writer.kill()
    assert repair.repair(TEST_CHANNEL).action == "repaired"


def test_broken_header_is_recreated_and_its_users_listed(clean_shm: None) -> None:
    ach.create(TEST_CHANNEL, 5, 300, mode=0o640)
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\nfrom mds_ach import ach\n"
                               f"c = ach.Channel({TEST_CHANNEL!r}, create=False)\nprint('open', flush=True)\n"
                               "time.sleep(600)"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "open"
        layout = ach.native_layout()
        with open(ach.shm_path(TEST_CHANNEL), "r+b") as f:  # scribble over the header guard
            f.seek(layout.header_size)
            f.write(b"\0" * 8)
        assert repair.check(TEST_CHANNEL).state == repair.BROKEN
        cli = mds_ach_cli("repair", TEST_CHANNEL)
        assert cli.returncode == 0, cli.stderr
        assert "re-created" in cli.stdout and str(holder.pid) in cli.stdout, cli.stdout
        with ach.Channel(TEST_CHANNEL, create=False) as ch:
            assert (ch.frame_count, ch.frame_size) == (5, 300)
            ch.put(payload(1))
        assert os.stat(ach.shm_path(TEST_CHANNEL)).st_mode & 0o777 == 0o640
    finally:
        holder.kill()
        holder.wait(10)
        holder.stdout.close()


def test_repair_command_usage_errors(clean_shm: None) -> None:
    assert mds_ach_cli("repair", "--recreate").returncode == 2
    assert mds_ach_cli("repair", "bad/name").returncode == 2
    missing = mds_ach_cli("repair", "--check", TEST_CHANNEL)
    assert missing.returncode == 1 and "missing" in missing.stderr
    assert mds_ach_cli("repair").returncode == 0  # no channels at all: nothing to do


# ============================================================================================ 2. CAN faults

MOVING = ("LSP", "LEP", "LWY", "RSP", "REP", "NKY")  # arms and neck, commanded every cycle
AMPLITUDE = 0.15  # rad
MOTION_PERIOD = 4.0  # s


def counts_range(j: config.JointConfig) -> tuple[float, float]:
    a, b = j.to_counts(j.lower), j.to_counts(j.upper)
    return min(a, b), max(a, b)


def unsafe_commands(sent: list[tuple[float, mcb.McbFrame]]) -> list[str]:
    """Every frame on the bus that could move a joint somewhere it must not go: a MOVETO (or SET_TARGET) outside the
    joint's limits in counts, not finite, or addressed to a joint that is disabled or not in the table."""
    bad = []
    for _, f in sent:
        target = (f.command == Command.SET and f.argument == StateArg.MOVETO_TARGET) or f.command == Command.SET_TARGET
        if not target:
            continue
        j = TABLE.get(f.arbitration_id)
        if j is None or not j.enabled:
            bad.append(f"{f} to a joint that is not enabled")
            continue
        lo, hi = counts_range(j)
        if not (math.isfinite(f.value) and lo - 0.5 <= f.value <= hi + 0.5):
            bad.append(f"{f}: {j.short} limits are [{lo:.1f}, {hi:.1f}] counts")
    return bad


@dataclass
class CanRig:
    """The daemon loop on a simulated clock and bus, with a client that moves the arms every cycle."""

    clock: ManualClock
    net: SimNetwork
    io: canio.CanIO
    channels: DaemonChannels
    loop: DaemonLoop
    ref_out: StructChannel
    status_in: StructChannel
    cmd_out: StructChannel
    centre: dict[str, float] = field(default_factory=dict)
    states: list[MDS_STATE] = field(default_factory=list)
    t: float = 0.0
    cmd_seq: int = 0

    @classmethod
    def start(cls, rate: float = 10.0) -> CanRig:
        clock = ManualClock()
        net = SimNetwork.from_table(TABLE, pose={"LEP": -1.0, "REP": -1.0, "LSP": -0.3, "RSP": -0.3}, clock=clock)
        io = canio.make_canio(nocan=True, network=net)
        io.recorder = MemoryLog(clock)
        channels = DaemonChannels.open()
        loop = DaemonLoop(TABLE, io, channels, rate_hz=rate, nocan=True, clock=clock)
        rig = cls(clock, net, io, channels, loop, StructChannel(mds.MDS_CHAN_REF_NAME, MDS_REF),
                  StructChannel(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS),
                  StructChannel(mds.MDS_CHAN_BOARD_CMD_NAME, MDS_CMD))
        loop.start_up()
        rig.centre = {s: loop.state.joint[TABLE[s].address].ref for s in MOVING}
        return rig

    def close(self) -> None:
        self.loop.stop()
        self.io.close()
        self.channels.close()
        for ch in (self.ref_out, self.status_in, self.cmd_out):
            ch.close()

    def target(self, short: str, t: float) -> float:
        j = TABLE[short]
        return j.clamp(self.centre[short] + AMPLITUDE * math.sin(2 * math.pi * t / MOTION_PERIOD))

    def run(self, seconds: float, inject: Callable[[CanRig], None] | None = None, move: bool = True,
            mode: int = mds.MDS_REF_MODE_REF) -> None:
        """Run ``seconds`` of robot time; with ``move`` one mds-ref frame per cycle moves the arms (``mode`` for the
        moving joints, pass-through by default; the others hold their reference)."""
        for _ in range(max(1, round(seconds / self.loop.period))):
            if move:
                ref = MDS_REF()
                for j in TABLE:
                    r = self.loop.state.joint[j.address].ref_r
                    ref.joint[j.address].ref = r if math.isfinite(r) else self.loop.state.joint[j.address].ref
                    ref.joint[j.address].mode = mds.MDS_REF_MODE_REF
                for s in MOVING:
                    ref.joint[TABLE[s].address].ref = self.target(s, self.t)
                    ref.joint[TABLE[s].address].mode = mode
                self.ref_out.put(ref)
            if inject is not None:
                inject(self)
            start = self.clock.now
            self.loop.cycle(deadline=start, start=start)
            self.clock.now = max(self.clock.now, start + self.loop.period)
            self.t += self.loop.period
            self.states.append(MDS_STATE.from_buffer_copy(self.loop.state))

    def status(self) -> ds.MDS_DAEMON_STATUS:
        st = None
        while (frame := self.status_in.latest()) is not None:
            st = frame
        return st if st is not None else ds.MDS_DAEMON_STATUS.from_buffer_copy(self.loop.status)

    def command(self, code: int) -> None:
        self.cmd_seq += 1
        self.cmd_out.put(MDS_CMD(seq=self.cmd_seq, cmd=code))

    def pos(self, short: str) -> float:
        return self.loop.state.joint[TABLE[short].address].pos

    def measured(self, short: str) -> float:
        return TABLE[short].to_joint(self.net.position(TABLE[short].address))

    def travel(self, short: str, since: int) -> float:
        """How far the joint's measured position moved over the states recorded since index ``since``."""
        a = TABLE[short].address
        values = [s.joint[a].pos for s in self.states[since:] if s.joint[a].active]
        return max(values) - min(values) if values else 0.0


@pytest.fixture
def can_rig(clean_shm: None) -> Iterator[CanRig]:
    rig = CanRig.start()
    rig.run(2.0)
    assert rig.travel("LSP", 0) > 0.05, "the arms do not move"
    yield rig
    try:
        assert unsafe_commands(rig.net.commands) == []
        assert all(math.isfinite(s.joint[TABLE[n].address].ref) for s in rig.states for n in MOVING)
        bounded = audit(rig.io.recorder.frames, TABLE, rig.loop.bounds, rig.loop.stale_after)
        assert bounded.violations == [], bounded.violations
    finally:
        rig.close()


def test_silent_node_is_flagged_and_recovers_while_the_arms_move(can_rig: CanRig) -> None:
    rig = can_rig
    lep = TABLE["LEP"]
    rig.net.set_offline(lep.address)  # it finishes the move it had, then takes no new target
    mark = len(rig.states)
    rig.run(rig.loop.stale_after + 1.0)
    st = rig.status()
    assert st.stale_count == 1 and st.joint_flags[lep.address] & ds.JOINT_STALE
    assert rig.loop.state.joint[lep.address].active == 0
    frozen_at = rig.measured("LEP")
    rig.run(0.5)
    assert rig.measured("LEP") == frozen_at and rig.loop.state.joint[lep.address].active == 0
    assert rig.travel("RSP", mark) > 0.05 and rig.travel("LSP", mark) > 0.05  # everything else moves on
    rig.net.set_offline(lep.address, False)
    mark = len(rig.states)
    rig.run(2.0)
    st = rig.status()
    assert st.stale_count == 0 and st.joint_flags[lep.address] & ds.JOINT_FRESH
    assert rig.travel("LEP", mark) > 0.05  # back under control: it follows its reference again
    assert rig.pos("LEP") == pytest.approx(rig.measured("LEP"), abs=0.02)


def test_error_frames_are_flagged_and_motion_goes_on(can_rig: CanRig) -> None:
    rig = can_rig
    mark = len(rig.states)
    rig.run(1.0, inject=lambda r: r.net.inject_error_frame(CAN_ERR_PROT | CAN_ERR_BUSERROR))
    st = rig.status()
    assert st.error_frames >= 10 and st.bus_state == ds.BUS_STATE_ACTIVE  # bus errors alone change no state
    rig.net.inject_error_frame(CAN_ERR_CRTL, status=CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_WARNING)
    rig.run(1.0)
    assert rig.status().bus_state == ds.BUS_STATE_PASSIVE
    assert rig.travel("LSP", mark) > 0.05 and rig.status().stale_count == 0  # frames still get through
    rig.command(mds.MDS_CMD_RESET_BUS)  # what `mds-ach resetbus` sends
    rig.run(0.5)
    st = rig.status()
    assert st.bus_state == ds.BUS_STATE_ACTIVE and st.bus_resets == 1 and st.cmd_result == ds.CMD_OK


def test_error_passive_clears_when_the_controller_reports_error_active(can_rig: CanRig) -> None:
    """SocketCAN reports the way back too: CAN_ERR_CRTL with data[1] = CAN_ERR_CRTL_ACTIVE (0x40). A transient
    error-passive phase must not leave the daemon warning until someone resets a healthy bus."""
    rig = can_rig
    rig.net.inject_error_frame(CAN_ERR_CRTL, status=CAN_ERR_CRTL_RX_PASSIVE)
    rig.run(0.5)
    assert rig.status().bus_state == ds.BUS_STATE_PASSIVE
    rig.net.inject_error_frame(CAN_ERR_CRTL, status=CAN_ERR_CRTL_ACTIVE)
    rig.run(0.5)
    assert rig.status().bus_state == ds.BUS_STATE_ACTIVE


def test_bus_off_sends_nothing_and_resetbus_recovers(can_rig: CanRig) -> None:
    rig = can_rig
    rig.net.bus_off()
    sent_before = len(rig.net.commands)
    rig.run(1.5)
    st = rig.status()
    assert st.bus_state == ds.BUS_STATE_BUS_OFF and st.bus_off_count == 1 and st.tx_errors > 0
    assert len(rig.net.commands) == sent_before  # nothing reached the bus
    assert rig.states[-1].time > rig.states[-15].time  # the state stream goes on
    held = rig.measured("LSP")
    rig.run(0.5)
    assert rig.measured("LSP") == held  # the robot stands still (its last move had ended)
    rig.command(mds.MDS_CMD_RESET_BUS)
    mark = len(rig.states)
    rig.run(2.0)
    st = rig.status()
    assert st.bus_state == ds.BUS_STATE_ACTIVE and st.bus_resets == 1 and st.stale_count == 0
    assert rig.travel("LSP", mark) > 0.05  # moving again


def test_garbled_frames_are_counted_and_never_taken_as_positions(can_rig: CanRig) -> None:
    rig = can_rig
    lsp = TABLE["LSP"]
    nan = struct.unpack("<I", struct.pack("<f", math.nan))[0]
    inf = struct.unpack("<I", struct.pack("<f", math.inf))[0]

    def garble(r: CanRig) -> None:
        r.net.inject_frame(mcb.HOST_SID, mcb.pack(mcb.Response.STATE, StateArg.ACTUAL_POSITION, nan, lsp.address))
        r.net.inject_frame(mcb.HOST_SID, mcb.pack(mcb.Response.STATE, StateArg.ACTUAL_POSITION, inf, lsp.address))
        r.net.inject_frame(mcb.HOST_SID, b"\x01\x02\x03")  # short
        r.net.inject_frame(mcb.HOST_SID, bytes(8), is_extended_id=True)
        r.net.inject_frame(mcb.HOST_SID, bytes([0xFF] * 8))  # unknown response from node 0xFFFF
        r.net.inject_frame(0x7FF, bytes(range(8)))  # another host's traffic
        r.net.inject_frame(mcb.HOST_SID, mcb.pack(mcb.Response.STATE, StateArg.ACTUAL_POSITION, 0, 0x3F))

    mark = len(rig.states)
    rig.run(1.0, inject=garble)
    st = rig.status()
    assert st.malformed_frames >= 40 and st.unknown_node_frames >= 20, ds.summary_line(st)
    positions = [s.joint[lsp.address].pos for s in rig.states[mark:]]
    assert all(math.isfinite(p) for p in positions)
    assert rig.travel("LSP", mark) > 0.05 and st.stale_count == 0
    assert rig.pos("LSP") == pytest.approx(rig.measured("LSP"), abs=0.05)


# ============================================================================================ 3. the running system

# Kill order: the filter and the daemon wait on no channel; the others block in get(wait=True) when killed.
NODES = ("filter", "mux", "collision", "ik", "bridge")
SYSTEM_MOVING = ("LSP", "LEP", "RSP", "REP")  # driven through mds-ref-filter (the mux's default input)
SYSTEM_AMPLITUDE = 0.2  # rad
SYSTEM_PERIOD = 3.0  # s: at most 0.42 rad/s, well inside the filter's 1.57 rad/s
GATE_SPEED = 2.0  # rad/s, config/collision.yaml max_velocity: no reference may move faster
START_TIMEOUT = 150.0  # s: cold imports (torch, fcl, rclpy) on a shared 2-core machine
MODEL = [mds.BY_SHORT[n].address for n in mds.joints.MODEL_JOINTS]
HEARTBEATS = {  # node -> a channel it writes periodically (mds-collide: reports at 10 Hz even without input)
    "daemon": mds.MDS_CHAN_STATE_NAME,
    "mux": mds.MDS_CHAN_MUX_STATE_NAME,
    "filter": mds.MDS_CHAN_REF_SMOOTH_NAME,
    "collision": mds.MDS_CHAN_COLLIDE_NAME,
}


def bounded(fn: Callable[[], object], timeout: float, what: str) -> object:
    """Run ``fn`` on a helper thread; fail (instead of hanging the test run) if it does not return in time. Ach
    calls from this process go through here when a killed node may have wedged the channel."""
    result: list[object] = []
    error: list[BaseException] = []

    def body() -> None:
        try:
            result.append(fn())
        except BaseException as exc:  # handed to the test thread
            error.append(exc)

    t = threading.Thread(target=body, name=what, daemon=True)
    t.start()
    t.join(timeout)
    assert not t.is_alive(), f"{what} hangs (more than {timeout:g} s)"
    if error:
        raise error[0]
    return result[0] if result else None


class Driver:
    """A legacy client moving both arms: read-modify-write of mds-ref-filter at 20 Hz (sinusoids around the pose
    the mux seeded). Put errors (a corrupt channel) are counted and retried, as a careful client would."""

    def __init__(self) -> None:
        with StructChannel(mds.MDS_CHAN_REF_FILTER_NAME, MDS_REF) as seeded:
            base = seeded.latest()
        assert base is not None, "the mux did not seed mds-ref-filter"
        self.base = base
        self.centre = {s: TABLE[s].clamp(base.joint[TABLE[s].address].ref) for s in SYSTEM_MOVING}
        self.chan = ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME, create=False)
        self.errors = 0
        self.puts = 0
        self.last_put = time.monotonic()
        self.phase = 0.0
        self.offset = 0.0  # added to every target (to move the commanded pose away from where the robot is)
        self.frozen: float | None = None  # hold the sinusoid at this phase
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="driver", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        t0 = time.monotonic()
        while not self._stop.wait(0.05):
            frame = MDS_REF.from_buffer_copy(self.base)
            phase = math.sin(2 * math.pi * (time.monotonic() - t0) / SYSTEM_PERIOD)
            if self.frozen is not None:
                phase = self.frozen
            self.phase = phase
            for s in SYSTEM_MOVING:
                target = self.centre[s] + SYSTEM_AMPLITUDE * phase + self.offset
                frame.joint[TABLE[s].address].ref = TABLE[s].clamp(target)
            try:
                self.chan.put(frame)
                self.puts += 1
            except ach.AchException:
                self.errors += 1
            self.last_put = time.monotonic()

    @property
    def stuck(self) -> bool:
        """Its put has not returned for two seconds: the channel is wedged (or a lock is held)."""
        return time.monotonic() - self.last_put > 2.0

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        if not self._thread.is_alive():  # a put stuck in the channel: leave the handle to the process exit
            self.chan.close()


@dataclass
class Frame:
    received: float  # time.monotonic() at receipt
    time: float  # state.time
    ref: np.ndarray  # by address
    pos: np.ndarray


class Recorder:
    """Every mds-state frame, with its receipt time, from a background thread (it polls: it can never hang on a
    wedged channel)."""

    def __init__(self) -> None:
        self.frames: list[Frame] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._chan = StructChannel(mds.MDS_CHAN_STATE_NAME, MDS_STATE)
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            st = self._chan.latest()  # polled: a blocking wait could hang on a condvar wedged by a killed node
            if st is None:
                time.sleep(0.005)
            else:
                ref = np.array([st.joint[a].ref for a in range(mds.MDS_JOINT_COUNT)])
                pos = np.array([st.joint[a].pos for a in range(mds.MDS_JOINT_COUNT)])
                with self._lock:
                    self.frames.append(Frame(time.monotonic(), st.time, ref, pos))

    def mark(self) -> int:
        with self._lock:
            return len(self.frames)

    def since(self, mark: int) -> list[Frame]:
        with self._lock:
            return self.frames[mark:]

    def last(self) -> Frame:
        wait_for(lambda: self.mark() > 0, 10, what="an mds-state frame")
        with self._lock:
            return self.frames[-1]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self._chan.close()


def travel(frames: list[Frame], short: str) -> float:
    a = TABLE[short].address
    values = [f.ref[a] for f in frames]
    return max(values) - min(values) if values else 0.0


def assert_no_jump(frames: list[Frame], what: str) -> None:
    """Between consecutive state frames no modelled joint's reference moves faster than the gate allows, and every
    reference is inside its joint's limits."""
    for f0, f1 in zip(frames, frames[1:], strict=False):
        dt = f1.time - f0.time
        step = np.abs(f1.ref[MODEL] - f0.ref[MODEL])
        k = int(np.argmax(step))
        assert step[k] <= GATE_SPEED * dt + 0.02, \
            f"{what}: {mds.BY_ADDRESS[MODEL[k]].short} jumped {step[k]:.3f} rad in {dt:.3f} s"
    for f in frames:
        for j in TABLE.enabled:
            assert j.lower - 1e-9 <= f.ref[j.address] <= j.upper + 1e-9, f"{what}: {j.short} ref outside its limits"


def live(channel: str, within: float = 1.5) -> bool:
    """Does someone still publish on ``channel`` (a new frame within ``within`` s)? Polls without waiting on the
    channel's condvar, which a killed node may have wedged."""
    with ach.Channel(channel, create=False) as ch:
        ch.flush()
        buf = bytearray(ch.data_size)
        deadline = time.monotonic() + within
        while time.monotonic() < deadline:
            if ch.get(buf)[0] in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
                return True
            time.sleep(0.02)
    return False


def pipeline_lsp() -> str:
    """LSP's newest reference and mode on each pipeline channel: where a motion stops when it does not arrive (a
    channel whose lock is held is reported with the holder instead of being read)."""
    parts = []
    for name in (mds.MDS_CHAN_REF_FILTER_NAME, mds.MDS_CHAN_REF_MUX_NAME, mds.MDS_CHAN_REF_SMOOTH_NAME,
                 mds.MDS_CHAN_REF_NAME):
        health = repair.check(name, timeout=0.2)
        if not health.ok:
            parts.append(f"{name}: {health.state}: {health.detail}")
            continue
        frame = MDS_REF()
        with ach.Channel(name, create=False) as ch:
            status, size = ch.get(frame, last=True, copy=True)
            seq = ch.last_seq
        j = frame.joint[TABLE["LSP"].address]
        parts.append(f"{name} seq {seq}: {j.ref:.4f}/{j.mode}" if size == ctypes.sizeof(frame) else f"{name}: -")
    return "LSP " + ", ".join(parts)


class System:
    """daemon --nocan (with a CAN log), then `mds-ach start --only` the other nodes; the driver and the recorder."""

    def __init__(self, rt: Path) -> None:
        self.rt = rt
        self.can_logs: list[Path] = []
        self.driver: Driver | None = None
        self.recorder: Recorder | None = None

    def cli(self, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
        return mds_ach_cli(*args, timeout=timeout)

    def start(self, pose: dict[str, float] | None = None) -> None:
        from mds_ach.robot.channels import make_channels

        assert all(r.ok for r in make_channels())
        self.start_daemon(pose)
        self.start_nodes(*NODES)
        self.recorder = Recorder()
        self.driver = Driver()
        self.moving(20)

    def start_daemon(self, pose: dict[str, float] | None = None) -> None:
        from mds_ach.tools import launcher

        log = self.rt / f"can-{len(self.can_logs) + 1}.asc"
        self.can_logs.append(log)
        args = ["--nocan", "--can-log", str(log)]
        if pose:
            args += ["--sim-pose", ",".join(f"{k}={v:.6f}" for k, v in pose.items())]
        with StructChannel(mds.MDS_CHAN_STATE_NAME, MDS_STATE) as state:
            state.flush()
            proc = launcher.start_node("daemon", args, self.rt)
            deadline = time.monotonic() + START_TIMEOUT
            frames = 0
            while frames < 2:
                assert proc.poll() is None, f"daemon exited:\n{launcher.log_tail('daemon', rt=self.rt)}"
                assert time.monotonic() < deadline, f"daemon not up:\n{launcher.log_tail('daemon', rt=self.rt)}"
                frames += state.latest() is not None
                time.sleep(0.02)

    def start_nodes(self, *names: str) -> None:
        proc = self.cli("start", "--only", *names, "--timeout", str(START_TIMEOUT), timeout=START_TIMEOUT + 30)
        assert proc.returncode == 0, f"mds-ach start --only {' '.join(names)}:\n{proc.stdout}\n{proc.stderr}"

    def pid(self, name: str) -> int | None:
        from mds_ach.tools import launcher

        return launcher.read_pid(name, self.rt)

    def kill(self, name: str) -> None:
        pid = self.pid(name)
        assert pid is not None, f"{name} is not running"
        os.kill(pid, signal.SIGKILL)
        wait_for(lambda: self.pid(name) is None, 10, what=f"{name} to die")

    def log(self, name: str) -> str:
        from mds_ach.tools import launcher

        path = launcher.log_path(name, self.rt)
        return path.read_text(errors="replace") if path.exists() else ""

    def moving(self, timeout: float = 10.0) -> None:
        """Wait until the arms are seen moving (the driver's motion reaches the daemon)."""
        mark = self.recorder.mark()
        deadline = time.monotonic() + timeout
        while travel(self.recorder.since(mark), "LSP") <= 0.05:
            if time.monotonic() > deadline:
                stuck = [n for n, ch in HEARTBEATS.items() if not live(ch)]
                raise AssertionError(f"the arms do not move within {timeout:g} s; nodes not publishing: {stuck}; "
                                     f"client put {'hangs' if self.driver.stuck else 'works'}; {pipeline_lsp()}")
            time.sleep(0.05)

    def healthy(self) -> bool:
        """Every node runs and publishes, the channels are sound, and the client's motion reaches the robot."""
        if self.driver is None or self.recorder is None:
            return False
        if not (all(self.pid(n) for n in ("daemon", *NODES)) and all(live(ch) for ch in HEARTBEATS.values())
                and not self.driver.stuck and all(r.ok for r in repair.scan())):
            return False
        try:
            self.moving(5)
        except AssertionError:
            return False
        return True

    def heal(self) -> None:
        """After a test that left the system broken (a hung node, a wedged channel), start it again from scratch
        where the robot stands, so the next test does not inherit the damage."""
        if self.healthy():
            return
        pose = self.pose()
        self.stop()
        self.start(pose)

    def pose(self) -> dict[str, float]:
        """Where the simulated joints are now (the robot stays there while its driver is down)."""
        if self.recorder is None:
            return {}
        last = self.recorder.last()
        return {n: TABLE[n].clamp(float(last.pos[mds.BY_SHORT[n].address])) for n in mds.joints.MODEL_JOINTS
                if math.isfinite(last.pos[mds.BY_SHORT[n].address]) and TABLE[n].enabled}

    def stop(self) -> None:
        for obj in (self.driver, self.recorder):
            if obj is not None:
                obj.close()
        self.driver = self.recorder = None
        self.cli("stop")
        self.cli("killall")


@pytest.fixture(scope="module")
def system(tmp_path_factory: pytest.TempPathFactory) -> Iterator[System]:
    assert in_netns(), "run through tools/netns-run (private /dev/shm and network namespace)"
    rt = tmp_path_factory.mktemp("runtime")
    mp = pytest.MonkeyPatch()
    mp.setenv("MDS_ACH_RUNTIME_DIR", str(rt))
    mp.setenv("MDS_ACH_CONFIG_DIR", str(rt / "config"))
    mp.delenv("MDS_ACH_ROBOT", raising=False)
    remove_mds_channels()
    s = System(rt)
    try:
        s.start()
        yield s
        # Everything any daemon sent during the whole module, from its CAN logs: never outside a joint's limits.
        s.stop()
        import can

        sent = []
        for path in s.can_logs:
            for msg in can.LogReader(str(path)):
                if not msg.is_error_frame and msg.arbitration_id != mcb.HOST_SID and len(msg.data) == mcb.DLC:
                    sent.append((msg.timestamp, mcb.decode(msg.arbitration_id, bytes(msg.data))))
        # (a SIGKILLed daemon loses the tail of its log; the last one is stopped cleanly)
        assert any(f.argument == StateArg.MOVETO_TARGET for _, f in sent), "no motion was logged"
        assert unsafe_commands(sent) == []
        for path in s.can_logs:  # every daemon run on its own: each restarts from the joints' first replies
            bounded = audit(read_log(str(path)), TABLE, TABLE.motion_bounds(mds.MDS_LOOP_PERIOD),
                            3.5 * mds.MDS_LOOP_PERIOD)
            assert bounded.violations == [], f"{path.name}: {bounded.violations}"
    finally:
        s.stop()
        mp.undo()
        remove_mds_channels()


@pytest.mark.ros
@pytest.mark.slow
def test_sigkill_daemon_while_the_arms_move(system: System) -> None:
    """The pipeline survives its daemon; a restarted daemon starts where the robot stands and resumes the motion
    without a jump (the simulated robot lives in the daemon's process: it is restarted where it stood)."""
    s = system
    s.moving()
    s.kill("daemon")
    pose = s.pose()
    mark = s.recorder.mark()
    # The operator's client goes on commanding while the daemon is down: the pipeline's reference moves 0.6 rad
    # away from where the robot stands (the robot cannot follow without its daemon).
    s.driver.frozen, s.driver.offset = s.driver.phase, -0.6
    time.sleep(1.5)
    try:
        assert s.recorder.since(mark) == [], "frames on mds-state without a daemon"
        assert all(s.pid(n) is not None for n in NODES), "a node died with the daemon"
        s.start_daemon(pose)
        time.sleep(1.0)
        s.driver.frozen, s.driver.offset = None, 0.0
        s.moving()
        after = s.recorder.since(mark)
        for n, q in pose.items():
            assert after[0].ref[TABLE[n].address] == pytest.approx(q, abs=1e-3), f"{n} does not start where it stands"
        assert_no_jump(after, "daemon killed and restarted")
    finally:
        s.heal()


@pytest.mark.ros
@pytest.mark.slow
def test_client_killed_inside_a_put_on_a_mux_input(system: System) -> None:
    """A legacy client dies inside its put on mds-ref-filter: the mux reports the corrupt input and the robot stays
    safe; `mds-ach repair` fixes the channel in place and the client's frames move the robot again, through the same
    mux (no node restarted)."""
    s = system
    s.moving()
    mark = s.recorder.mark()
    StuckWriter(mds.MDS_CHAN_REF_FILTER_NAME, before=0, marker=PUT_STAGES["copying the data"][0]).kill()
    corrupt = s.recorder.mark()
    try:
        wait_for(lambda: s.driver.errors > 0, 5, what="the client to see ACH_CORRUPT")
        time.sleep(1.5)
        assert len(s.recorder.since(corrupt)) >= 10 and all(s.pid(n) for n in ("daemon", *NODES))
        check = s.cli("repair", "--check")
        assert check.returncode == 1
        assert [ln.split()[0] for ln in check.stderr.splitlines()] == [mds.MDS_CHAN_REF_FILTER_NAME], check.stderr
        assert "corrupt" in s.log("mux").lower(), "the mux did not report its corrupt input"
        fixed = s.cli("repair")
        assert fixed.returncode == 0 and "repaired in place" in fixed.stdout, fixed.stdout + fixed.stderr
        errors = s.driver.errors
        s.moving(timeout=10)  # the client's frames reach the robot again, through the same mux
        assert s.driver.errors == errors
        assert_no_jump(s.recorder.since(mark), "corrupt mux input repaired")
    finally:
        s.heal()


@pytest.mark.ros
@pytest.mark.slow
def test_writer_killed_inside_a_put_on_the_daemon_input(system: System) -> None:
    """mds-ref (collision gate -> daemon) left corrupt: the daemon keeps publishing mds-state and holds the last
    reference; `mds-ach repair`, plus `mds-ach start --only` for any node that stopped, resume the motion."""
    s = system
    s.moving()
    mark = s.recorder.mark()
    StuckWriter(mds.MDS_CHAN_REF_NAME, before=0, marker=PUT_STAGES["copying the data"][0]).kill()
    corrupt = s.recorder.mark()
    try:
        time.sleep(2.0)
        frames = s.recorder.since(corrupt)
        assert len(frames) >= 10, f"the daemon stopped publishing mds-state ({len(frames)} frames in 2 s)"
        held = [f for f in frames if f.received > frames[0].received + 0.3]
        assert held and all(np.array_equal(f.ref[MODEL], held[0].ref[MODEL]) for f in held), \
            "the reference moved while mds-ref was corrupt"
        check = s.cli("repair", "--check")
        assert check.returncode == 1 and mds.MDS_CHAN_REF_NAME in check.stderr
        assert s.cli("repair").returncode == 0
        stopped = [n for n in NODES if s.pid(n) is None]
        if stopped:
            s.start_nodes(*stopped)
        s.moving()
        assert_no_jump(s.recorder.since(mark), "corrupt daemon input repaired")
    finally:
        s.heal()


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.parametrize("node", NODES)
def test_sigkill_node_while_the_arms_move(system: System, node: str) -> None:
    s = system
    s.moving()
    mark = s.recorder.mark()
    s.kill(node)
    time.sleep(2.0)
    dead = s.recorder.since(mark)
    try:
        assert len(dead) >= 10, f"the state stream stopped when {node} died ({len(dead)} frames in 2 s)"
        assert s.pid("daemon") is not None
        if node in ("filter", "collision"):  # the daemon holds the last reference that passed the gate
            held = [f for f in dead if f.received > dead[0].received + 0.3]
            assert all(np.array_equal(f.ref[MODEL], held[0].ref[MODEL]) for f in held), f"{node} dead, ref moved"
        elif node in ("ik", "bridge"):  # not on the driver's path: the motion goes on
            assert travel(dead, "LSP") > 0.05
        s.start_nodes(node)
        s.moving()
        if node == "ik":  # it answers requests again
            assert_ik_answers(s)
        if node == "bridge":
            bounded(lambda: assert_bridge_commands_reach_the_robot(s), 60, "a ROS command through the bridge")
        assert_no_jump(s.recorder.since(mark), f"{node} killed and restarted")
    finally:
        s.heal()


def assert_ik_answers(s: System) -> None:
    from mds_ach.nodes.ik_client import IkClient
    from mds_ach.tools.console import fk_pose

    last = s.recorder.last()
    q = [last.ref[mds.BY_SHORT[n].address] for n in mds.joints.LEFT_ARM]
    pos, _ = fk_pose(q, "left")

    def ask() -> object:
        with IkClient() as client:
            return client.request("left", 3, [pos[0], pos[1], pos[2] + 0.02], timeout=30)

    reply = bounded(ask, 40, "an IK request")
    assert reply.success, reply.message


def assert_bridge_commands_reach_the_robot(s: System) -> None:
    """A ROS JointState command on mds/joint_command moves the neck (no one else commands it)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState

    nky = TABLE["NKY"]
    goal = nky.clamp(0.25 if s.recorder.last().ref[nky.address] < 0.1 else -0.05)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("fault_test_client", context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        states: list[JointState] = []
        node.create_subscription(JointState, "joint_states", states.append, qos_profile_sensor_data)
        pub = node.create_publisher(JointState, "mds/joint_command", 10)
        deadline = time.monotonic() + 30
        while not (states and pub.get_subscription_count() > 0):
            assert time.monotonic() < deadline, "the restarted bridge does not publish joint_states / subscribe"
            executor.spin_once(timeout_sec=0.1)
        pub.publish(JointState(name=["NKY"], position=[goal]))
        deadline = time.monotonic() + 15
        while abs(s.recorder.last().ref[nky.address] - goal) > 1e-6:
            assert time.monotonic() < deadline, "the bridge's command did not reach the daemon"
            executor.spin_once(timeout_sec=0.1)
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


# ============================================================================================ 4. a lock held too long

LOCK_HOLDER = """
import sys
from mds_ach import ach
ch = ach.Channel(sys.argv[1], create=False)
assert ch._lock() == 0
print("locked", flush=True)
sys.stdin.readline()
ch._mutex_unlock(ch._mutex)
print("released", flush=True)
sys.stdin.readline()
"""


def test_daemon_keeps_cycling_while_a_client_holds_the_state_lock(clean_shm: None) -> None:
    """A client stopped while it holds the ``mds-state`` lock (a reader SIGSTOPped inside its get, a debugger)
    must not freeze the daemon: each put waits at most a tenth of the period for the lock, is skipped and counted
    (``lock_timeouts``, logged at most every 5 s); the loop goes on querying the bus, taking references and
    answering commands, and ``mds-state`` flows again as soon as the lock is free."""
    daemon = subprocess.Popen([str(VENV_BIN / "daemon"), "--nocan", "--no-ros", "--sim-ideal", "--rate", "50"],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    status_in = StructChannel(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS)
    state_in = StructChannel(mds.MDS_CHAN_STATE_NAME, MDS_STATE)
    cmd_out = StructChannel(mds.MDS_CHAN_BOARD_CMD_NAME, MDS_CMD)
    holder = None
    newest: list[ds.MDS_DAEMON_STATUS] = []

    def status() -> ds.MDS_DAEMON_STATUS:
        frame = status_in.latest()
        if frame is not None:
            newest[:] = [frame]
        assert newest, "no mds-daemon-status"
        return newest[0]

    try:
        wait_for(lambda: state_in.latest(), 30, what="mds-state from the daemon")
        wait_for(lambda: status_in.latest(), 10, what="mds-daemon-status")
        holder = subprocess.Popen([sys.executable, "-c", LOCK_HOLDER, mds.MDS_CHAN_STATE_NAME],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert holder.stdout.readline().strip() == "locked"
        held_since = time.monotonic()
        before = wait_for(status, 10)
        cmd_out.put(MDS_CMD(seq=77, cmd=mds.MDS_CMD_ENABLE, address=0))
        during = wait_for(lambda: (st := status()).cmd_seq == 77 and st.cycle >= before.cycle + 25
                          and st.lock_timeouts >= before.lock_timeouts + 10 and st, 20,
                          what="the daemon cycling, answering mds-cmd and counting lock timeouts while locked")
        assert during.cmd_result == ds.CMD_OK
        assert during.tx_frames > before.tx_frames and during.rx_frames > before.rx_frames  # queries, replies
        assert during.channel_errors == before.channel_errors  # a busy lock is not a broken channel
        while time.monotonic() - held_since < 3.0:  # the whole 3 s: the loop never stops
            cycle = status().cycle
            wait_for(lambda c=cycle: status().cycle > c + 5, 5, what="cycles while the lock is held")
        assert holder.poll() is None  # still holding the lock all this time
        holder.stdin.write("\n")
        holder.stdin.flush()
        assert holder.stdout.readline().strip() == "released"
        released = time.monotonic()
        fresh = wait_for(lambda: (st := state_in.latest()) is not None and st.time > released and st, 10,
                         what="mds-state after the lock was released")
        assert fresh.time > released
        skipped = status().lock_timeouts
        time.sleep(0.3)
        assert status().lock_timeouts == skipped  # nothing skipped once the lock is free
    finally:
        if holder is not None:
            holder.kill()
            holder.wait(10)
        daemon.send_signal(signal.SIGTERM)
        out, _ = daemon.communicate(timeout=30)
        for ch in (status_in, state_in, cmd_out):
            ch.close()
    warnings = [line for line in out.splitlines() if "lock held by another process" in line]
    assert 1 <= len(warnings) <= 2 and mds.MDS_CHAN_STATE_NAME in warnings[0], out[-3000:]
    assert daemon.returncode == 0, out[-3000:]
