"""Channel memory safety: whatever another process does to a channel file -- scribble over its header or index,
truncate it, leave /dev/shm full, hold its lock -- a client never crashes, never reads or writes outside the
channel, keeps running, and is told what happened and what to do.

Each hazard runs in a child process (C fast path and pure Python, via ``ach_impl``), so a crash shows up as the
child's exit status instead of taking pytest down.
"""

from __future__ import annotations

import json
import mmap
import os
import shutil
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from support import REPO, in_netns
from support.faults import LockHolder

from mds_ach import ach
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import MDS_REF
from mds_ach.tools import repair

NAME = "test-safety"
LAYOUT = ach.native_layout()
H = LAYOUT.header_size
CNT, FRAME = 4, 64
DSIZE = CNT * FRAME
U64_MAX = 2**64 - 1

# The header words and index-entry words a scribbler overwrites, with values that point outside the ring.
# Slot 0 holds the oldest frame once the index is full: the next put evicts it and a fresh reader reads it.
SCRIBBLES: dict[str, tuple[int, list[int]]] = {
    "magic": (0, [0]),
    "len": (8, [0, LAYOUT.file_size(CNT, DSIZE) + 8, U64_MAX]),
    "index_cnt": (88, [CNT + 1, 1 << 40, U64_MAX]),
    "data_size": (96, [DSIZE * 2, 1 << 40, U64_MAX]),
    "data_head": (104, [DSIZE, 1 << 40, U64_MAX]),
    "data_free": (112, [DSIZE + 1, U64_MAX]),
    "index_head": (120, [CNT, 1 << 40, U64_MAX]),
    "index_free": (128, [CNT + 1, U64_MAX]),
    "index[0].size": (H + 8, [DSIZE + 1, 1 << 40, U64_MAX]),
    "index[0].offset": (H + 16, [DSIZE, 1 << 40, U64_MAX - 8]),
    "index[0].seq": (H + 24, [0, 1 << 40, U64_MAX]),
}

SCRIBBLE_CHILD = r"""
import json, mmap, os, struct, sys
from mds_ach import ach

name, cnt, frame = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
for field, (offset, values) in json.loads(sys.argv[4]).items():
    for value in values:
        ach.create(name, cnt, frame, truncate=True)
        with ach.Channel(name, create=False) as w, ach.Channel(name, create=False) as r:
            for k in range(cnt):  # the index is full: the next put evicts slot 0, a fresh reader reads slot 0
                w.put(bytes([k + 1]) * (frame - k))
            fd = os.open(ach.shm_path(name), os.O_RDWR)  # another process's view of the same memory
            with mmap.mmap(fd, 0) as mm:
                struct.pack_into("<Q", mm, offset, value)
            os.close(fd)
            got = r.get_status(bytearray(cnt * frame * 2))[0]
            put = w.put_status(b"x" * (frame - 1))
            try:
                w.put(b"y" * 8)
                message = ""
            except ach.AchException as exc:
                message = str(exc)
            print(json.dumps({"field": field, "value": value, "fast": w.fast, "get": got, "put": put,
                              "message": message}), flush=True)
"""


def run_child(code: str, *args: str, timeout: float = 60.0, stdin: str | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=timeout,
                          input=stdin)


def died(proc: subprocess.CompletedProcess | subprocess.Popen) -> str:
    """'' when the child exited normally, else how it died (the defect this module is about)."""
    if proc.returncode is not None and proc.returncode < 0:
        return f"child killed by {signal.Signals(-proc.returncode).name}"
    return "" if proc.returncode == 0 else f"child exited with {proc.returncode}"


@pytest.mark.usefixtures("ach_impl", "clean_shm")
def test_scribbled_header_or_index_reads_as_corrupt_never_as_a_wild_access(ach_impl: str) -> None:
    """Every header word and index-entry word that a put or get uses as an offset, a length or a count, overwritten
    with a value outside the ring: the next get and put report ACH_CORRUPT (naming the channel and `mds-ach
    repair`) instead of reading or writing outside the mapping (SIGSEGV, or silent damage to other memory)."""
    scribbles = {field: [offset, values] for field, (offset, values) in SCRIBBLES.items()}
    out = run_child(SCRIBBLE_CHILD, NAME, str(CNT), str(FRAME), json.dumps(scribbles))
    lines = [json.loads(line) for line in out.stdout.splitlines()]
    last = lines[-1]["field"] if lines else "(none)"
    assert not died(out), f"{died(out)} after the scribble following {last}:\n{out.stderr[-3000:]}"
    assert len(lines) == sum(len(v) for _, v in SCRIBBLES.values())
    for line in lines:
        assert line["fast"] == (ach_impl == "fast")
        what = f"{line['field']} = {line['value']:#x}"
        assert (line["get"], line["put"]) == (ach.ACH_CORRUPT, ach.ACH_CORRUPT), what
        assert f"channel '{NAME}'" in line["message"] and f"mds-ach repair {NAME}" in line["message"], \
            f"{what}: {line['message']}"


@pytest.mark.usefixtures("ach_impl")
@pytest.mark.parametrize("field", ["index_head", "data_free", "index[0].offset"])
def test_repair_fixes_scribbled_counters_and_entries_in_place(clean_shm: None, field: str) -> None:
    """Out-of-range ring counters or index entries are what a put or get refuses; `mds-ach repair` reports them and
    rebuilds the ring from the frames that are intact, and the open handles work again."""
    ach.create(NAME, CNT, FRAME)
    with ach.Channel(NAME, create=False) as w, ach.Channel(NAME, create=False) as r:
        for k in range(6):
            w.put(bytes([k + 1]) * 10)
        offset, values = SCRIBBLES[field]
        if field.startswith("index["):
            offset += 24 * ((6 - 1) % CNT)  # the newest frame's entry: seq s sits in slot (s - 1) % cnt
        fd = os.open(ach.shm_path(NAME), os.O_RDWR)
        with mmap.mmap(fd, 0) as mm:
            struct.pack_into("<Q", mm, offset, values[-1])
        os.close(fd)
        buf = bytearray(DSIZE)
        assert r.get_status(buf, ach.ACH_O_LAST)[0] == ach.ACH_CORRUPT
        report = repair.check(NAME)
        assert report.state == repair.CORRUPT and "out of range" in report.detail, report.line()
        fixed = repair.repair(NAME)
        assert fixed.ok and fixed.action == "repaired", fixed.line()
        assert repair.check(NAME).ok
        w.put(b"after repair")
        status, size = r.get(buf, last=True)
        assert status in (ach.ACH_OK, ach.ACH_MISSED_FRAME) and bytes(buf[:size]) == b"after repair"


# --- truncation ------------------------------------------------------------------------------------------------

TRUNCATE_CHILD = r"""
import json, sys, threading, time
from mds_ach import ach

name = sys.argv[1]
w = ach.Channel(name, create=False)
r = ach.Channel(name, create=False)
waiter = ach.Channel(name, create=False)
seen = {"put": [], "get": [], "wait": []}
stop = threading.Event()
messages = []

def record(kind, call):
    while not stop.is_set():
        try:
            status = call()
            status = status if isinstance(status, int) else status[0]
        except ach.AchException as exc:
            status = exc.status
            if status == ach.ACH_CORRUPT and len(messages) < 3:
                messages.append(str(exc))
        if not seen[kind] or seen[kind][-1] != status:
            seen[kind].append(status)
        time.sleep(0.001)  # a client's pace: at 1 kHz, not a lock-contention benchmark

threads = [threading.Thread(target=record, args=("put", lambda: w.put_status(b"x" * 3000))),
           threading.Thread(target=record, args=("get", lambda: r.get(bytearray(30000), last=True))),
           threading.Thread(target=record, args=("wait", lambda: waiter.get(bytearray(30000), wait=True,
                                                                             timeout=0.05)))]
for t in threads:
    t.start()
time.sleep(0.2)
print("running", flush=True)
sys.stdin.readline()  # the parent truncated the file meanwhile
deadline = time.monotonic() + 20
while time.monotonic() < deadline and not all(s and s[-1] == ach.ACH_CORRUPT for s in seen.values()):
    time.sleep(0.01)
stop.set()
for t in threads:
    t.join()
lost = [w.lost, r.lost, waiter.lost]
for ch in (w, r, waiter):
    ch.close()  # a lost mapping is kept, never unmapped
print(json.dumps({"seen": seen, "lost": lost, "messages": messages}), flush=True)
sys.stdin.readline()  # the parent ran `mds-ach repair` meanwhile
with ach.Channel(name, create=False) as again:  # re-opened: works
    again.put(b"after repair")
    print(json.dumps({"again": again.get(bytearray(64), last=True)[0]}), flush=True)
with ach.Channel("test-other", 4, 64) as other:  # other channels' robust mutexes still lock and unlock
    for _ in range(100):
        other.put(b"x")
print("done", flush=True)
"""


@pytest.mark.usefixtures("ach_impl")
@pytest.mark.parametrize("keep", ["nothing", "the first page", "half"])
def test_truncated_channel_under_running_clients_is_reported_never_sigbus(clean_shm: None, keep: str) -> None:
    """A channel file truncated while a writer, a reader and a waiting reader run (threads at 1 kHz, the file
    shrinking at whatever point they are): no SIGBUS; every call reports ACH_CORRUPT with a message that says what
    happened and what to do; the process keeps running, and after `mds-ach repair` a re-opened handle works."""
    ach.create(NAME, 10, 3000)
    size = os.stat(ach.shm_path(NAME)).st_size
    new_size = {"nothing": 0, "the first page": 4096, "half": size // 2}[keep]
    child = subprocess.Popen([sys.executable, "-c", TRUNCATE_CHILD, NAME], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "running", child.stderr.read()
        os.truncate(ach.shm_path(NAME), new_size)
        child.stdin.write("\n")
        child.stdin.flush()
        line = child.stdout.readline()
        if not line:
            child.wait(30)
            raise AssertionError(f"{died(child)}:\n{child.stderr.read()[-3000:]}")
        report = json.loads(line)
        for kind, statuses in report["seen"].items():
            assert statuses[-1] == ach.ACH_CORRUPT, f"{kind}: {[ach.result_string(s) for s in statuses]}"
            assert set(statuses) <= {ach.ACH_OK, ach.ACH_MISSED_FRAME, ach.ACH_STALE_FRAMES, ach.ACH_TIMEOUT,
                                     ach.ACH_CORRUPT}, f"{kind}: {statuses}"
        assert all(report["lost"]), report  # every handle of the file in the process knows
        assert report["messages"], report
        for message in report["messages"]:
            assert NAME in message and "mds-ach repair" in message, message
        assert any("truncated" in m and "re-open" in m for m in report["messages"]), report["messages"]
        fixed = repair.repair(NAME)
        assert fixed.ok and fixed.action == "re-created", fixed.line()
        child.stdin.write("\n")
        child.stdin.flush()
        assert json.loads(child.stdout.readline()) == {"again": ach.ACH_OK}
        assert child.stdout.readline().strip() == "done"
        child.wait(30)
        assert not died(child), child.stderr.read()[-3000:]
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()


BLOCKED_CHILD = r"""
import json, sys, threading, time
from mds_ach import ach

name, what = sys.argv[1], sys.argv[2]
ch = ach.Channel(name, create=False)
result = {}

def call():
    t0 = time.monotonic()
    try:
        if what == "frame":  # nothing new: sleeps in the futex wait on last_seq
            result["status"] = ch.get(bytearray(30000), wait=True, timeout=30)[0]
        else:  # another process holds the lock: waits for it (no lock_timeout: as long as it takes)
            result["status"] = ch.put_status(b"x" * 3000)
    except ach.AchException as exc:
        result["status"], result["message"] = exc.status, str(exc)
    result["seconds"] = time.monotonic() - t0

t = threading.Thread(target=call)
t.start()
time.sleep(0.3)
print("blocked" if t.is_alive() else "not blocked", flush=True)
sys.stdin.readline()  # the parent truncated the file meanwhile
t.join(20)
print(json.dumps(result), flush=True)
"""


@pytest.mark.usefixtures("ach_impl")
@pytest.mark.parametrize("what", ["frame", "lock"])
def test_truncation_ends_a_wait_for_a_frame_or_for_the_lock(clean_shm: None, what: str) -> None:
    """A reader asleep waiting for a frame, or a writer waiting for a lock that another process holds, when the file
    is truncated: the call comes back with ACH_CORRUPT within a wait slice, instead of a SIGBUS or waiting forever
    for a lock whose owner can no longer release it."""
    ach.create(NAME, 10, 3000)
    holder = LockHolder(NAME) if what == "lock" else None
    child = subprocess.Popen([sys.executable, "-c", BLOCKED_CHILD, NAME, what], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "blocked", child.stderr.read()
        os.truncate(ach.shm_path(NAME), 0)
        out, err = child.communicate("\n", timeout=60)
        assert not died(child), f"{died(child)}:\n{err[-3000:]}"
        result = json.loads(out.splitlines()[-1]) if out.strip() else {}
        assert result.get("status") == ach.ACH_CORRUPT, (result, err[-3000:])
        if what == "frame":
            assert "truncated" in result["message"] and "mds-ach repair" in result["message"], result
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
        if holder is not None:
            holder.close()


STUCK_CHILD = r"""
import inspect, sys
from mds_ach import ach

name, method, marker = sys.argv[1:4]
ch = ach.Channel(name, create=False, fast=False)  # the pure-Python path, so a trace can stop it inside
ch.put(b"a" * 3000)
function = getattr(ach.Channel, method)
lines, first = inspect.getsourcelines(function)
stop = first + next(i for i, text in enumerate(lines) if marker in text)

def local(frame, event, arg):
    if event == "line" and frame.f_lineno == stop:
        sys.settrace(None)
        print("inside, holding the lock", flush=True)
        sys.stdin.readline()  # the parent truncates the file to 0 bytes: the mutex we hold is gone too
    return local

sys.settrace(lambda frame, event, arg: local if frame.f_code is function.__code__ else None)
status = ch.put_status(b"b" * 3000) if method == "_write_locked" else ch.get_status(bytearray(3000))[0]
print(status, ch.lost, flush=True)
ch.close()
with ach.Channel("test-other", 4, 64) as other:  # this thread's robust-mutex list still works
    for _ in range(100):
        other.put(b"x")
    print(other.get(bytearray(64), last=True), flush=True)
"""


@pytest.mark.skipif(not ach.GUARD_AVAILABLE, reason="mds_ach.ach._shmguard not built (no C compiler)")
@pytest.mark.parametrize("method, marker", [("_write_locked", "self._mv[start:start + n] = src"),
                                            ("_read_locked", "dst[:size] = self._mv[start:start + size]")],
                         ids=["put", "get"])
def test_file_truncated_to_nothing_inside_a_put_or_get(clean_shm: None, method: str, marker: str) -> None:
    """The hardest case: the file vanishes, the page of the channel mutex included, while this thread holds that
    mutex in the middle of copying a frame. The copy completes on the restored (zeroed) pages, the call reports
    ACH_CORRUPT, and the thread then locks other channels normally."""
    ach.create(NAME, 10, 3000)
    child = subprocess.Popen([sys.executable, "-c", STUCK_CHILD, NAME, method, marker], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "inside, holding the lock", child.stderr.read()
        os.truncate(ach.shm_path(NAME), 0)
        out, err = child.communicate("\n", timeout=30)
        assert not died(child), f"{died(child)}:\n{err[-3000:]}"
        assert out.splitlines() == [f"{ach.ACH_CORRUPT} True", f"({ach.ACH_MISSED_FRAME}, 1)"], out + err
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()


# --- a full /dev/shm -----------------------------------------------------------------------------------------------

FULL_SHM_CHILD = r"""
import mmap, os, sys
from mds_ach import ach

free = os.statvfs("/dev/shm")
filler = os.open("/dev/shm/filler", os.O_RDWR | os.O_CREAT, 0o600)
os.posix_fallocate(filler, 0, free.f_bavail * free.f_frsize - 2 * 4096)  # leave two pages
try:
    ach.create("test-full", 10, 3000)
    print("created")
    with ach.Channel("test-full", create=False) as ch:
        for _ in range(30):
            ch.put(b"x" * 3000)
    print("no error")
except ach.AchException as exc:
    print("create:", exc)
print("exists:", ach.exists("test-full"), sorted(os.listdir("/dev/shm")))

# A sparse channel file, as libach's `ach mk` leaves it: the header page written, the rest unallocated.
os.ftruncate(filler, 0)
ach.create("test-sparse", 10, 3000)
with open("/dev/shm/achshm-test-sparse", "rb") as f:
    header = f.read(4096)
size = os.stat("/dev/shm/achshm-test-sparse").st_size
os.unlink("/dev/shm/achshm-test-sparse")
fd = os.open("/dev/shm/achshm-test-sparse", os.O_RDWR | os.O_CREAT, 0o660)
os.ftruncate(fd, size)
os.pwrite(fd, header, 0)
os.pwrite(fd, ach.GUARD_DATA.to_bytes(8, "little"), size - 8)
free = os.statvfs("/dev/shm")
os.posix_fallocate(filler, 0, free.f_bavail * free.f_frsize)  # now /dev/shm is full
try:
    ach.Channel("test-sparse", create=False)
    print("opened")
except ach.AchException as exc:
    print("open:", exc)

# The guard itself: a first write to an unallocated page of a mapped sparse file on a full tmpfs.
mm = mmap.mmap(fd, size)
guard = ach.MappingGuard(mm, fd)
mm[8192:8200] = b"12345678"
print("guard:", guard.lost, guard.reason("test-sparse", size))
"""


@pytest.mark.skipif(not in_netns() or os.geteuid() != 0 or shutil.which("unshare") is None,
                    reason="needs root inside tools/netns-run to mount a tiny tmpfs on /dev/shm")
@pytest.mark.usefixtures("ach_impl")
def test_full_dev_shm_fails_at_creation_with_the_sizes_never_later_with_sigbus() -> None:
    """Channel memory is reserved when a channel is created (and when a sparse one is opened): on a full /dev/shm
    that is where it fails, saying which channel, how many bytes and what to check, instead of a SIGBUS in the
    first writer that touches a fresh page."""
    out = subprocess.run(["unshare", "-m", "--propagation", "private", "sh", "-c",
                          'mount -t tmpfs -o size=64k tmpfs /dev/shm && exec "$@"', "sh",
                          sys.executable, "-c", FULL_SHM_CHILD], capture_output=True, text=True, timeout=60,
                         cwd=REPO)
    assert not died(out), f"{died(out)}:\n{out.stdout}\n{out.stderr[-3000:]}"
    lines = out.stdout.splitlines()
    create = next(line for line in lines if line.startswith(("create:", "created", "no error")))
    assert create.startswith("create:"), out.stdout
    for text in ("channel 'test-full'", "ACH_FAILED_SYSCALL", f"{ach.native_layout().file_size(10, 30000)} bytes",
                 "df -h /dev/shm", "No space left"):
        assert text in create, create
    assert "exists: False ['filler']" in lines, out.stdout  # nothing left behind
    opened = next(line for line in lines if line.startswith(("open:", "opened")))
    assert opened.startswith("open:") and "channel 'test-sparse'" in opened and "cannot open it" in opened, opened
    guard = next(line for line in lines if line.startswith("guard:"))
    if ach.GUARD_AVAILABLE:
        assert guard.startswith("guard: True") and "could not be allocated" in guard, guard


# --- timed locks ---------------------------------------------------------------------------------------------------

def image(name: str) -> bytes:
    data = bytearray(Path(ach.shm_path(name)).read_bytes())
    data[LAYOUT.mutex:LAYOUT.dirty] = bytes(LAYOUT.dirty - LAYOUT.mutex)  # glibc's bytes inside the mutex/condvar
    return bytes(data)


def bounded(call: Callable[[], object]) -> tuple[ach.AchException, float]:
    """The AchException ``call`` raises, and how long it took."""
    t0 = time.monotonic()
    with pytest.raises(ach.AchException) as info:
        call()
    return info.value, time.monotonic() - t0


@pytest.mark.usefixtures("ach_impl")
def test_lock_timeout_gives_up_without_touching_the_channel(clean_shm: None) -> None:
    ach.create(NAME, CNT, 1024)  # room for an MDS_REF
    with ach.Channel(NAME, create=False) as w:
        w.put(b"before")
    holder = LockHolder(NAME)
    try:
        before = image(NAME)
        with ach.Channel(NAME, create=False) as ch:
            buf = bytearray(FRAME)
            for call in (lambda: ch.put(b"x", lock_timeout=0.05), lambda: ch.get(buf, lock_timeout=0.05),
                         lambda: ch.get(buf, wait=True, timeout=5, lock_timeout=0.05)):
                exc, took = bounded(call)
                assert exc.status == ach.ACH_LOCKED and 0.04 < took < 3.0, (exc, took)
                assert "lock held by another process" in str(exc) and "> 50 ms" in str(exc) and NAME in str(exc)
            assert ch.put_status(b"x", lock_timeout=0) == ach.ACH_LOCKED
            assert ch.get_status(buf, lock_timeout=0) == (ach.ACH_LOCKED, 0)
            assert ch.seq_num == 0  # nothing was read
            ch.lock_timeout = 0.02  # the handle's default for every put and get
            assert bounded(lambda: ch.put(b"x"))[0].status == ach.ACH_LOCKED
            assert bounded(lambda: ch.poll(buf, timeout=1))[0].status == ach.ACH_LOCKED
        typed = StructChannel(NAME, MDS_REF, create=False, lock_timeout=0.02)
        try:
            for call in (typed.latest, lambda: typed.put(MDS_REF()), lambda: typed.wait(timeout=1)):
                assert bounded(call)[0].status == ach.ACH_LOCKED
        finally:
            typed.close()
        assert image(NAME) == before  # nothing was written, nothing marked dirty
        holder.release()
        with ach.Channel(NAME, create=False, lock_timeout=0.05) as ch:
            ch.put(b"after")
            buf = bytearray(FRAME)
            assert ch.get(buf, last=True) == (ach.ACH_MISSED_FRAME, 5) and buf[:5] == b"after"
    finally:
        holder.close()


@pytest.mark.usefixtures("ach_impl")
def test_lock_timeout_still_recovers_a_dead_owner(clean_shm: None) -> None:
    """A timed lock keeps libach's robust-mutex handling: an owner that died is recovered (EOWNERDEAD)."""
    ach.create(NAME, CNT, FRAME)
    holder = LockHolder(NAME)
    holder.close()  # SIGKILLed while holding the lock
    with ach.Channel(NAME, create=False) as ch:
        ch.put(b"x", lock_timeout=0.05)
        assert ch.get(bytearray(FRAME), lock_timeout=0.05) == (ach.ACH_OK, 1)


def test_bad_lock_timeouts_are_refused(clean_shm: None) -> None:
    with ach.Channel(NAME, CNT, FRAME) as ch:
        for bad in (-1.0, float("nan")):
            with pytest.raises(ValueError, match="lock_timeout"):
                ch.put(b"x", lock_timeout=bad)
        ch.lock_timeout = float("inf")
        assert ch.lock_timeout is None


def test_waiting_for_a_held_lock_releases_the_gil(clean_shm: None) -> None:
    """While one thread waits (bounded) for a held lock, the others run."""
    ach.create(NAME, CNT, FRAME)
    holder = LockHolder(NAME)
    try:
        with ach.Channel(NAME, create=False) as ch:
            result: list[int] = []
            t = threading.Thread(target=lambda: result.append(ch.put_status(b"x", lock_timeout=0.5)))
            t.start()
            ticks = 0
            while t.is_alive():
                ticks += 1
            assert result == [ach.ACH_LOCKED] and ticks > 1000
    finally:
        holder.close()
