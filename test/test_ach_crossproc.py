"""mds_ach.ach across processes: frames flow, waits are woken by other processes, dead lock holders are handled
like libach handles them (dead reader: channel goes on; dead writer mid-put: CORRUPT everywhere)."""

from __future__ import annotations

import json
import os
import queue
import signal
import struct
import subprocess
import sys
import textwrap
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from support import wait_for

from mds_ach import ach
from mds_ach.ach import channel as ach_channel  # the wait tunables are globals of the module that waits

pytestmark = pytest.mark.usefixtures("ach_impl")  # every test: C fast path and pure Python

NAME = "test-xproc"
LAYOUT = ach.native_layout()
FUTEX_OWNER_DIED = 0x40000000
FUTEX_TID_MASK = 0x3FFFFFFF


class Child:
    """A Python child process running ``code``; its stdout lines are read by a thread so waits can time out."""

    def __init__(self, code: str, *args: str):
        prelude = "import json, os, sys, time\nfrom mds_ach import ach\n"
        self.proc = subprocess.Popen([sys.executable, "-c", prelude + textwrap.dedent(code), *args],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: queue.Queue[str] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))

    def expect(self, prefix: str, timeout: float = 30.0) -> str:
        """The next stdout line, which must start with ``prefix``."""
        try:
            line = self.lines.get(timeout=timeout)
        except queue.Empty:
            self.proc.kill()
            _, err = self.proc.communicate()
            msg = f"child printed nothing starting with {prefix!r} in {timeout} s; stderr:\n{err}"
            raise AssertionError(msg) from None
        assert line.startswith(prefix), f"expected {prefix!r}, child printed {line!r}"
        return line[len(prefix):].strip()

    def finish(self, timeout: float = 30.0) -> int:
        rc = self.proc.wait(timeout=timeout)
        self._reader.join(timeout=5)
        return rc

    def kill9(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=10)

    def stderr(self) -> str:
        assert self.proc.stderr is not None
        return self.proc.stderr.read()


@pytest.fixture
def children(clean_shm: None) -> Iterator[list[Child]]:
    started: list[Child] = []
    yield started
    for c in started:
        if c.proc.poll() is None:
            c.proc.kill()
            c.proc.wait()


def spawn(children: list[Child], code: str, *args: str) -> Child:
    child = Child(code, *args)
    children.append(child)
    return child


def file_i32(offset: int) -> int:
    return struct.unpack_from("<i", Path(ach.shm_path(NAME)).read_bytes(), offset)[0]


SYS_FUTEX = {"x86_64": 202, "aarch64": 98}[LAYOUT.arch]


def blocked_in_wait(pid: int, tid: int | None = None) -> bool:
    """The thread sleeps in a process-shared futex wait, where get(wait=True) blocks in either wait mode (the
    GIL and other process-private waits set FUTEX_PRIVATE_FLAG, 128)."""
    try:
        fields = Path(f"/proc/{pid}/task/{tid or pid}/syscall").read_text().split()
    except FileNotFoundError:
        return False
    return fields[0] == str(SYS_FUTEX) and int(fields[2], 16) & 128 == 0


READER = """
    ch = ach.Channel(sys.argv[1], create=False)
    buf = bytearray(64)
    got = []
    print("ready", flush=True)
    while not got or got[-1][1] != int(sys.argv[2]) - 1:
        status, size = ch.get(buf, wait=True, timeout=20)
        if status == ach.ACH_TIMEOUT:
            break
        got.append((status, int.from_bytes(buf[:8], "little")))
    print("got", json.dumps(got), flush=True)
"""

WRITER = """
    ch = ach.Channel(sys.argv[1], create=False)
    print("ready", flush=True)
    for i in range(int(sys.argv[2])):
        ch.put(i.to_bytes(8, "little"))
        if i % 10 == 9:
            time.sleep(0.001)
    print("done", flush=True)
"""


def check_stream(got: list[tuple[int, int]], count: int) -> None:
    """In order, ending with the last frame; a gap is always reported as MISSED_FRAME."""
    values = [v for _, v in got]
    assert values[-1] == count - 1
    assert values == sorted(set(values))
    previous = -1
    for status, value in got:
        assert status == (ach.ACH_OK if value == previous + 1 else ach.ACH_MISSED_FRAME), (status, value, previous)
        previous = value


def test_child_writer_parent_reader(children: list[Child]) -> None:
    ach.create(NAME, 10, 64)
    count = 300
    with ach.Channel(NAME) as r:
        w = spawn(children, WRITER, NAME, str(count))
        w.expect("ready")
        got = []
        buf = bytearray(64)
        while not got or got[-1][1] != count - 1:
            status, _ = r.get(buf, wait=True, timeout=20)
            assert status != ach.ACH_TIMEOUT, f"stalled after {got[-1:]}"
            got.append((status, int.from_bytes(buf[:8], "little")))
    w.expect("done")
    assert w.finish() == 0
    check_stream(got, count)


def test_parent_writer_child_reader(children: list[Child]) -> None:
    ach.create(NAME, 10, 64)
    count = 300
    r = spawn(children, READER, NAME, str(count))
    r.expect("ready")
    with ach.Channel(NAME) as w:
        for i in range(count):
            w.put(i.to_bytes(8, "little"))
    got = [tuple(x) for x in json.loads(r.expect("got"))]
    assert r.finish() == 0
    check_stream(got, count)  # type: ignore[arg-type]


def test_concurrent_writers_keep_channel_consistent(children: list[Child]) -> None:
    """Three processes hammer the same channel: every put is counted and the ring stays well-formed."""
    ach.create(NAME, 10, 64)
    writers = [spawn(children, WRITER, NAME, "200") for _ in range(3)]
    for w in writers:
        w.expect("ready")
        w.expect("done")
        assert w.finish() == 0
    with ach.Channel(NAME) as ch:
        img = ch.snapshot()
    assert img.last_seq == 600
    assert [seq for seq, _ in img.frames()] == list(range(591, 601))
    assert img.dirty == 0


@pytest.mark.parametrize("condvar_wait", [False, True])
def test_blocked_get_woken_by_other_process(children: list[Child], condvar_wait: bool) -> None:
    ach.create(NAME, 10, 64)
    code = """
        ach.channel.POLL_SLICE = ach.channel.WAIT_SLICE = 60.0  # only the writer's wake-up can end this wait in time
        ch = ach.Channel(sys.argv[1], create=False, condvar_wait=sys.argv[2] == "True")
        buf = bytearray(64)
        print("ready", flush=True)
        status, size = ch.get(buf, wait=True, timeout=30)
        print("got", status, size, bytes(buf[:size]).decode(), flush=True)
    """
    r = spawn(children, code, NAME, str(condvar_wait))
    r.expect("ready")
    wait_for(lambda: blocked_in_wait(r.proc.pid), timeout=20, what="child blocked in get(wait=True)")
    with ach.Channel(NAME) as w:
        w.put(b"wake up")
    assert r.expect("got") == f"{ach.ACH_OK} 7 wake up"
    assert r.finish() == 0


@pytest.mark.parametrize("condvar_wait", [False, True])
def test_blocked_get_woken_by_other_process_put_reverse(children: list[Child], condvar_wait: bool,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """This process blocks; another process's put wakes it."""
    monkeypatch.setattr(ach_channel, "POLL_SLICE", 60.0)
    monkeypatch.setattr(ach_channel, "IDLE_SLICE", 60.0)
    monkeypatch.setattr(ach_channel, "WAIT_SLICE", 60.0)
    ach.create(NAME, 10, 64)
    result: list[tuple[int, int]] = []
    buf = bytearray(64)
    with ach.Channel(NAME, condvar_wait=condvar_wait) as r:
        t = threading.Thread(target=lambda: result.append(r.get(buf, wait=True, timeout=30)))
        t.start()
        wait_for(lambda: blocked_in_wait(os.getpid(), t.native_id), timeout=20, what="our thread blocked in get")
        w = spawn(children, 'ach.Channel(sys.argv[1], create=False).put(b"from child")\nprint("done", flush=True)',
                  NAME)
        w.expect("done")
        t.join(timeout=30)
    assert result == [(ach.ACH_OK, 10)]
    assert buf[:10] == b"from child"
    assert w.finish() == 0


def test_reader_killed_holding_lock(children: list[Child]) -> None:
    """A reader SIGKILLed inside the lock: the next locker gets EOWNERDEAD, recovers it, the channel goes on."""
    ach.create(NAME, 10, 64)
    with ach.Channel(NAME) as ch:
        ch.put(b"before")
        code = """
            ch = ach.Channel(sys.argv[1], create=False)
            assert ch._lock() == ach.ACH_OK  # what a reader holds while it copies a frame
            print("locked", flush=True)
            time.sleep(120)
        """
        holder = spawn(children, code, NAME)
        holder.expect("locked")
        assert file_i32(LAYOUT.mutex) & FUTEX_TID_MASK == holder.proc.pid  # the child's main thread owns it
        holder.kill9()
        assert file_i32(LAYOUT.mutex) & FUTEX_OWNER_DIED  # the kernel marked the robust mutex
        ch.put(b"after")  # EOWNERDEAD -> pthread_mutex_consistent -> not dirty -> OK
        assert file_i32(LAYOUT.mutex) == 0
        buf = bytearray(64)
        assert ch.get(buf, last=True) == (ach.ACH_MISSED_FRAME, 5)
        assert buf[:5] == b"after"
    other = spawn(children, """
        buf = bytearray(64)
        print("got", *ach.Channel(sys.argv[1], create=False).get(buf, last=True), bytes(buf[:5]).decode(), flush=True)
    """, NAME)
    assert other.expect("got") == f"{ach.ACH_MISSED_FRAME} 5 after"


def test_writer_killed_mid_put(children: list[Child]) -> None:
    """A writer SIGKILLed mid-put leaves dirty=1: every later get/put/flush, in every process, is CORRUPT."""
    ach.create(NAME, 10, 64)
    code = """
        ch = ach.Channel(sys.argv[1], create=False, fast=False)  # a C put cannot be stopped half-way
        ch.put(b"good frame")

        def stuck(self, src, n):  # the real put path, stopped half-way through its update
            self._i32[self._i_dirty] = 1
            self._mv[self._d0 + 10:self._d0 + 13] = bytes(src[:3])
            print("mid-put", flush=True)
            time.sleep(120)

        ach.Channel._write_locked = stuck
        ch.put(b"never finished")
    """
    with ach.Channel(NAME) as ch:
        writer = spawn(children, code, NAME)
        writer.expect("mid-put")
        writer.kill9()
        assert file_i32(LAYOUT.dirty) == 1
        for call in (lambda: ch.put(b"x"), lambda: ch.get(bytearray(64)), ch.flush):
            with pytest.raises(ach.AchException) as info:
                call()
            assert info.value.status == ach.ACH_CORRUPT
            assert "corrupt" in str(info.value)
        assert ch.put_status(b"x") == ach.ACH_CORRUPT
        other = spawn(children, """
            ch = ach.Channel(sys.argv[1], create=False)
            print("status", ch.get_status(bytearray(64))[0], ch.put_status(b"y"), flush=True)
        """, NAME)
        assert other.expect("status") == f"{ach.ACH_CORRUPT} {ach.ACH_CORRUPT}"
        assert file_i32(LAYOUT.mutex) & FUTEX_TID_MASK == 0  # recovered and released, but still dirty
    ach.create(NAME, 10, 64, truncate=True)  # the cure, as with libach: re-create the channel
    with ach.Channel(NAME) as ch:
        ch.put(b"fresh")
        assert ch.get(bytearray(64)) == (ach.ACH_OK, 5)


def test_file_mode_shared_between_processes(children: list[Child]) -> None:
    """A channel made here with 0660 is usable from another process (every participant needs read-write)."""
    ach.create(NAME, 10, 64, mode=0o660)
    assert os.stat(ach.shm_path(NAME)).st_mode & 0o777 == 0o660
    child = spawn(children, 'ach.Channel(sys.argv[1], create=False).put(b"hi")\nprint("ok", flush=True)', NAME)
    child.expect("ok")
    with ach.Channel(NAME) as ch:
        assert ch.last_seq == 1


def put_returns(ch: ach.Channel, frame: bytes, timeout: float) -> bool:
    """Put from a daemon thread; False if it has not returned within ``timeout`` (a wedged writer)."""
    done = threading.Event()
    threading.Thread(target=lambda: (ch.put(frame), done.set()), daemon=True).start()
    return done.wait(timeout)


WAITER = """
    ch = ach.Channel(sys.argv[1], create=False)
    print("ready", flush=True)
    while True:
        status, size = ch.get(bytearray(64), wait=True, timeout=60)
        print("got", status, size, flush=True)
"""


def test_reader_killed_while_waiting_does_not_wedge(children: list[Child]) -> None:
    """A reader SIGKILLed while blocked in get(wait=True) leaves nothing behind: writers never hang and the next
    waiter is woken by the next put. (A reader dying inside glibc's process-shared condvar wait would make every
    later pthread_cond_broadcast wait for it forever; the default futex wait is not exposed to that.)"""
    ach.create(NAME, 10, 64)
    with ach.Channel(NAME) as w:
        for trial in range(5):
            victim = spawn(children, WAITER, NAME)
            victim.expect("ready")
            wait_for(lambda p=victim.proc.pid: blocked_in_wait(p), timeout=20, what="victim blocked in get")
            victim.kill9()
            survivor = spawn(children, WAITER, NAME)
            survivor.expect("ready")
            wait_for(lambda p=survivor.proc.pid: blocked_in_wait(p), timeout=20, what="next waiter blocked")
            assert put_returns(w, b"after %d" % trial, timeout=10), f"trial {trial}: put() hangs after the kill"
            assert survivor.expect("got") == f"{ach.ACH_OK} 7"
            survivor.kill9()
