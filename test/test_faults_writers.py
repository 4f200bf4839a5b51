"""Fault injection: a writer killed inside a put.

A child process runs the real ``ach.Channel.put``, is stopped by a line tracer at a chosen point of the update
and SIGKILLed there (``support.faults.StuckWriter``), so the channel is left exactly as libach leaves it
(``dirty`` = 1, the mutex owner dead): every handle in every process gets ``ACH_CORRUPT``. ``mds-ach repair``
reports it, repairs it in place (frames that are complete survive, nothing half written is ever returned), open
handles work again, and the other channels are not touched. A reader killed while waiting wedges no writer.
"""


from __future__ import annotations

import ctypes
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from support.faults import PUT_STAGES, TEST_CHANNEL, StuckWriter, check_payload, payload, read_all
from support.system import mds_ach

import mds_ach as mds
from mds_ach import ach
from mds_ach.robot import access as channel_access
from mds_ach.robot.msgs import MDS_REF, MDS_STATE
from mds_ach.tools import repair

# ============================================================================================ 1. crashed writers

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

    check = mds_ach("repair", "--check")
    assert check.returncode == 1, check.stdout + check.stderr
    corrupt = [line.split()[0] for line in check.stderr.splitlines() if "corrupt" in line]
    assert corrupt == [mds.MDS_CHAN_REF_FILTER_NAME], check.stderr
    fixed = mds_ach("repair")
    assert fixed.returncode == 0, fixed.stdout + fixed.stderr
    assert "repaired in place" in fixed.stdout and mds.MDS_CHAN_REF_FILTER_NAME in fixed.stdout
    assert mds_ach("repair", "--check", "-q").returncode == 0
    after = {n: without_sync(n) for n in before}
    assert after == before  # the healthy channels were looked at under their lock, never written


def test_channel_held_by_a_live_stuck_process_is_reported_not_broken(clean_shm: None) -> None:
    ach.create(TEST_CHANNEL, 4, 256)
    writer = StuckWriter(TEST_CHANNEL, before=2, marker=PUT_STAGES["data copied"][0])
    try:
        report = repair.repair(TEST_CHANNEL, timeout=0.3)
        assert report.state == repair.LOCKED and f"pid {writer.proc.pid}" in report.detail, report.line()
        cli = mds_ach("repair", "--timeout", "0.3", TEST_CHANNEL)
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
        cli = mds_ach("repair", TEST_CHANNEL)
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
    assert mds_ach("repair", "--recreate").returncode == 2
    assert mds_ach("repair", "bad/name").returncode == 2
    missing = mds_ach("repair", "--check", TEST_CHANNEL)
    assert missing.returncode == 1 and "missing" in missing.stderr
    assert mds_ach("repair").returncode == 0  # no channels at all: nothing to do


