"""Find and repair corrupt Ach channels (``mds-ach repair``), without touching the healthy ones.

libach marks a channel corrupt when a writer dies inside ``ach_put``: the ``dirty`` word stays 1 and from then
on every get, put and flush in every process returns ``ACH_CORRUPT``. libach's own remedy is to re-create the
channel, which strands every process that still has the old file mapped (it keeps the orphaned, corrupt
memory) until it is restarted. This module repairs such a channel *in place* instead, so the daemon and the
pipeline nodes carry on with their open handles:

1. take the channel's robust mutex like any libach client (``EOWNERDEAD`` -> ``pthread_mutex_consistent``),
   with a timeout so a live but stuck holder is reported instead of waited for;
2. keep only the frames that are certainly complete: libach zeroes an evicted index entry before it copies the
   new frame's data, so every live entry except the one being written points at intact data. The entry of the
   interrupted put, entries torn by a half-done eviction and anything not contiguous with the newest good
   frame are dropped;
3. rebuild the ring counters from the kept frames, set ``last_seq`` to the newest kept frame (no reader can
   have seen a frame whose put never finished), clear ``dirty`` and unlock. The condvar is never touched.

The same rebuild repairs ring counters or index entries that something scribbled out of range (every get and put
refuses them with ACH_CORRUPT). The result is a state libach itself produces, so C and Python clients alike
continue. A channel whose geometry (length, frame count, data size), guards or mutex are damaged, or whose file
was truncated, cannot be repaired in place: it is re-created with the same geometry and mode, and the processes
that still map the old file are listed, because they must be restarted.
"""

from __future__ import annotations

import argparse
import ctypes
import errno
import math
import mmap
import os
import struct
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import mds_ach as mds
from mds_ach import ach
from mds_ach.ach.glibc import FUTEX_TID_MASK, Timespec, pthread
from mds_ach.ach.layout import (
    OFF_DATA_FREE,
    OFF_DATA_HEAD,
    OFF_DATA_SIZE,
    OFF_INDEX_CNT,
    OFF_INDEX_FREE,
    OFF_INDEX_HEAD,
    entry_ok,
)
from mds_ach.argtypes import seconds
from mds_ach.robot import access as channel_access

LOCK_TIMEOUT = 1.0  # s: a healthy put or get holds the lock for microseconds

_U64 = struct.Struct("<Q")
_I32 = struct.Struct("<i")

OK = "ok"
MISSING = "missing"
CORRUPT = "corrupt"  # dirty (a writer died mid-put) or counters/index out of range; repairable in place
BROKEN = "broken"  # header, guards or mutex damaged; must be re-created
LOCKED = "locked"  # a live process holds the lock and does not let go
UNSAFE = "unsafe"  # owner, mode or type the stack must not trust (channel_access); must be re-created


@dataclass
class Report:
    """What ``check``/``repair`` found and did for one channel. ``ok`` is True when it is usable now."""

    name: str
    state: str
    detail: str = ""
    action: str = ""  # "", "repaired", "re-created"
    kept: int = 0  # frames kept by an in-place repair
    dropped: int = 0  # index entries dropped by it
    users: list[int] = field(default_factory=list)  # pids that map the (old) file, for a re-creation

    @property
    def ok(self) -> bool:
        return self.state == OK

    def hint(self) -> str:
        """What to do about a channel that is not ok (empty when it is)."""
        return {
            MISSING: "mds-ach make (or start) creates it",
            CORRUPT: f"repair it in place: mds-ach repair {self.name}",
            BROKEN: f"mds-ach repair {self.name} re-creates it; the stack's nodes re-open it by themselves, "
                    "restart any other process that uses it",
            LOCKED: "resume (kill -CONT) or kill that process, then mds-ach repair (docs/reliability.md)",
            UNSAFE: channel_access.recreate_hint(self.name),
        }.get(self.state, "")

    def line(self) -> str:
        """One line for the command line: name, state, what was done."""
        text = f"{self.name:<20} {self.state:<8} {self.detail}"
        if self.state == UNSAFE:
            text += f"; {self.hint()}"
        if self.action == "repaired":
            text += (f" -> repaired in place (kept {self.kept} frame(s), dropped {self.dropped}); "
                     "open handles work again")
        elif self.action == "re-created":
            text += " -> re-created empty with the channel's size and a safe mode (docs/operator.md)"
            if self.users:
                text += (f"; the stack's nodes re-open it by themselves, restart any other process that still maps "
                         f"the old file: pids {' '.join(map(str, self.users))}")
        return text


# --------------------------------------------------------------------------------------------- who uses it


def users(name: str) -> list[int]:
    """Pids (other than ours) that have the channel file mapped, including an unlinked (orphaned) one."""
    path = ach.shm_path(name)
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            maps = (entry / "maps").read_text()
        except OSError:
            continue
        for line in maps.splitlines():
            fields = line.split(None, 5)
            if len(fields) == 6 and fields[5] in (path, f"{path} (deleted)"):
                found.append(int(entry.name))
                break
    return sorted(found)


def _holder(tid: int) -> str:
    """'pid P (comm, state S)' for the thread id stored in a locked futex word."""
    for task in Path("/proc").glob(f"[0-9]*/task/{tid}"):
        pid = task.parent.parent.name
        try:
            stat = (task / "stat").read_text()
            comm, state = stat[stat.find("(") + 1:stat.rfind(")")], stat[stat.rfind(")") + 2:][:1]
        except OSError:
            return f"pid {pid}"
        return f"pid {pid} ({comm}, state {state})"
    return f"thread {tid} (not visible here)"


# --------------------------------------------------------------------------------------------- the mapped file


class _Mapped:
    """The channel file mapped read-write, with the address of the mutex libach locks. The mapping is guarded:
    if the file shrinks meanwhile, ``lost`` turns true instead of the process dying of SIGBUS."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.path = ach.shm_path(name)
        self.layout = ach.native_layout()
        self.fd = os.open(self.path, os.O_RDWR | os.O_CLOEXEC)
        try:
            self.stat = os.fstat(self.fd)
            self.mm = mmap.mmap(self.fd, self.stat.st_size)
        except BaseException:
            os.close(self.fd)
            raise
        self.guard = ach.MappingGuard(self.mm, self.fd)
        self._anchor = ctypes.c_char.from_buffer(self.mm)
        base = ctypes.addressof(self._anchor)
        self.mutex = ctypes.c_void_p(base + self.layout.mutex)

    def u64(self, offset: int) -> int:
        value: int = _U64.unpack_from(self.mm, offset)[0]
        return value

    def set_u64(self, offset: int, value: int) -> None:
        _U64.pack_into(self.mm, offset, value)

    @property
    def dirty(self) -> int:
        flag: int = _I32.unpack_from(self.mm, self.layout.dirty)[0]
        return flag

    @dirty.setter
    def dirty(self, value: int) -> None:
        _I32.pack_into(self.mm, self.layout.dirty, value)

    @property
    def lock_owner(self) -> int:
        word: int = _I32.unpack_from(self.mm, self.layout.mutex)[0]
        return word & FUTEX_TID_MASK

    @property
    def lost(self) -> bool:
        return self.guard.lost

    def close(self) -> None:
        del self._anchor
        if self.guard.release(self.mm, self.fd):  # a lost mapping stays (ach.MappingGuard)
            self.mm.close()
            os.close(self.fd)


def _structure_problem(m: _Mapped) -> str | None:
    """Why the file is not a sound Ach channel of this architecture (magic, length, guards), or None."""
    try:
        ach.parse_image(m.mm[:], m.layout.arch)
    except ach.AchException as exc:
        return exc.reason
    if m.lost:
        return f"{m.path} shrank while it was being checked (truncated)"
    return None


def _ring_problem(m: _Mapped) -> str | None:
    """Ring counters or live index entries out of range (what every get and put refuses), or None. Caller holds
    the lock."""
    h = m.layout.header_size
    cnt, dsize, last_seq = m.u64(OFF_INDEX_CNT), m.u64(OFF_DATA_SIZE), m.u64(m.layout.last_seq)
    index_head, index_free = m.u64(OFF_INDEX_HEAD), m.u64(OFF_INDEX_FREE)
    data_head, data_free = m.u64(OFF_DATA_HEAD), m.u64(OFF_DATA_FREE)
    if not (index_head < cnt and index_free <= cnt and data_head < dsize and data_free <= dsize):
        return (f"ring counters out of range: index_head {index_head}, index_free {index_free} ({cnt} slots), "
                f"data_head {data_head}, data_free {data_free} ({dsize} bytes)")
    for slot in range(cnt):
        size, offset, seq = struct.unpack_from("<QQQ", m.mm, h + 8 + 24 * slot)
        if (size or offset or seq) and not entry_ok(size, offset, seq, dsize, last_seq):
            return f"index entry {slot} out of range: size {size}, offset {offset}, seq {seq} (last_seq {last_seq})"
    return None


def _lock(m: _Mapped, timeout: float) -> tuple[int, str]:
    """pthread_mutex_timedlock on the channel mutex; (0 or EOWNERDEAD when we hold it, else the error), note."""
    fn = pthread()
    deadline = time.clock_gettime(time.CLOCK_REALTIME) + timeout
    ts = Timespec.at(deadline)
    r = fn.mutex_timedlock(m.mutex, ctypes.byref(ts))
    if r == errno.EOWNERDEAD:
        fn.mutex_consistent(m.mutex)
        return r, "a process died holding the lock (recovered)"
    if r == errno.ETIMEDOUT:
        return r, f"lock held for more than {timeout:g} s by {_holder(m.lock_owner)}"
    if r == errno.ENOTRECOVERABLE:
        return r, "the mutex is unrecoverable (a process unlocked it after its owner died without making it consistent)"
    if r:
        return r, f"pthread_mutex_timedlock: {os.strerror(r)}"
    return 0, ""


def _unlock(m: _Mapped) -> None:
    """Unlock only. No condvar broadcast: a corrupt channel has no waiters (every wait returns ACH_CORRUPT), the
    next put wakes readers anyway, and a condvar wedged by a killed waiter would hang the broadcast forever."""
    pthread().mutex_unlock(m.mutex)


# --------------------------------------------------------------------------------------------- in-place rebuild


@dataclass(frozen=True)
class _Entry:
    slot: int
    size: int
    offset: int
    seq: int


def _good_frames(m: _Mapped) -> tuple[list[_Entry], int]:
    """The frames that are certainly complete, oldest first, and how many live-looking entries were dropped."""
    h = m.layout.header_size
    cnt, dsize = m.u64(OFF_INDEX_CNT), m.u64(OFF_DATA_SIZE)
    last_seq, index_head, data_head = m.u64(m.layout.last_seq), m.u64(OFF_INDEX_HEAD), m.u64(OFF_DATA_HEAD)
    live = []
    for slot in range(cnt):
        size, offset, seq = struct.unpack_from("<QQQ", m.mm, h + 8 + 24 * slot)
        if size or offset or seq:
            live.append(_Entry(slot, size, offset, seq))
    candidates = [e for e in live if entry_ok(e.size, e.offset, e.seq, dsize, last_seq)
                  and e.slot == (e.seq - 1) % cnt]
    # The interrupted put's own entry sits at index_head until the head moves on; its fields may be half written.
    candidates = [e for e in candidates if not (e.seq == last_seq and e.slot == index_head % cnt
                                                and e.offset != data_head)]
    kept: list[_Entry] = []
    for e in sorted(candidates, key=lambda e: e.seq, reverse=True):  # newest first
        if kept:
            newer = kept[-1]
            contiguous = e.seq == newer.seq - 1 and (e.offset + e.size == newer.offset or newer.offset == 0)
            overlaps = any(e.offset < k.offset + k.size and k.offset < e.offset + e.size for k in kept)
            if not contiguous or overlaps:
                break
        kept.append(e)
    kept.reverse()
    return kept, len(live) - len(kept)


def _rebuild(m: _Mapped) -> tuple[int, int]:
    """Rewrite index and counters around the good frames (caller holds the lock). Returns (kept, dropped)."""
    h = m.layout.header_size
    cnt, dsize = m.u64(OFF_INDEX_CNT), m.u64(OFF_DATA_SIZE)
    kept, dropped = _good_frames(m)
    keep = {e.slot for e in kept}
    for slot in range(cnt):
        if slot not in keep:
            struct.pack_into("<QQQ", m.mm, h + 8 + 24 * slot, 0, 0, 0)
    if kept:
        newest, oldest = kept[-1], kept[0]
        data_head = (newest.offset + newest.size) % dsize
        data_free = (oldest.offset - data_head) % dsize  # free bytes from the head up to the oldest frame
        index_head = (newest.slot + 1) % cnt
        m.set_u64(m.layout.last_seq, newest.seq)
    else:  # nothing survived: an empty ring; last_seq stays, so readers that saw older frames just wait
        data_head, data_free, index_head = 0, dsize, m.u64(OFF_INDEX_HEAD) % cnt
    for offset, value in ((OFF_DATA_HEAD, data_head), (OFF_DATA_FREE, data_free),
                          (OFF_INDEX_HEAD, index_head), (OFF_INDEX_FREE, cnt - len(kept))):
        m.set_u64(offset, value)
    m.dirty = 0
    return len(kept), dropped


# --------------------------------------------------------------------------------------------- check / repair


def _examine(name: str, timeout: float, fix: bool) -> Report:
    """Check one channel; with ``fix`` repair a dirty one in place while holding its lock."""
    unsafe = channel_access.path_problem(name)
    if unsafe is not None:  # never lock or rewrite a file another user controls
        return Report(name, UNSAFE, unsafe)
    try:
        m = _Mapped(name)
    except FileNotFoundError:
        return Report(name, MISSING, "no such channel (mds-ach make creates the MDS channels)")
    except ValueError as exc:  # mmap of an empty file
        return Report(name, BROKEN, f"not an Ach channel: {exc}")
    except OSError as exc:
        return Report(name, BROKEN, f"cannot open {ach.shm_path(name)}: {exc.strerror}")
    try:
        problem = _structure_problem(m)
        if problem:
            return Report(name, BROKEN, problem)
        r, note = _lock(m, timeout)
        if r not in (0, errno.EOWNERDEAD):
            return Report(name, LOCKED if r == errno.ETIMEDOUT else BROKEN, note)
        try:
            if m.dirty:
                detail = "a writer died inside a put (dirty flag set): every get/put returns ACH_CORRUPT"
            else:
                ring = _ring_problem(m)
                if ring is None:
                    return Report(name, OK, note)
                detail = ring + ": every get/put that meets it returns ACH_CORRUPT"
            if not fix:
                return Report(name, CORRUPT, detail)
            kept, dropped = _rebuild(m)
        finally:
            _unlock(m)
        if m.lost:
            return Report(name, BROKEN, f"{m.path} shrank while it was being repaired (truncated)")
        return Report(name, OK, detail, "repaired", kept, dropped)
    finally:
        m.close()


def check(name: str, timeout: float = LOCK_TIMEOUT) -> Report:
    """Is the channel usable? Takes its lock (like any client) but changes nothing."""
    ach.validate_name(name)
    return _examine(name, timeout, fix=False)


def repair(name: str, timeout: float = LOCK_TIMEOUT, recreate: bool = False) -> Report:
    """Repair a corrupt channel in place; re-create a broken one (or any, with ``recreate``). Healthy channels
    are left alone unless ``recreate`` is given; a channel locked by a live process is only reported."""
    ach.validate_name(name)
    report = _examine(name, timeout, fix=not recreate)
    if report.state == BROKEN or (recreate and report.state in (OK, CORRUPT, UNSAFE)):
        return _recreate(name, report)
    return report


def _geometry(name: str) -> tuple[int, int, int, int, int]:
    """(frame_count, frame_size, mode, uid, gid) of the existing file, MDS defaults where it is unreadable."""
    count, size = mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE
    path = ach.shm_path(name)
    st = os.stat(path)
    try:
        with open(path, "rb") as f:
            head = f.read(OFF_DATA_SIZE + 8)
        cnt, dsize = struct.unpack_from("<QQ", head, OFF_INDEX_CNT)
        if 0 < cnt <= 1 << 20 and 0 < dsize <= 1 << 34 and dsize % cnt == 0:
            count, size = cnt, dsize // cnt
    except (OSError, struct.error):
        pass
    return count, size, st.st_mode & 0o7777, st.st_uid, st.st_gid


def _recreate(name: str, report: Report) -> Report:
    """Replace the file with an empty channel: same geometry, mode (never looser than the channel's, see
    ``channel_access``), owner and group; an untrusted file's geometry, owner and group are not kept (MDS
    sizes, the new file belongs to us)."""
    if report.state == UNSAFE:
        count, size = mds.CHANNEL_FRAME_COUNT, mds.CHANNEL_FRAME_SIZE
        mode, owner = channel_access.channel_mode(name), None
    else:
        count, size, mode, uid, gid = _geometry(name)
        mode, owner = channel_access.channel_mode(name, mode & channel_access.CHANNEL_MODE), (uid, gid)
    holders = users(name)
    ach.create(name, count, size, mode=mode, truncate=True)  # atomic replace; old mappings keep the old memory
    if owner is not None:
        try:
            os.chown(ach.shm_path(name), *owner)
        except OSError:
            pass  # not ours to give away: the new file belongs to us
    return Report(name, OK, report.detail or report.state, "re-created", users=holders)


def scan(names: list[str] | tuple[str, ...] | None = None, timeout: float = LOCK_TIMEOUT,
         fix: bool = False, recreate: bool = False) -> list[Report]:
    """Check (or repair) ``names``, default: every MDS channel that exists. Other channels are not touched."""
    chosen = list(names) if names is not None else [n for n in mds.ALL_CHANNELS if ach.exists(n)]
    out = []
    for name in chosen:
        out.append(repair(name, timeout, recreate) if fix else check(name, timeout))
    return out


# --------------------------------------------------------------------------------------------- mds-ach repair


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Check the Ach channels and repair corrupt ones in place. A process killed inside a put "
                     "leaves its channel marked corrupt (libach's dirty flag): every get and put then fails "
                     "with ACH_CORRUPT. 'repair' keeps the frames that are complete, clears the flag and wakes "
                     "the waiting readers, so running nodes carry on with their open handles. Channels with a "
                     "damaged header or mutex are re-created (their users must be restarted; they are listed). "
                     "Healthy channels are never touched. See docs/reliability.md.")
    p.add_argument("names", nargs="*", metavar="NAME", help="channels (default: every MDS channel that exists)")
    p.add_argument("--check", action="store_true", help="only report; exit 1 if any channel needs a repair")
    p.add_argument("--recreate", action="store_true",
                   help="re-create the named channels empty instead of repairing in place (libach's remedy)")
    p.add_argument("--timeout", type=seconds(), default=LOCK_TIMEOUT,
                   help=f"seconds to wait for a channel's lock (default {LOCK_TIMEOUT:g})")
    p.add_argument("-q", "--quiet", action="store_true", help="print only channels that are not ok")


def run(args: argparse.Namespace) -> int:
    if args.recreate and not args.names:
        print("mds-ach repair: --recreate needs the channel names (it empties them)", file=sys.stderr)
        return 2
    if not (args.timeout > 0 and math.isfinite(args.timeout)):
        print("mds-ach repair: --timeout must be > 0", file=sys.stderr)
        return 2
    try:
        reports = scan(args.names or None, args.timeout, fix=not args.check, recreate=args.recreate)
    except ach.AchException as exc:
        if exc.status == ach.ACH_EACCES:  # e.g. replacing another user's file in the sticky /dev/shm
            print(f"mds-ach repair: {exc}; run it as root (or as the file's owner)", file=sys.stderr)
            return 1
        print(f"mds-ach repair: {exc}", file=sys.stderr)
        return 2
    if not reports:
        print("mds-ach repair: no MDS channels exist (mds-ach make creates them)")
        return 0
    failed = False
    for r in reports:
        bad = not r.ok and not (r.state == MISSING and not args.names)
        failed |= bad
        if bad or r.action or not args.quiet:
            print(r.line(), file=sys.stderr if bad else sys.stdout)
    return 1 if failed else 0

