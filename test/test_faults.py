"""Fault injection on the simulated robot: crashed writers, CAN faults, killed nodes.

1. **A writer killed inside a put.** A child process runs the real ``ach.Channel.put``, is stopped by a line
   tracer at a chosen point of the update and SIGKILLed there, so the channel is left exactly as libach leaves
   it (``dirty`` = 1, the mutex owner dead): every handle in every process gets ``ACH_CORRUPT``. ``mds-ach
   repair`` reports it, repairs it in place (frames that are complete survive, nothing half written is ever
   returned), open handles work again, and the other channels are not touched.
2. **CAN faults** on the daemon loop (simulated clock and bus) while the arms move: a silent node, error frames,
   bus-off, garbled frames. Each is flagged in ``mds-daemon-status``, recovers, and every MOVETO that reaches the
   bus is inside the joint's limits.
3. **The running system** (daemon --nocan, mux, filter, collision gate, IK, bridge; each its own process):
   SIGKILL each node while the arms move. The daemon holds the last safe reference, the state stream goes on,
   and restarting the node resumes the motion without a jump. A writer killed inside a put on a pipeline
   channel is reported and repaired with ``mds-ach repair`` while everything keeps running.
"""

from __future__ import annotations

import ctypes
import os
import signal
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import pytest
from conftest import VENV_BIN

import mds_ach as mds
from mds_ach import ach, config, repair
from mds_ach.msgs import MDS_REF, MDS_STATE

TABLE = config.load("default")
CAN_ERR_CRTL_ACTIVE = 0x40  # <linux/can/error.h>: data[1] "recovered to error active state"


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
ch = ach.Channel(name, create=False)
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
    "dirty set": ("cnt = self._cnt", [3, 4, 5, 6]),
    "evicting the oldest frame": ("data_free += q[e]", [3, 4, 5, 6]),
    "copying the data": ("self._mv[start:start + n] = src", [4, 5, 6]),
    "data copied": ("seq = q[self._q_last] + 1", [4, 5, 6]),
    "last_seq bumped": ("q[e] = n", [4, 5, 6]),
    "index entry half written": ("q[e + 2] = seq", [4, 5, 6]),
    "entry written, heads not moved": ("q[_Q_DATA_HEAD] = (data_head + n) % dsize", [4, 5, 6, 7]),
    "data head moved, index head not": ("q[_Q_INDEX_HEAD] = (index_head + 1) % cnt", [4, 5, 6]),
}


class StuckWriter:
    """A child process that puts ``before`` frames, then stops inside the next put at ``marker`` (holding the
    lock). ``kill()`` SIGKILLs it there: a writer that died mid-put."""

    def __init__(self, name: str, before: int, marker: str) -> None:
        env = dict(os.environ, PYTHONPATH=f"{Path(__file__).parent}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
        self.proc = subprocess.Popen([sys.executable, "-c", STUCK_WRITER, name, str(before), marker], env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline().strip()
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
    for name in names:
        ach.create(name, mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE)
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
