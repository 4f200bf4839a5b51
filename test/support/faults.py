"""Writers that die inside a put, and the frames they write: shared by the crashed-writer tests and the running
system's fault tests.

A ``StuckWriter`` child process runs the real (pure-Python) ``ach.Channel.put``, is stopped by a line tracer at
a chosen point of the update (``PUT_STAGES``), and ``kill()`` SIGKILLs it there, so the channel is left exactly
as libach leaves it. ``payload``/``check_payload`` make every complete frame recognisable and every torn one
detectable.
"""

from __future__ import annotations

import os
import select
import signal
import struct
import subprocess
import sys
import zlib
from pathlib import Path

from mds_ach import ach

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


STUCK_WRITER = """
import inspect, sys, time
from mds_ach import ach
from support.faults import payload

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
        test_dir = str(Path(__file__).resolve().parent.parent)  # so the child imports support.faults
        env = dict(os.environ, PYTHONPATH=f"{test_dir}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
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


LOCK_HOLDER = r"""
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


class LockHolder:
    """A process that holds a channel's mutex until ``release()`` (like a client stopped inside a put)."""

    def __init__(self, name: str) -> None:
        self.proc = subprocess.Popen([sys.executable, "-c", LOCK_HOLDER, name], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None and self.proc.stdout.readline().strip() == "locked"

    def holding(self) -> bool:
        return self.proc.poll() is None

    def release(self) -> None:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write("\n")
        self.proc.stdin.flush()
        assert self.proc.stdout.readline().strip() == "released"

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait(10)
        for stream in (self.proc.stdin, self.proc.stdout):
            if stream is not None:
                stream.close()
