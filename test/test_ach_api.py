"""mds_ach.ach in one process: the classic-binding API, reader semantics, cancel/close, and bad input.

Channel names start with ``test-`` so the ``clean_shm`` fixture removes them.
"""

from __future__ import annotations

import array
import ctypes
import os
import signal
import struct
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from support import NOBODY, run_as, wait_for

from mds_ach import ach
from mds_ach.ach import channel as ach_channel  # the wait tunables are globals of the module that waits
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import MDS_IK, MDS_JOINT_PARAM, MDS_REF, MDS_STATE

pytestmark = pytest.mark.usefixtures("ach_impl")  # every test: C fast path and pure Python

NAME = "test-api"


SYS_FUTEX = {"x86_64": 202, "aarch64": 98}[ach.native_layout().arch]
FUTEX_PRIVATE_FLAG = 128


def blocked_in_wait(thread: threading.Thread) -> bool:
    """The thread sleeps in a process-shared futex wait: where get(wait=True) blocks, in either wait mode (the
    GIL and other process-private waits set FUTEX_PRIVATE_FLAG)."""
    fields = Path(f"/proc/{os.getpid()}/task/{thread.native_id}/syscall").read_text().split()
    return fields[0] == str(SYS_FUTEX) and int(fields[2], 16) & FUTEX_PRIVATE_FLAG == 0


@pytest.fixture
def chan(clean_shm: None) -> Iterator[ach.Channel]:
    ach.create(NAME, 4, 64)
    ch = ach.Channel(NAME, create=False)
    yield ch
    ch.close()


@pytest.fixture
def pair(clean_shm: None) -> Iterator[tuple[ach.Channel, ach.Channel]]:
    """A writer and a reader handle on the same 4 x 64 channel."""
    ach.create(NAME, 4, 64)
    with ach.Channel(NAME) as w, ach.Channel(NAME) as r:
        yield w, r


# --- constants and names ---------------------------------------------------------------------------


def test_status_codes_and_names() -> None:
    expected = ["ACH_OK", "ACH_OVERFLOW", "ACH_INVALID_NAME", "ACH_BAD_SHM_FILE", "ACH_FAILED_SYSCALL", "ACH_EAGAIN",
                "ACH_MISSED_FRAME", "ACH_TIMEOUT", "ACH_EEXIST", "ACH_ENOENT", "ACH_CLOSED", "ACH_BUG", "ACH_EINVAL",
                "ACH_CORRUPT", "ACH_BAD_HEADER", "ACH_EACCES", "ACH_CANCELED", "ACH_EFAULT", "ACH_EINTR",
                "ACH_ENOTSUP"]
    for value, name in enumerate(expected):
        assert ach.result_string(value) == name
        if name != "ACH_EAGAIN":
            assert getattr(ach, name) == value
    assert ach.ACH_STALE_FRAMES == ach.ACH_EAGAIN == ach.ACH_LOCKED == 5
    assert ach.result_string(ach.ACH_STALE_FRAMES) == "ACH_EAGAIN"
    assert (ach.ACH_O_WAIT, ach.ACH_O_LAST, ach.ACH_O_COPY, ach.ACH_O_RELTIME) == (1, 2, 4, 8)
    assert ach.ACH_O_NONBLOCK == ach.ACH_O_FIRST == ach.ACH_O_ABSTIME == 0
    assert "UNKNOWN" in ach.result_string(99)


def test_exception_text() -> None:
    exc = ach.AchException(ach.ACH_OVERFLOW, "frame is 10 bytes", channel="mds-x", frame_size=10)
    assert exc.status == ach.ACH_OVERFLOW
    assert exc.frame_size == 10
    text = str(exc)
    assert "ACH_OVERFLOW" in text and "does not fit" in text and "mds-x" in text and "10 bytes" in text
    assert str(ach.AchException(ach.ACH_ENOENT)) == "ACH_ENOENT: channel does not exist"


@pytest.mark.parametrize("name", ["a", "x" * 63, "mds-state", "A.b_c-9", "a.", "-a"])
def test_valid_names(name: str) -> None:
    assert ach.validate_name(name) == name


@pytest.mark.parametrize("name", ["", "x" * 64, ".hidden", "a/b", "a b", "na\u00efve", "a\0b", "semi;colon", 7, None])
def test_invalid_names(clean_shm: None, name: object) -> None:
    opened = ach.Channel if name is not None else ach.Channel().open  # Channel(): the classic unopened handle
    calls = (ach.validate_name, opened, lambda n: ach.create(n, 1, 1), ach.unlink, ach.exists)
    for call in calls:
        with pytest.raises(ach.AchException) as info:
            call(name)
        assert info.value.status == ach.ACH_INVALID_NAME
        assert "name" in str(info.value)


# --- create / open -----------------------------------------------------------------------------------


def test_channel_creates_with_defaults(clean_shm: None) -> None:
    assert not ach.exists(NAME)
    with ach.Channel(NAME) as ch:
        assert (ch.frame_count, ch.frame_size, ch.data_size) == (16, 512, 8192)
    assert ach.exists(NAME)
    assert os.stat(ach.shm_path(NAME)).st_size == ach.native_layout().file_size(16, 8192)


def test_channel_without_create(clean_shm: None) -> None:
    with pytest.raises(ach.AchException) as info:
        ach.Channel(NAME, create=False)
    assert info.value.status == ach.ACH_ENOENT
    assert NAME in str(info.value)
    assert not ach.exists(NAME)


def test_create_exists_and_truncate(clean_shm: None) -> None:
    ach.create(NAME, 4, 64)
    with pytest.raises(ach.AchException) as info:
        ach.create(NAME, 4, 64)
    assert info.value.status == ach.ACH_EEXIST
    with ach.Channel(NAME) as old:
        old.put(b"old frame")
        ach.create(NAME, 2, 32, truncate=True)
        with ach.Channel(NAME) as new:
            assert (new.frame_count, new.data_size, new.last_seq) == (2, 64, 0)
        assert old.last_seq == 1  # the old handle keeps its (now orphaned) memory
    assert not [f for f in os.listdir(ach.SHM_DIR) if f.endswith(".tmp")]


def test_create_mode_ignores_umask(clean_shm: None) -> None:
    old = os.umask(0o077)
    try:
        ach.create(NAME, 1, 8, mode=0o640)
    finally:
        os.umask(old)
    assert os.stat(ach.shm_path(NAME)).st_mode & 0o777 == 0o640
    with ach.Channel(NAME) as ch:
        ch.chmod(0o600)
    assert os.stat(ach.shm_path(NAME)).st_mode & 0o777 == 0o600


@pytest.mark.parametrize(("count", "size"), [(-1, 8), (4, -3), (2.5, 8), (True, 8)])
def test_create_rejects_bad_sizes(clean_shm: None, count: object, size: object) -> None:
    with pytest.raises(ach.AchException) as info:
        ach.create(NAME, count, size)  # type: ignore[arg-type]
    assert info.value.status == ach.ACH_EINVAL
    assert not ach.exists(NAME)


def test_unlink(clean_shm: None) -> None:
    with ach.Channel(NAME) as ch:
        ch.put(b"x")
        ch.unlink()
        assert not ach.exists(NAME)
        ch.put(b"still usable")  # classic binding: the handle keeps working on the orphan
        assert ch.last_seq == 2
    with pytest.raises(ach.AchException) as info:
        ach.unlink(NAME)
    assert info.value.status == ach.ACH_ENOENT


# --- put / get ------------------------------------------------------------------------------------


def test_put_get_buffer_types(pair: tuple[ach.Channel, ach.Channel]) -> None:
    w, r = pair
    w.put(b"bytes")
    w.put(bytearray(b"bytearray"))
    w.put(memoryview(b"..memoryview..")[2:-2])
    w.put(array.array("d", [1.5, -2.0]))
    buf = bytearray(64)
    assert r.get(buf) == (ach.ACH_OK, 5)
    assert buf[:5] == b"bytes"
    view = memoryview(buf)[10:30]
    assert r.get(view) == (ach.ACH_OK, 9)
    assert buf[10:19] == b"bytearray"
    arr = (ctypes.c_char * 16)()
    assert r.get(arr) == (ach.ACH_OK, 10)
    assert arr.value == b"memoryview"
    doubles = array.array("d", [0.0, 0.0, 0.0])
    assert r.get(doubles) == (ach.ACH_OK, 16)
    assert list(doubles) == [1.5, -2.0, 0.0]


def test_put_get_ctypes_struct_in_place(clean_shm: None) -> None:
    with ach.Channel(NAME, 10, 3000) as w, ach.Channel(NAME) as r:
        ik = MDS_IK()
        ik.move = 1
        ik.arm[1].t_x = 0.25
        ik.arm[1].ik_method = 3
        w.put(ik)
        got = MDS_IK()
        assert r.get(got, wait=True, last=True) == (ach.ACH_OK, ctypes.sizeof(MDS_IK))
        assert (got.move, got.arm[1].t_x, got.arm[1].ik_method) == (1, 0.25, 3)
        state = MDS_STATE()
        state.joint[0x5F].pos = -0.5
        state.refWait = 1
        w.put(state)
        out = MDS_STATE()
        assert r.get(out) == (ach.ACH_OK, 14051)
        assert bytes(out) == bytes(state)


def test_get_refuses_read_only_buffer(pair: tuple[ach.Channel, ach.Channel]) -> None:
    w, r = pair
    with pytest.raises(TypeError, match="bytes-like"):
        w.put("text is not a frame")  # type: ignore[arg-type]
    w.put(b"x")
    with pytest.raises(TypeError, match="writable"):
        r.get(b"immutable")
    assert r.seq_num == 0


def test_put_empty_and_too_large(pair: tuple[ach.Channel, ach.Channel]) -> None:
    w, r = pair
    with pytest.raises(ach.AchException) as info:
        w.put(b"")
    assert info.value.status == ach.ACH_EINVAL
    with pytest.raises(ach.AchException) as info:
        w.put(bytes(257))
    assert info.value.status == ach.ACH_OVERFLOW
    assert "257" in str(info.value)
    assert w.put_status(bytes(257)) == ach.ACH_OVERFLOW
    assert w.last_seq == 0  # nothing changed
    w.put(bytes(range(256)))  # exactly data_size: evicts everything, accepted
    buf = bytearray(256)
    assert r.get(buf) == (ach.ACH_OK, 256)
    assert bytes(buf) == bytes(range(256))


def test_overflow_reports_needed_size_and_keeps_frame(pair: tuple[ach.Channel, ach.Channel]) -> None:
    w, r = pair
    w.put(b"0123456789")
    with pytest.raises(ach.AchException) as info:
        r.get(bytearray(4))
    assert info.value.status == ach.ACH_OVERFLOW
    assert info.value.frame_size == 10
    assert r.get_status(bytearray(4)) == (ach.ACH_OVERFLOW, 10)
    buf = bytearray(info.value.frame_size)
    assert r.get(buf) == (ach.ACH_OK, 10)


def test_in_order_last_copy_and_missed(pair: tuple[ach.Channel, ach.Channel]) -> None:
    w, r = pair
    buf = bytearray(64)
    assert r.get(buf) == (ach.ACH_STALE_FRAMES, 0)
    for i in range(3):
        w.put(bytes([i]) * 4)
    assert r.get(buf) == (ach.ACH_OK, 4)
    assert buf[0] == 0
    assert r.get(buf, last=True) == (ach.ACH_MISSED_FRAME, 4)  # skipped frame 1
    assert buf[0] == 2
    assert r.get(buf) == (ach.ACH_STALE_FRAMES, 0)
    assert r.get(buf, copy=True) == (ach.ACH_OK, 4)
    assert buf[0] == 2
    for i in range(3, 10):  # 7 more into a 4-slot ring: the reader falls behind
        w.put(bytes([i]) * 4)
    assert r.get(buf) == (ach.ACH_MISSED_FRAME, 4)
    assert buf[0] == 6  # the oldest surviving frame
    assert [r.get(buf)[0] == ach.ACH_OK and buf[0] for _ in range(3)] == [7, 8, 9]


def test_flush(pair: tuple[ach.Channel, ach.Channel]) -> None:
    w, r = pair
    for i in range(3):
        w.put(bytes([i]))
    r.flush()
    assert r.seq_num == 3
    buf = bytearray(8)
    assert r.get(buf) == (ach.ACH_STALE_FRAMES, 0)
    w.put(b"\x07")
    assert r.get(buf) == (ach.ACH_OK, 1)
    assert buf[0] == 7


@pytest.mark.parametrize("condvar_wait", [False, True])
def test_wait_timeout_and_wakeup_by_thread(clean_shm: None, condvar_wait: bool) -> None:
    ach.create(NAME, 4, 64)
    w = ach.Channel(NAME)
    r = ach.Channel(NAME, condvar_wait=condvar_wait)
    buf = bytearray(64)
    assert r.get(buf, wait=True, timeout=0.05) == (ach.ACH_TIMEOUT, 0)
    assert r.get(buf, wait=True, timeout=0) == (ach.ACH_TIMEOUT, 0)
    started = threading.Event()

    def writer() -> None:
        started.wait()
        time.sleep(0.05)
        w.put(b"wake up")

    t = threading.Thread(target=writer)
    t.start()
    started.set()
    assert r.get(buf, wait=True, timeout=10) == (ach.ACH_OK, 7)
    t.join()
    assert buf[:7] == b"wake up"
    with pytest.raises(ValueError, match="NaN"):
        r.get(buf, wait=True, timeout=float("nan"))
    w.close()
    r.close()


def test_wait_returns_at_once_when_a_frame_is_unseen(pair: tuple[ach.Channel, ach.Channel]) -> None:
    w, r = pair
    w.put(b"a")
    w.put(b"b")
    buf = bytearray(8)
    assert r.get(buf, wait=True, last=True, timeout=0) == (ach.ACH_MISSED_FRAME, 1)
    assert buf[:1] == b"b"


def test_poll(pair: tuple[ach.Channel, ach.Channel]) -> None:
    w, r = pair
    buf = bytearray(64)
    assert r.poll(buf, timeout=0.01) == (ach.ACH_TIMEOUT, 0)
    w.put(b"first")
    w.put(b"second")
    assert r.poll(buf) == (ach.ACH_MISSED_FRAME, 6)
    assert buf[:6] == b"second"
    t = threading.Timer(0.02, lambda: w.put(b"third"))
    t.start()
    assert r.poll(buf, timeout=10) == (ach.ACH_OK, 5)
    t.join()


@pytest.mark.parametrize("condvar_wait", [False, True])
@pytest.mark.parametrize("async_unsafe", [False, True])
def test_cancel_wakes_waiter_and_is_sticky(clean_shm: None, async_unsafe: bool, condvar_wait: bool) -> None:
    ach.create(NAME, 4, 64)
    w = ach.Channel(NAME)
    r = ach.Channel(NAME, condvar_wait=condvar_wait)
    result: list[tuple[int, int]] = []
    t = threading.Thread(target=lambda: result.append(r.get(bytearray(64), wait=True)))
    t.start()
    wait_for(lambda: blocked_in_wait(t), timeout=20, what="reader thread blocked in get(wait=True)")
    r.cancel(async_unsafe=async_unsafe)
    t.join(timeout=5)
    assert not t.is_alive()
    assert result == [(ach.ACH_CANCELED, 0)]
    w.put(b"data")
    assert r.get(bytearray(64)) == (ach.ACH_CANCELED, 0)  # sticky
    with pytest.raises(ach.AchException) as info:
        r.flush()
    assert info.value.status == ach.ACH_CANCELED
    assert w.get(bytearray(64)) == (ach.ACH_OK, 4)  # other handles are unaffected
    w.close()
    r.close()


@pytest.mark.parametrize("condvar_wait", [False, True])
def test_close_wakes_waiter_and_refuses_calls(clean_shm: None, condvar_wait: bool) -> None:
    ach.create(NAME, 4, 64)
    w = ach.Channel(NAME)
    r = ach.Channel(NAME, condvar_wait=condvar_wait)
    result: list[tuple[int, int]] = []
    t = threading.Thread(target=lambda: result.append(r.get(bytearray(64), wait=True)))
    t.start()
    wait_for(lambda: blocked_in_wait(t), timeout=20, what="reader thread blocked in get(wait=True)")
    t0 = time.monotonic()
    r.close()
    t.join(timeout=5)
    assert result == [(ach.ACH_CANCELED, 0)]
    assert time.monotonic() - t0 < 5
    assert r.closed
    r.close()  # idempotent
    for call in (lambda: r.get(bytearray(8)), lambda: r.put(b"x"), r.flush):
        with pytest.raises(ach.AchException) as info:
            call()
        assert info.value.status == ach.ACH_CLOSED
    w.put(b"writer unaffected")
    w.close()


@pytest.mark.parametrize("condvar_wait", [False, True])
def test_interrupt_while_waiting_releases_lock(clean_shm: None, condvar_wait: bool) -> None:
    """A Python signal handler raising (Ctrl-C) surfaces after the wait returned, possibly holding the mutex: the
    exception must not leave the channel locked."""
    ach.create(NAME, 4, 64)
    w = ach.Channel(NAME)
    r = ach.Channel(NAME, condvar_wait=condvar_wait)

    class InterruptError(Exception):
        pass

    def handler(signum: int, frame: object) -> None:
        raise InterruptError

    old = signal.signal(signal.SIGALRM, handler)
    try:
        signal.setitimer(signal.ITIMER_REAL, 0.05)
        with pytest.raises(InterruptError):
            r.get(bytearray(8), wait=True, timeout=5)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    lock_word = struct.unpack_from("<i", Path(ach.shm_path(NAME)).read_bytes(), ach.native_layout().mutex)[0]
    assert lock_word & 0x3FFFFFFF == 0  # nobody owns the mutex
    w.put(b"ok")
    assert r.get(bytearray(8)) == (ach.ACH_OK, 2)
    w.close()
    r.close()


# --- corruption and bad files ---------------------------------------------------------------------


def write_shm(name: str, data: bytes) -> None:
    Path(ach.shm_path(name)).write_bytes(data)


def patch_shm(name: str, offset: int, data: bytes) -> None:
    with open(ach.shm_path(name), "r+b") as f:
        f.seek(offset)
        f.write(data)


@pytest.mark.parametrize(("content", "status"), [
    (b"", ach.ACH_BAD_SHM_FILE),
    (b"hello, I am not an Ach channel" * 40, ach.ACH_BAD_SHM_FILE),
    (struct.pack("<I", 0xB07511F3) + bytes(100), ach.ACH_BAD_SHM_FILE),  # right magic, far too short
])
def test_open_non_ach_files(clean_shm: None, content: bytes, status: int) -> None:
    write_shm(NAME, content)
    with pytest.raises(ach.AchException) as info:
        ach.Channel(NAME)
    assert info.value.status == status
    assert NAME in str(info.value)
    assert Path(ach.shm_path(NAME)).read_bytes() == content  # never "repaired" or re-created


def test_open_truncated_file(clean_shm: None) -> None:
    ach.create(NAME, 4, 64)
    full = Path(ach.shm_path(NAME)).read_bytes()
    for cut in (len(full) - 1, len(full) - 100, 400):
        write_shm(NAME, full[:cut])
        with pytest.raises(ach.AchException) as info:
            ach.Channel(NAME)
        assert info.value.status == ach.ACH_CORRUPT
        assert "truncated" in str(info.value)


def test_open_wrong_magic(clean_shm: None) -> None:
    ach.create(NAME, 4, 64)
    patch_shm(NAME, 0, b"\xde\xad\xbe\xef")
    with pytest.raises(ach.AchException) as info:
        ach.Channel(NAME)
    assert info.value.status == ach.ACH_BAD_SHM_FILE
    assert "magic" in str(info.value)


@pytest.mark.parametrize("guard", ["header", "index", "data"])
def test_bad_guards(clean_shm: None, guard: str) -> None:
    ach.create(NAME, 4, 64)
    h = ach.native_layout().header_size
    offset = {"header": h, "index": h + 8 + 24 * 4, "data": h + 16 + 24 * 4 + 256}[guard]
    patch_shm(NAME, offset, b"\0")
    with pytest.raises(ach.AchException) as info:
        ach.Channel(NAME)
    assert info.value.status == ach.ACH_CORRUPT
    assert f"{guard} guard" in str(info.value)


def test_guard_damaged_while_open(chan: ach.Channel) -> None:
    chan.put(b"before")
    h = ach.native_layout().header_size
    patch_shm(NAME, h + 8 + 24 * 4, b"\xff")  # index guard, through the file, while mapped
    with pytest.raises(ach.AchException) as info:
        chan.put(b"after")
    assert info.value.status == ach.ACH_CORRUPT
    with pytest.raises(ach.AchException) as info:
        chan.get(bytearray(64))
    assert info.value.status == ach.ACH_CORRUPT


def test_dirty_channel_is_corrupt(chan: ach.Channel) -> None:
    chan.put(b"frame")
    patch_shm(NAME, ach.native_layout().dirty, struct.pack("<i", 1))
    for call in (lambda: chan.put(b"x"), lambda: chan.get(bytearray(64)), chan.flush):
        with pytest.raises(ach.AchException) as info:
            call()
        assert info.value.status == ach.ACH_CORRUPT
    assert chan.put_status(b"x") == ach.ACH_CORRUPT


def test_snapshot(chan: ach.Channel) -> None:
    chan.put(b"abc")
    chan.put(b"defg")
    img = chan.snapshot()
    assert img.name == NAME
    assert img.frames() == [(1, b"abc"), (2, b"defg")]
    assert (img.data_head, img.index_head, img.last_seq) == (7, 2, 2)


# --- StructChannel --------------------------------------------------------------------------------


def test_struct_channel_latest_and_wait(clean_shm: None) -> None:
    with StructChannel("test-ref", MDS_REF) as w, StructChannel("test-ref", MDS_REF) as r:
        assert (w.channel.frame_count, w.channel.frame_size) == (10, 3000)
        assert r.latest() is None
        assert r.wait(timeout=0.01) is None
        for i in range(3):
            ref = MDS_REF()
            ref.joint[0x5F].ref = i / 10
            w.put(ref)
        got = r.latest()
        assert got is not None and got.joint[0x5F].ref == 0.2  # newest wins
        assert r.latest() is None  # nothing new since
        t = threading.Timer(0.02, lambda: w.put(MDS_REF()))
        t.start()
        got = r.wait(timeout=10)
        t.join()
        assert isinstance(got, MDS_REF) and got.joint[0x5F].ref == 0.0
        assert r.bad_frames == 0


def test_struct_channel_refuses_wrong_sizes(clean_shm: None) -> None:
    with StructChannel("test-ref", MDS_REF) as r, ach.Channel("test-ref") as raw:
        raw.put(bytes(999))  # one byte short
        assert r.latest() is None
        raw.put(bytes(1001))  # one byte too long (still fits the channel)
        assert r.wait(timeout=0.01) is None
        assert r.bad_frames == 2
        good = MDS_REF()
        good.joint[1].mode = 2
        raw.put(bytes(1001))
        raw.put(good)
        got = r.latest()
        assert got is not None and got.joint[1].mode == 2
        assert r.bad_frames == 2  # the skipped bad frame was never looked at
        with pytest.raises(TypeError, match="MDS_REF"):
            r.put(MDS_IK())  # type: ignore[arg-type]


def test_struct_channel_wait_skips_bad_frame(clean_shm: None) -> None:
    with StructChannel("test-ik", MDS_IK) as r, ach.Channel("test-ik") as raw:
        def feed() -> None:
            raw.put(b"garbage")
            deadline = time.monotonic() + 10
            while r.bad_frames == 0 and time.monotonic() < deadline:  # the reader has seen the garbage
                time.sleep(0.001)
            raw.put(MDS_IK(move=1))

        t = threading.Thread(target=feed)
        t.start()
        got = r.wait(timeout=10)
        t.join()
        assert got is not None and got.move == 1
        assert r.bad_frames == 1


def test_struct_larger_than_channel(clean_shm: None) -> None:
    ach.create("test-small", 16, 512)
    with pytest.raises(ValueError, match=r"test-small.*8192.*MDS_JOINT_PARAM.*29000"):
        StructChannel("test-small", MDS_JOINT_PARAM)


def test_struct_channel_cancel(clean_shm: None) -> None:
    r = StructChannel("test-state", MDS_STATE)
    result: list[object] = []
    t = threading.Thread(target=lambda: result.append(r.wait()))
    t.start()
    time.sleep(0.05)
    r.cancel()
    t.join(timeout=5)
    assert result == [None]
    r.close()


def _open_as_other_user(name: str) -> int:
    """Status of opening ``name`` from a forked child running as nobody, without supplementary groups (the test
    runs as root; a normal user's groups map to root's group in its user namespace)."""
    def open_it() -> int:
        try:
            ach.Channel(name, create=False).close()
        except ach.AchException as exc:
            return exc.status
        return ach.ACH_OK

    return run_as(NOBODY, NOBODY, open_it)


def test_permission_denied(clean_shm: None, request: pytest.FixtureRequest) -> None:
    if os.geteuid() == 0:
        request.getfixturevalue("other_user")  # root in a user namespace: nobody must exist there
        ach.create(NAME, 2, 8, mode=0o660)  # root:root rw-rw---- : nobody may not use it
        assert _open_as_other_user(NAME) == ach.ACH_EACCES
        with ach.Channel(NAME) as ch:
            ch.chmod(0o666)
        assert _open_as_other_user(NAME) == ach.ACH_OK
    else:
        ach.create(NAME, 2, 8, mode=0o000)
        with pytest.raises(ach.AchException) as info:
            ach.Channel(NAME)
        assert info.value.status == ach.ACH_EACCES
        assert "ermission" in str(info.value)


@pytest.mark.parametrize("condvar_wait", [False, True])
def test_put_wakes_waiter_without_polling(clean_shm: None, monkeypatch: pytest.MonkeyPatch,
                                          condvar_wait: bool) -> None:
    """With the re-check slices stretched to 60 s, only the writer's wake-up (futex wake / condvar broadcast)
    can end the wait before the 30 s timeout."""
    monkeypatch.setattr(ach_channel, "POLL_SLICE", 60.0)
    monkeypatch.setattr(ach_channel, "IDLE_SLICE", 60.0)
    monkeypatch.setattr(ach_channel, "WAIT_SLICE", 60.0)
    ach.create(NAME, 4, 64)
    with ach.Channel(NAME) as w, ach.Channel(NAME, condvar_wait=condvar_wait) as r:
        result: list[tuple[int, int]] = []
        t = threading.Thread(target=lambda: result.append(r.get(bytearray(64), wait=True, timeout=30)))
        t.start()
        wait_for(lambda: blocked_in_wait(t), timeout=20, what="reader thread blocked in get(wait=True)")
        w.put(b"wake")
        t.join(timeout=25)
        assert result == [(ach.ACH_OK, 4)]


# --- what a channel path may be (issue #25, item 9) -------------------------------------------------------


def test_a_symlink_at_the_channel_path_is_refused_not_followed(clean_shm: None) -> None:
    """Another user can plant /dev/shm/achshm-NAME -> a valid Ach file of theirs: the open never follows it (so
    nothing is read from or written into that file)."""
    ach.create("test-theirs", 4, 64)
    before = Path(ach.shm_path("test-theirs")).read_bytes()
    os.symlink(ach.shm_path("test-theirs"), ach.shm_path(NAME))
    with pytest.raises(ach.AchException) as exc:
        ach.Channel(NAME, create=True)  # not even "create if missing": the path is taken
    assert exc.value.status == ach.ACH_BAD_SHM_FILE and "is a symbolic link" in str(exc.value)
    assert f"mds-ach repair --recreate {NAME}" in str(exc.value)
    assert Path(ach.shm_path("test-theirs")).read_bytes() == before


@pytest.mark.parametrize("kind", ["fifo", "directory"])
def test_a_fifo_or_directory_at_the_channel_path_is_a_clear_error_without_blocking(clean_shm: None,
                                                                                   kind: str) -> None:
    path = ach.shm_path(NAME)
    if kind == "fifo":
        os.mkfifo(path)
    else:
        os.mkdir(path)
    try:
        t0 = time.monotonic()
        with pytest.raises(ach.AchException) as exc:
            ach.Channel(NAME, create=False)
        assert time.monotonic() - t0 < 5.0  # a FIFO never blocks the open
        assert exc.value.status == ach.ACH_BAD_SHM_FILE
        assert f"is a {'FIFO' if kind == 'fifo' else 'directory'}, not a channel file" in str(exc.value)
    finally:
        os.rmdir(path) if kind == "directory" else os.unlink(path)
