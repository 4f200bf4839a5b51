"""Pure-Python Ach: shared-memory channels that are byte- and lock-compatible with C libach.

A channel is the file ``/dev/shm/achshm-<name>`` laid out exactly as libach 2.0 lays it out (see
``specs/ach-format.md``). Readers and writers synchronise through the process-shared, robust,
priority-inheriting pthread mutex and condition variable stored inside the file, called through glibc
with ctypes, so C programs linked against libach and Python programs using this module share channels.

The API mirrors the classic ``ach`` Python binding so that old client code ports by changing one import::

    from mds_ach import ach
    c = ach.Channel("mds-state")              # opens; creates with 16 x 512 if missing
    status, size = c.get(state, wait=True, last=True)
    c.put(ref)

Why some things look the way they do:

* ``put`` and ``get`` follow libach's algorithms literally (index wrap, overlap eviction, reader
  ``next_index`` starting at 1, ...) because golden files and mixed C/Python deployments need the very
  same bytes, not just equivalent behaviour.
* Readers do not wait inside the channel's pthread condvar by default. glibc's process-shared condvar is not
  robust: a waiter SIGKILLed inside ``pthread_cond_wait`` keeps a group reference forever, and the next
  ``pthread_cond_broadcast`` (every writer's, C or Python) then waits for it -- forever. Instead a reader sleeps
  on a futex keyed on the ``last_seq`` word, which leaves nothing behind when the process dies; Python writers
  wake it directly (``FUTEX_WAKE`` after the unlock) and still broadcast the condvar for C readers. Frames from
  C libach writers, which only broadcast, are noticed by the reader's periodic re-check (``POLL_SLICE``; with
  the C fast path an idle reader re-checks every ``IDLE_SLICE`` until it has seen such a frame).
  ``Channel(..., condvar_wait=True)`` waits in the condvar exactly like libach instead (C writers wake it at
  once; the dead-waiter hazard is then libach's too).
* Waits are cut into short timed slices so that Ctrl-C, ``cancel()`` and ``close()`` are honoured even though
  neither the futex nor the condvar wait is interrupted by Python's signal handling.
* A Python exception (Ctrl-C) can surface right after a ctypes call returned with the mutex held, so every
  locked section releases the mutex if the kernel lock word says this thread owns it.
* The hot calls (put, get, poll, flush) have an optional C twin, ``mds_ach.ach._achfast``, built with the package
  when a compiler is there: one C call per frame instead of a few ctypes calls and ~100 bytecodes, which matters
  on a process that wakes with cold caches every cycle. Same algorithms, same bytes (the tests run both);
  ``MDS_ACH_PURE_PYTHON=1`` or ``Channel(..., fast=False)`` uses this module's code alone.
* The file is not trusted: any process with write access can scribble over it. The geometry (``len``,
  ``index_cnt``, ``data_size``) is validated once at open and compared with the header on every call; the ring
  counters and each index entry a put or get uses are bounds-checked before use (read once, so a concurrent
  scribble cannot slip between check and use). A damaged header reads as ACH_CORRUPT naming ``mds-ach repair``,
  never as an access outside the mapping.
* A channel file truncated while mapped would raise SIGBUS in every process touching it; so would a first write
  to a page of a sparse file on a full ``/dev/shm``. Channel memory is therefore reserved when a channel is
  created or opened (``posix_fallocate``: a full ``/dev/shm`` fails there, with the sizes), and every mapping is
  registered with ``mds_ach.ach._shmguard``, whose SIGBUS handler grows a truncated file back to its length (its
  pages return as zeros, for every process) or, where that is impossible, maps private zeros over the rest, and
  marks the handle lost: the call reports ACH_CORRUPT and the process keeps running (re-open the channel after
  ``mds-ach repair``). Waits for a busy lock come back every ``_LOCK_SLICE_NS`` to look at the header, so a
  waiter parked in the kernel notices a truncation too. Without the compiled guard (no C compiler) a
  truncation still kills the process.
* ``lock_timeout`` (per handle, or per ``put``/``get``) bounds the wait for the channel mutex: a lock held by a
  stopped or runaway process then costs at most that long, and the call reports ACH_LOCKED without having
  touched the channel. Default: wait as long as it takes, like libach.
"""

from __future__ import annotations

import ctypes
import errno
import math
import mmap
import os
import platform
import struct
import threading
import time
from dataclasses import dataclass, field
from types import ModuleType

# --- status codes (enum ach_status) --------------------------------------------------------------
ACH_OK = 0
ACH_OVERFLOW = 1
ACH_INVALID_NAME = 2
ACH_BAD_SHM_FILE = 3
ACH_FAILED_SYSCALL = 4
ACH_EAGAIN = 5
ACH_STALE_FRAMES = ACH_EAGAIN
ACH_LOCKED = ACH_EAGAIN  # also: the channel mutex was not acquired within lock_timeout (put/get raise it)
ACH_MISSED_FRAME = 6
ACH_TIMEOUT = 7
ACH_EEXIST = 8
ACH_ENOENT = 9
ACH_CLOSED = 10
ACH_BUG = 11
ACH_EINVAL = 12
ACH_CORRUPT = 13
ACH_BAD_HEADER = 14
ACH_EACCES = 15
ACH_CANCELED = 16
ACH_EFAULT = 17
ACH_EINTR = 18
ACH_ENOTSUP = 19

_STATUS_NAMES = (
    "ACH_OK",
    "ACH_OVERFLOW",
    "ACH_INVALID_NAME",
    "ACH_BAD_SHM_FILE",
    "ACH_FAILED_SYSCALL",
    "ACH_EAGAIN",
    "ACH_MISSED_FRAME",
    "ACH_TIMEOUT",
    "ACH_EEXIST",
    "ACH_ENOENT",
    "ACH_CLOSED",
    "ACH_BUG",
    "ACH_EINVAL",
    "ACH_CORRUPT",
    "ACH_BAD_HEADER",
    "ACH_EACCES",
    "ACH_CANCELED",
    "ACH_EFAULT",
    "ACH_EINTR",
    "ACH_ENOTSUP",
)

_EXPLANATIONS = {
    ACH_OK: "success",
    ACH_OVERFLOW: "frame does not fit (buffer too small for the frame, or frame larger than the channel)",
    ACH_INVALID_NAME: "invalid channel name (1-63 characters of [A-Za-z0-9_.-], not starting with '.')",
    ACH_BAD_SHM_FILE: "not an Ach channel file (bad magic number or too short)",
    ACH_FAILED_SYSCALL: "a system call failed",
    ACH_EAGAIN: "no new frame (stale frames), or the channel lock was busy (ACH_LOCKED)",
    ACH_MISSED_FRAME: "frames were skipped",
    ACH_TIMEOUT: "timed out waiting for a frame",
    ACH_EEXIST: "channel already exists",
    ACH_ENOENT: "channel does not exist",
    ACH_CLOSED: "channel handle is closed",
    ACH_BUG: "internal inconsistency (was the channel re-created while open?)",
    ACH_EINVAL: "invalid argument",
    ACH_CORRUPT: "channel is corrupt (damaged header or index, or a writer died mid-put); run `mds-ach repair`",
    ACH_BAD_HEADER: "bad header",
    ACH_EACCES: "permission denied",
    ACH_CANCELED: "operation canceled",
    ACH_EFAULT: "bad address",
    ACH_EINTR: "interrupted",
    ACH_ENOTSUP: "not supported on this platform",
}

# --- get() options -------------------------------------------------------------------------------
ACH_O_NONBLOCK = 0
ACH_O_FIRST = 0
ACH_O_ABSTIME = 0
ACH_O_WAIT = 1
ACH_O_LAST = 2
ACH_O_COPY = 4
ACH_O_RELTIME = 8

ACH_DEFAULT_FRAME_COUNT = 16
ACH_DEFAULT_FRAME_SIZE = 512

MAGIC = 0xB07511F3
GUARD_HEADER = 0x1A2A3A4A5A6A7A8A
GUARD_INDEX = 0x1B2B3B4B5B6B7B8B
GUARD_DATA = 0x1C2C3C4C5C6C7C8C

SHM_DIR = "/dev/shm"
SHM_PREFIX = "achshm-"
NAME_MAX = 64  # libach: strlen(name) < 64
WAIT_SLICE = 0.1  # s per condvar wait slice (condvar_wait=True), so Ctrl-C / cancel / close are seen promptly
POLL_SLICE = 0.005  # s per futex wait slice: how late a frame from a C writer (no futex wake) can be noticed
IDLE_SLICE = 0.05  # C fast path: s per futex wait slice while every frame comes with a wake-up (fewer idle wakes)
_SHORT_SLICE_FRAMES = 100  # after a frame that came without a wake-up, this many woken frames before IDLE_SLICE
_WAIT_WOKEN, _WAIT_TIMED_OUT = 1, 2  # _achfast.Handle.woken: how the last get's futex wait ended (0: no wait)

CLOCK_REALTIME = 0
CLOCK_MONOTONIC = 1

# glibc constants, identical on x86_64 and aarch64
_PTHREAD_PROCESS_SHARED = 1
_PTHREAD_PRIO_INHERIT = 1
_PTHREAD_MUTEX_ROBUST = 1
_EOWNERDEAD = 130
_ENOTRECOVERABLE = 131
_ETIMEDOUT = 110
_FUTEX_TID_MASK = 0x3FFFFFFF
_FUTEX_WAIT = 0  # shared (no FUTEX_PRIVATE_FLAG): the word lives in a file mapped by several processes
_FUTEX_WAKE = 1
_SYS_FUTEX = {"x86_64": 202, "aarch64": 98}

_U64 = struct.Struct("<Q")
_U64_MAX = 2**64 - 1
_SPIN_SLICE_NS = 10_000_000  # a busy-poll returns to Python this often to see cancel, close and Ctrl-C


def _load_fast() -> ModuleType | None:
    """The optional C extension, unless it is missing or MDS_ACH_PURE_PYTHON is set."""
    if os.environ.get("MDS_ACH_PURE_PYTHON", "") not in ("", "0"):
        return None
    try:
        from mds_ach.ach import _achfast
    except ImportError:
        return None
    return _achfast


_achfast = _load_fast()
FAST_AVAILABLE = _achfast is not None  # the C fast path is built and not disabled
_LOCK_TIMED_OUT = -1  # internal status (not libach's): the mutex was not acquired within lock_timeout
_LOCK_SLICE_NS = 50_000_000  # a busy channel lock is waited for in timed slices this long (Channel._wait_for_lock)
_GONE = -2  # _wait_for_lock: the header changed (e.g. the file was truncated) while waiting for the lock


def _load_guard() -> ModuleType | None:
    """The SIGBUS guard for channel mappings. Both paths use it, so MDS_ACH_PURE_PYTHON does not turn it off."""
    try:
        from mds_ach.ach import _shmguard
    except ImportError:
        return None
    return _shmguard


_shmguard = _load_guard()
GUARD_AVAILABLE = _shmguard is not None  # a truncated channel file cannot kill this process
_NAME_CHARS = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_.-")


def result_string(status: int) -> str:
    """libach's ``ach_result_to_string``: the enum name, ``"ACH_EAGAIN"`` for 5."""
    if 0 <= status < len(_STATUS_NAMES):
        return _STATUS_NAMES[status]
    return f"ACH_UNKNOWN({status})"


def explain(status: int) -> str:
    """A human sentence for a status code."""
    return _EXPLANATIONS.get(status, "unknown status")


class AchException(Exception):  # noqa: N818 - the classic binding's name
    """An Ach call failed. ``status`` is the libach status code; ``str()`` names it and explains it.

    For ``ACH_OVERFLOW`` from ``get`` the exception carries ``frame_size``, the buffer size that is needed.
    """

    def __init__(self, status: int, detail: str = "", *, channel: str | None = None, frame_size: int | None = None):
        self.status = status
        self.detail = detail
        self.channel = channel
        self.frame_size = frame_size
        super().__init__(status)

    @property
    def reason(self) -> str:
        """Status name, explanation and detail, without the channel name."""
        text = f"{result_string(self.status)}: {explain(self.status)}"
        return f"{text}: {self.detail}" if self.detail else text

    def __str__(self) -> str:
        return f"channel '{self.channel}': {self.reason}" if self.channel is not None else self.reason


# --- layout ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Layout:
    """Byte offsets of one architecture's channel file; only the mutex size differs between arches."""

    arch: str
    mutex_size: int

    @property
    def mutex(self) -> int:
        return 216

    @property
    def cond(self) -> int:
        return 216 + self.mutex_size

    @property
    def dirty(self) -> int:
        return 264 + self.mutex_size

    @property
    def last_seq(self) -> int:
        return 272 + self.mutex_size

    @property
    def header_size(self) -> int:
        return 280 + self.mutex_size

    def file_size(self, index_cnt: int, data_size: int) -> int:
        """``sizeof(header) + guard + 24*cnt + guard + data_size + guard``."""
        return self.header_size + 24 * index_cnt + data_size + 24

    def index_offset(self) -> int:
        return self.header_size + 8

    def data_offset(self, index_cnt: int) -> int:
        return self.header_size + 16 + 24 * index_cnt


LAYOUT_X86_64 = Layout("x86_64", 40)
LAYOUT_AARCH64 = Layout("aarch64", 48)
LAYOUTS = {"x86_64": LAYOUT_X86_64, "aarch64": LAYOUT_AARCH64}
_MACHINE_ALIASES = {"amd64": "x86_64", "x86_64": "x86_64", "aarch64": "aarch64", "arm64": "aarch64"}


def native_layout() -> Layout:
    """The layout for this machine (glibc on 64-bit x86 or ARM); other platforms are refused."""
    arch = _MACHINE_ALIASES.get(platform.machine().lower())
    if arch is None or ctypes.sizeof(ctypes.c_void_p) != 8:
        raise AchException(ACH_ENOTSUP, f"no known Ach layout for {platform.machine()} "
                                        f"({8 * ctypes.sizeof(ctypes.c_void_p)}-bit); only x86_64 and aarch64")
    return LAYOUTS[arch]


# Header fields at fixed offsets, in units of u64 (the mmap is 8-aligned).
_Q_LEN = 1
_Q_INDEX_CNT = 11
_Q_DATA_SIZE = 12
_Q_DATA_HEAD = 13
_Q_DATA_FREE = 14
_Q_INDEX_HEAD = 15
_Q_INDEX_FREE = 16
_OFF_NAME = 16
_OFF_CLOCK = 136


def validate_name(name: object) -> str:
    """libach's ``libach_name_ok``: raise ``AchException(ACH_INVALID_NAME)`` with the reason."""
    if not isinstance(name, str):
        raise AchException(ACH_INVALID_NAME, f"channel name must be a str, got {type(name).__name__}")
    if not name:
        raise AchException(ACH_INVALID_NAME, "channel name is empty")
    if len(name) >= NAME_MAX:
        raise AchException(ACH_INVALID_NAME, f"{name[:20]!r}... is {len(name)} characters, at most 63 allowed")
    if name.startswith("."):
        raise AchException(ACH_INVALID_NAME, f"{name!r} starts with '.'")
    bad = sorted({c for c in name if c not in _NAME_CHARS})
    if bad:
        raise AchException(ACH_INVALID_NAME, f"{name!r} contains {''.join(bad)!r}; allowed are [A-Za-z0-9_.-]")
    return name


def shm_path(name: str) -> str:
    """``/dev/shm/achshm-<name>``, the file behind ``shm_open("/achshm-<name>")``."""
    return os.path.join(SHM_DIR, SHM_PREFIX + validate_name(name))


def exists(name: str) -> bool:
    """True when a channel file of that name exists (its contents are not checked)."""
    return os.path.exists(shm_path(name))


def unlink(name: str) -> None:
    """Remove the channel (``shm_unlink``); processes that have it open keep the orphaned memory."""
    path = shm_path(name)
    try:
        os.unlink(path)
    except FileNotFoundError:
        raise AchException(ACH_ENOENT, path, channel=name) from None
    except PermissionError as exc:
        raise AchException(ACH_EACCES, f"{path}: {exc.strerror}", channel=name) from None


# --- read-only parsing (any arch, no locking) ------------------------------------------------------


@dataclass(frozen=True)
class IndexEntry:
    size: int
    offset: int
    seq_num: int


@dataclass
class ChannelImage:
    """A decoded channel file. Parsing takes no lock: use it for inspection, foreign-arch files and tests."""

    layout: Layout
    len: int
    name: str
    index_cnt: int
    data_size: int
    data_head: int
    data_free: int
    index_head: int
    index_free: int
    clock: int
    dirty: int
    last_seq: int
    index: list[IndexEntry]
    data: bytes = field(repr=False)

    @property
    def frame_size(self) -> int:
        """Nominal frame size, as achd reports it."""
        return self.data_size // self.index_cnt

    def frames(self) -> list[tuple[int, bytes]]:
        """Live frames as ``(seq_num, payload)``, oldest first."""
        live = [e for e in self.index if e.seq_num]
        return [(e.seq_num, self.data[e.offset:e.offset + e.size]) for e in sorted(live, key=lambda e: e.seq_num)]

    def newest(self) -> bytes | None:
        frames = self.frames()
        return frames[-1][1] if frames else None


def detect_layout(image: bytes) -> Layout:
    """Pick the arch whose size formula matches the file (magic and guard H decide)."""
    for layout in LAYOUTS.values():
        h = layout.header_size
        if len(image) >= h + 8 and struct.unpack_from("<Q", image, h)[0] == GUARD_HEADER:
            return layout
    raise AchException(ACH_BAD_SHM_FILE, "no header guard where x86_64 or aarch64 libach puts it")


def parse_image(image: bytes | bytearray | memoryview, arch: str | None = None) -> ChannelImage:
    """Decode a whole channel file. Bad magic -> ACH_BAD_SHM_FILE; wrong length or guards -> ACH_CORRUPT."""
    data = bytes(image)
    if len(data) < 4 or struct.unpack_from("<I", data, 0)[0] != MAGIC:
        raise AchException(ACH_BAD_SHM_FILE, "bad magic number")
    layout = LAYOUTS[arch] if arch else detect_layout(data)
    cnt, dsize = _check_geometry(data, layout)
    h = layout.header_size
    fields = struct.unpack_from("<QQQQ", data, 104)
    index = [IndexEntry(*struct.unpack_from("<QQQ", data, h + 8 + 24 * i)) for i in range(cnt)]
    d0 = layout.data_offset(cnt)
    return ChannelImage(
        layout=layout,
        len=struct.unpack_from("<Q", data, 8)[0],
        name=data[_OFF_NAME:_OFF_NAME + 65].split(b"\0", 1)[0].decode("ascii", "replace"),
        index_cnt=cnt,
        data_size=dsize,
        data_head=fields[0],
        data_free=fields[1],
        index_head=fields[2],
        index_free=fields[3],
        clock=struct.unpack_from("<i", data, _OFF_CLOCK)[0],
        dirty=struct.unpack_from("<i", data, layout.dirty)[0],
        last_seq=struct.unpack_from("<Q", data, layout.last_seq)[0],
        index=index,
        data=data[d0:d0 + dsize],
    )


def _check_geometry(data: bytes | memoryview | mmap.mmap, layout: Layout) -> tuple[int, int]:
    """Header length fields, file length and the three guards; raises AchException with the reason. Returns the
    (index_cnt, data_size) it checked: use those, never a second read of the header, which may change meanwhile."""
    h = layout.header_size
    size = len(data)
    if size < h + 24:
        raise AchException(ACH_BAD_SHM_FILE, f"truncated: {size} bytes, an Ach header alone needs {h + 24}")
    length, = struct.unpack_from("<Q", data, 8)
    cnt, dsize = struct.unpack_from("<QQ", data, 88)
    if length != size:
        raise AchException(ACH_CORRUPT, f"header says {length} bytes but the file has {size} (truncated?)")
    expected = layout.file_size(cnt, dsize)
    if cnt == 0 or dsize == 0 or expected != length:
        other = [a.arch for a in LAYOUTS.values() if a is not layout and cnt and a.file_size(cnt, dsize) == length]
        hint = f"; it looks like a {other[0]} file (Ach files are not portable across architectures)" if other else ""
        raise AchException(ACH_CORRUPT, f"inconsistent header: index_cnt={cnt} data_size={dsize} len={length}, "
                                        f"{layout.arch} expects {expected}{hint}")
    guards = (
        (h, GUARD_HEADER, "header"),
        (h + 8 + 24 * cnt, GUARD_INDEX, "index"),
        (h + 16 + 24 * cnt + dsize, GUARD_DATA, "data"),
    )
    for offset, value, what in guards:
        if struct.unpack_from("<Q", data, offset)[0] != value:
            raise AchException(ACH_CORRUPT, f"bad {what} guard at offset {offset}")
    return cnt, dsize


# --- glibc ---------------------------------------------------------------------------------------


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Pthread:
    """The glibc pthread calls Ach needs, with argtypes set once (cached function pointers)."""

    def __init__(self) -> None:
        try:
            libc = ctypes.CDLL("libc.so.6", use_errno=True)
            libc.pthread_mutex_consistent  # noqa: B018 - glibc >= 2.34 has pthread in libc
        except (OSError, AttributeError):
            libc = ctypes.CDLL("libpthread.so.0", use_errno=True)
        vp = [ctypes.c_void_p]
        self.mutex_lock = self._fn(libc.pthread_mutex_lock, vp)
        self.mutex_trylock = self._fn(libc.pthread_mutex_trylock, vp)
        self.mutex_timedlock = self._fn(libc.pthread_mutex_timedlock, [ctypes.c_void_p, ctypes.POINTER(_Timespec)])
        self.mutex_unlock = self._fn(libc.pthread_mutex_unlock, vp)
        self.mutex_consistent = self._fn(libc.pthread_mutex_consistent, vp)
        self.cond_broadcast = self._fn(libc.pthread_cond_broadcast, vp)
        self.cond_timedwait = self._fn(libc.pthread_cond_timedwait,
                                       [ctypes.c_void_p, ctypes.c_void_p, ctypes.POINTER(_Timespec)])
        self.mutex_init = self._fn(libc.pthread_mutex_init, [ctypes.c_void_p, ctypes.c_void_p])
        self.cond_init = self._fn(libc.pthread_cond_init, [ctypes.c_void_p, ctypes.c_void_p])
        self.mutexattr_init = self._fn(libc.pthread_mutexattr_init, vp)
        self.mutexattr_destroy = self._fn(libc.pthread_mutexattr_destroy, vp)
        self.mutexattr_setpshared = self._fn(libc.pthread_mutexattr_setpshared, [ctypes.c_void_p, ctypes.c_int])
        self.mutexattr_setprotocol = self._fn(libc.pthread_mutexattr_setprotocol, [ctypes.c_void_p, ctypes.c_int])
        self.mutexattr_setrobust = self._fn(libc.pthread_mutexattr_setrobust, [ctypes.c_void_p, ctypes.c_int])
        self.condattr_init = self._fn(libc.pthread_condattr_init, vp)
        self.condattr_destroy = self._fn(libc.pthread_condattr_destroy, vp)
        self.condattr_setpshared = self._fn(libc.pthread_condattr_setpshared, [ctypes.c_void_p, ctypes.c_int])
        self.condattr_setclock = self._fn(libc.pthread_condattr_setclock, [ctypes.c_void_p, ctypes.c_int])
        self.syscall = libc.syscall  # variadic: called with explicit ctypes arguments
        self.syscall.restype = ctypes.c_long

    @staticmethod
    def _fn(f, argtypes):
        f.argtypes = argtypes
        f.restype = ctypes.c_int
        return f

    def init_sync(self, mutex_addr: int, cond_addr: int, clock: int) -> None:
        """libach's creation: cond (pshared + clock), then mutex (pshared + PRIO_INHERIT + ROBUST)."""
        cattr = ctypes.create_string_buffer(64)
        _check_zero(self.condattr_init(cattr), "pthread_condattr_init")
        try:
            _check_zero(self.condattr_setpshared(cattr, _PTHREAD_PROCESS_SHARED), "pthread_condattr_setpshared")
            _check_zero(self.condattr_setclock(cattr, clock), "pthread_condattr_setclock")
            _check_zero(self.cond_init(cond_addr, cattr), "pthread_cond_init")
        finally:
            self.condattr_destroy(cattr)
        mattr = ctypes.create_string_buffer(64)
        _check_zero(self.mutexattr_init(mattr), "pthread_mutexattr_init")
        try:
            _check_zero(self.mutexattr_setpshared(mattr, _PTHREAD_PROCESS_SHARED), "pthread_mutexattr_setpshared")
            _check_zero(self.mutexattr_setprotocol(mattr, _PTHREAD_PRIO_INHERIT), "pthread_mutexattr_setprotocol")
            _check_zero(self.mutexattr_setrobust(mattr, _PTHREAD_MUTEX_ROBUST), "pthread_mutexattr_setrobust")
            _check_zero(self.mutex_init(mutex_addr, mattr), "pthread_mutex_init")
        finally:
            self.mutexattr_destroy(mattr)


def _check_zero(r: int, what: str) -> None:
    if r != 0:
        raise AchException(ACH_FAILED_SYSCALL, f"{what}: {os.strerror(r)}")


_pthread: _Pthread | None = None


def _libc() -> _Pthread:
    global _pthread
    if _pthread is None:
        _pthread = _Pthread()
    return _pthread


# --- create ----------------------------------------------------------------------------------------


def create(
    name: str,
    frame_count: int = 0,
    frame_size: int = 0,
    mode: int = 0o660,
    truncate: bool = False,
    clock: int = CLOCK_MONOTONIC,
) -> None:
    """Create channel ``name`` with ``frame_count`` frames of nominal ``frame_size`` bytes (0 = libach default).

    The file is built under a temporary name and linked into place, so no process ever opens a half
    initialised channel. Without ``truncate`` an existing channel gives ``ACH_EEXIST``; with it the old file
    is atomically replaced (processes that still have it open keep the old memory, they are not clobbered).
    ``mode`` is applied exactly (not filtered by the umask). Every page is allocated here (unlike libach, which
    leaves the file sparse): a full ``/dev/shm`` fails now with ``ACH_FAILED_SYSCALL`` saying how many bytes
    were needed, not later with a SIGBUS in the writer.
    """
    validate_name(name)
    count = ACH_DEFAULT_FRAME_COUNT if frame_count == 0 else frame_count
    size = ACH_DEFAULT_FRAME_SIZE if frame_size == 0 else frame_size
    for what, value in (("frame_count", count), ("frame_size", size)):
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise AchException(ACH_EINVAL, f"{what} must be a positive integer, got {value!r}", channel=name)
    if count * size > 1 << 40:
        raise AchException(ACH_EINVAL, f"{count} x {size} bytes is unreasonably large", channel=name)
    layout = native_layout()
    length = layout.file_size(count, count * size)
    path = shm_path(name)
    tmp = os.path.join(SHM_DIR, f".{SHM_PREFIX}{name}.{os.getpid()}.{threading.get_native_id()}.tmp")
    try:
        fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
    except OSError as exc:
        raise _os_error(exc, name, tmp) from None
    try:
        try:
            os.ftruncate(fd, length)
            _reserve(fd, length, name, "create")
            _initialise(fd, length, layout, name, count, count * size, clock)
            os.fchmod(fd, mode)
            if truncate:
                os.replace(tmp, path)
            else:
                os.link(tmp, path)
        except FileExistsError:
            raise AchException(ACH_EEXIST, path, channel=name) from None
        except OSError as exc:
            raise _os_error(exc, name, path) from None
    finally:
        os.close(fd)
        if os.path.exists(tmp):
            os.unlink(tmp)


_create = create  # Channel.__init__ has a parameter called ``create``


def _initialise(fd: int, length: int, layout: Layout, name: str, count: int, dsize: int, clock: int) -> None:
    """Fill a zeroed file the way libach's ``ach_create`` does: sync objects, counters, guards, magic, name."""
    mm = mmap.mmap(fd, length)
    try:
        anchor = ctypes.c_char.from_buffer(mm)
        try:
            base = ctypes.addressof(anchor)
            _libc().init_sync(base + layout.mutex, base + layout.cond, clock)
        finally:
            del anchor
        h = layout.header_size
        struct.pack_into("<IxxxxQ", mm, 0, MAGIC, length)
        mm[_OFF_NAME:_OFF_NAME + len(name)] = name.encode("ascii")
        struct.pack_into("<QQQQQQ", mm, 88, count, dsize, 0, dsize, 0, count)
        struct.pack_into("<i", mm, _OFF_CLOCK, clock)
        struct.pack_into("<Q", mm, h, GUARD_HEADER)
        struct.pack_into("<Q", mm, h + 8 + 24 * count, GUARD_INDEX)
        struct.pack_into("<Q", mm, h + 16 + 24 * count + dsize, GUARD_DATA)
    finally:
        mm.close()


def _reserve(fd: int, length: int, name: str, what: str) -> None:
    """Allocate every page of the channel file now (``posix_fallocate``; a no-op for pages that exist), so a full
    ``/dev/shm`` is a clear error here and not a SIGBUS in whichever process first writes a fresh page later."""
    try:
        os.posix_fallocate(fd, 0, length)
    except OSError as exc:
        if exc.errno in (errno.EOPNOTSUPP, errno.ENODEV):  # not tmpfs: that file system reserves nothing
            return
        if exc.errno not in (errno.ENOSPC, errno.ENOMEM, errno.EFBIG, errno.EDQUOT):
            raise _os_error(exc, name, shm_path(name)) from None
        try:
            vfs = os.statvfs(SHM_DIR)
            room = f"{vfs.f_bavail * vfs.f_frsize} of {vfs.f_blocks * vfs.f_frsize} bytes free"
        except OSError:
            room = "free space unknown"
        raise AchException(ACH_FAILED_SYSCALL, f"cannot {what} it: {length} bytes of channel memory cannot be "
                                               f"reserved in {SHM_DIR} ({exc.strerror}; {room}); see `df -h "
                                               f"{SHM_DIR}`, remove unused channels (`mds-ach rm`) or enlarge the "
                                               f"tmpfs (`mount -o remount,size=256M {SHM_DIR}`)",
                           channel=name) from None


class MappingGuard:
    """Keeps a SIGBUS in one mapped channel file from killing the process (see ``mds_ach/ach/_shmguard.c``).

    ``lost`` turns true when the file vanished under the mapping (truncated: the guard grows it back, so the
    vanished part reads as zeros) or a page of it could not be allocated (private zeros from there on); every
    mapping of a truncated file in this process is marked. ``release()`` before unmapping: a lost mapping must
    stay mapped (a robust-mutex list may point into it) and its file open (the guard still watches it through
    that descriptor), so both are kept, and ``release`` says so. Without the compiled guard nothing is guarded
    and ``lost`` stays false.
    """

    _kept: list[tuple[mmap.mmap, int]] = []  # lost mappings and their files, never unmapped or closed

    def __init__(self, mm: mmap.mmap, fd: int) -> None:
        self._slot = -1
        self._flag = ctypes.c_int(0)
        if _shmguard is not None:
            anchor = ctypes.c_char.from_buffer(mm)
            try:
                address = ctypes.addressof(anchor)
            finally:
                del anchor
            self._slot = _shmguard.watch(address, len(mm), fd)
            self._flag = ctypes.c_int.from_address(_shmguard.flag_address(self._slot))

    @property
    def flag(self) -> ctypes.c_int:
        """The C int the SIGBUS handler sets (0: fine); ``flag.value`` is the cheapest way to look."""
        return self._flag

    @property
    def flag_address(self) -> int:
        """Address of ``flag`` for the C fast path; 0 without the guard."""
        return 0 if self._slot < 0 else ctypes.addressof(self._flag)

    @property
    def lost(self) -> bool:
        return self._flag.value != 0

    def reason(self, name: str, length: int) -> str:
        """What happened to a lost mapping, and what to do about it."""
        size = _shmguard.state(self._slot)[1] if self._slot >= 0 else -1
        path = shm_path(name)
        if self._flag.value == getattr(_shmguard, "LOST_TRUNCATED", 1):
            what = f"{path} shrank to {size} bytes while this process had its {length} bytes mapped (truncated)"
        else:
            what = (f"a page of {path} could not be allocated when it was first written (is {SHM_DIR} full? "
                    f"`df -h {SHM_DIR}`)")
        return (f"{what}; this handle stays unusable: run `mds-ach repair {name}` (it re-creates the channel), "
                "then re-open the channel (restart this node)")

    def release(self, mm: mmap.mmap, fd: int) -> bool:
        """Stop guarding before ``mm`` is unmapped and ``fd`` closed. False when the mapping is lost: both are
        kept, close neither."""
        if self._slot < 0:
            return True
        if self.lost:
            MappingGuard._kept.append((mm, fd))
            return False
        _shmguard.forget(self._slot)
        self._slot = -1
        self._flag = ctypes.c_int(0)
        return True


def _os_error(exc: OSError, name: str, path: str) -> AchException:
    if exc.errno == errno.ENOENT:
        return AchException(ACH_ENOENT, path, channel=name)
    if exc.errno in (errno.EACCES, errno.EPERM):
        return AchException(ACH_EACCES, f"{path}: {exc.strerror}", channel=name)
    if exc.errno == errno.EEXIST:
        return AchException(ACH_EEXIST, path, channel=name)
    return AchException(ACH_FAILED_SYSCALL, f"{path}: {exc.strerror}", channel=name)


# --- channel handle --------------------------------------------------------------------------------


def _byte_view(buf: object, writable: bool) -> memoryview:
    """A flat unsigned-byte view of any contiguous buffer (bytes, bytearray, memoryview, ctypes object)."""
    if type(buf) is memoryview:
        mv = buf
    else:
        try:
            mv = memoryview(buf)
        except TypeError:
            raise TypeError(f"Ach frames are bytes-like objects (bytes, bytearray, memoryview, ctypes structure), "
                            f"got {type(buf).__name__}") from None
    if writable and mv.readonly:
        raise TypeError(f"get() needs a writable buffer (bytearray, memoryview, ctypes object), "
                        f"got read-only {type(buf).__name__}")
    if mv.format == "B" and mv.ndim == 1:
        return mv
    try:
        return mv.cast("B")
    except TypeError:
        if not mv.c_contiguous:
            raise TypeError("Ach buffers must be contiguous") from None
        if mv.readonly:
            return memoryview(mv.tobytes())
        return memoryview((ctypes.c_ubyte * mv.nbytes).from_buffer(buf)).cast("B")


class Channel:
    """An open Ach channel: one per reader/writer. Reader state (last seen frame) lives in this handle.

    ``Channel(name)`` opens the channel, creating it first with ``frame_count`` x ``frame_size`` (0 means the
    libach defaults 16 x 512) when it does not exist and ``create`` is true, like the classic binding.
    A handle may be shared between threads; ``close()`` waits for calls in progress to leave.
    ``condvar_wait`` selects libach's condvar waits instead of the crash-safe futex waits (module docstring);
    such handles use the pure-Python path. ``fast=False`` refuses the C fast path for this handle.
    ``lock_timeout`` (seconds, None = no bound) bounds the wait for the channel mutex in ``put``, ``get`` and
    ``poll`` (``put`` and ``get`` can override it per call); a call that could not get the lock in time gives up
    without touching the channel and reports ACH_LOCKED (``put``, ``get`` and ``poll`` raise it, ``put_status``
    and ``get_status`` return it). ``flush`` always waits: a reader must not keep old frames because of a
    busy lock.
    """

    def __init__(self, name: str, frame_count: int = 0, frame_size: int = 0, *, create: bool = True,
                 mode: int = 0o660, condvar_wait: bool = False, fast: bool = True, lock_timeout: float | None = None):
        self.name = validate_name(name)
        self._condvar_wait = condvar_wait
        self._want_fast = fast
        self._closed = True  # until fully open, so __del__ / close() are harmless
        self.lock_timeout = lock_timeout
        try:
            self._open()
        except AchException as exc:
            if exc.status != ACH_ENOENT or not create:
                raise
            try:
                _create(name, frame_count, frame_size, mode=mode)
            except AchException as exc2:
                if exc2.status != ACH_EEXIST:  # lost a creation race: fine, open theirs
                    raise
            self._open()

    # -- open / close ------------------------------------------------------------------------------

    def _open(self) -> None:
        """libach ``ach_open``: map the whole file, check magic/length/guards, reset the reader state. Also reserve
        the file's memory and guard the mapping (module docstring)."""
        layout = native_layout()
        path = shm_path(self.name)
        try:
            fd = os.open(path, os.O_RDWR | os.O_CLOEXEC)
        except OSError as exc:
            raise _os_error(exc, self.name, path) from None
        try:
            size = os.fstat(fd).st_size
            head = os.pread(fd, 4, 0)
            if len(head) < 4 or struct.unpack("<I", head)[0] != MAGIC:
                raise AchException(ACH_BAD_SHM_FILE, f"{path}: bad magic number ({size} bytes)", channel=self.name)
            if size < layout.header_size + 24:
                raise AchException(ACH_BAD_SHM_FILE, f"{path}: truncated, {size} bytes", channel=self.name)
            _reserve(fd, size, self.name, "open")  # a sparse file (made by libach's ach mk) gets its pages now
            mm = mmap.mmap(fd, size)
        except BaseException:
            os.close(fd)
            raise
        guard = MappingGuard(mm, fd)  # before the first access: the file may shrink at any time
        try:
            cnt, dsize = _check_geometry(mm, layout)
            if guard.lost:
                raise AchException(ACH_CORRUPT, guard.reason(self.name, size))
        except AchException as exc:
            if guard.release(mm, fd):
                mm.close()
                os.close(fd)
            exc.channel = self.name
            raise
        self._layout = layout
        self._fd = fd
        self._mm = mm
        self._guard = guard
        self._lost = guard.flag  # .value != 0: the file vanished under the mapping
        self._anchor = ctypes.c_char.from_buffer(mm)
        base = ctypes.addressof(self._anchor)
        self._mutex = ctypes.c_void_p(base + layout.mutex)
        self._cond = ctypes.c_void_p(base + layout.cond)
        self._mv = memoryview(mm)
        self._q = self._mv[: size - size % 8].cast("Q")
        self._i32 = self._mv[: size - size % 4].cast("i")
        h = layout.header_size
        self._len = size
        self._cnt = cnt
        self._dsize = dsize
        self._ix = (h + 8) // 8  # u64 index of index[0].size
        self._d0 = h + 16 + 24 * cnt  # byte offset of the data ring
        self._qg_h = h // 8
        self._qg_i = (h + 8 + 24 * cnt) // 8
        self._off_g_d = h + 16 + 24 * cnt + dsize  # may be unaligned
        self._q_last = layout.last_seq // 8
        self._i_dirty = layout.dirty // 4
        self._i_lock = layout.mutex // 4
        self._clock = self._i32[_OFF_CLOCK // 4]
        self._fn = _libc()
        self._mutex_lock = self._fn.mutex_lock  # cached: attribute lookups show up on the hot path
        self._mutex_trylock = self._fn.mutex_trylock
        self._mutex_unlock = self._fn.mutex_unlock
        self._cond_broadcast = self._fn.cond_broadcast
        sys_futex = ctypes.c_long(_SYS_FUTEX[layout.arch])
        last_seq_word = ctypes.c_void_p(base + layout.last_seq)  # low 32 bits of last_seq (little-endian)
        self._futex_wait_args = (sys_futex, last_seq_word, ctypes.c_int(_FUTEX_WAIT))
        self._futex_wake_args = (sys_futex, last_seq_word, ctypes.c_int(_FUTEX_WAKE), ctypes.c_int(0x7FFFFFFF))
        self._syscall = self._fn.syscall
        # reader state (libach ach_open): seq_num = 0, next_index = 1; kept in the C handle when there is one
        self._seq = 0
        self._next = 1
        self._fast = None
        self._short_slices = 0  # > 0: a writer that does not wake the futex was seen; wait in POLL_SLICE slices
        if _achfast is not None and self._want_fast and not self._condvar_wait:
            try:
                self._fast = _achfast.Handle(base, layout.mutex, layout.cond, layout.dirty, layout.last_seq,
                                             layout.header_size, cnt, dsize, size, guard.flag_address)
            except ValueError:  # a libc whose mutex size differs from the layout: stay in Python
                self._fast = None
        self._cancel = False
        self._active: list[int] = []
        self._release_lock = threading.Lock()
        self._released = False
        self._closed = False

    def close(self) -> None:
        """Unmap and close. Calls in progress in other threads are woken and finish first (or later, in the
        background: the last one to leave releases the mapping)."""
        if self._closed:
            return
        self._active.append(1)  # keep the mapping while we wake the others: a woken waiter may leave at once
        try:
            self._closed = True
            if len(self._active) > 1:
                self._wake_all()  # waiters see _closed at once (or within one slice at worst)
        finally:
            self._active.pop()
        deadline = time.monotonic() + 1.0
        while self._active and time.monotonic() < deadline:
            time.sleep(0.001)
        if not self._active:  # otherwise (e.g. called from a signal handler on the waiting thread) _leave() does it
            self._release()

    def _release(self) -> None:
        with self._release_lock:
            if self._released:
                return
            self._released = True
        if self._fast is not None:
            self._fast.detach()
        self._q.release()
        self._i32.release()
        self._mv.release()
        del self._anchor
        if self._guard.release(self._mm, self._fd):  # a lost mapping stays mapped (MappingGuard)
            self._mm.close()
            os.close(self._fd)

    def __enter__(self) -> Channel:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            if not self._closed:
                self.close()
        except Exception:  # interpreter shutdown: nothing sensible left to do
            pass

    def __repr__(self) -> str:
        state = "closed" if self._closed else f"{self._cnt} x {self._dsize // self._cnt} B"
        return f"<ach.Channel {self.name!r} {state}>"

    def _enter(self) -> None:
        """Register a call in progress (list append/pop are atomic under the GIL), then check for close."""
        self._active.append(1)
        if self._closed:
            self._leave()
            raise AchException(ACH_CLOSED, channel=self.name)

    def _leave(self) -> None:
        self._active.pop()
        if self._closed and not self._active:
            self._release()

    # -- properties --------------------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def frame_count(self) -> int:
        return self._cnt

    @property
    def data_size(self) -> int:
        """Largest frame the channel accepts (the whole data ring)."""
        return self._dsize

    @property
    def frame_size(self) -> int:
        """Nominal frame size given at creation (data_size / frame_count)."""
        return self._dsize // self._cnt

    @property
    def seq_num(self) -> int:
        """Sequence number of the last frame this handle read."""
        return self._seq if self._fast is None else self._fast.seq

    @property
    def next_index(self) -> int:
        return self._next if self._fast is None else self._fast.next

    @property
    def condvar_wait(self) -> bool:
        """Waits happen in the channel's condvar, exactly like libach (set at open)."""
        return self._condvar_wait

    @property
    def fast(self) -> bool:
        """This handle's put/get run in the C fast path (``mds_ach.ach._achfast``)."""
        return self._fast is not None

    @property
    def lost(self) -> bool:
        """The channel file vanished under this handle's mapping (truncated): every call reports ACH_CORRUPT."""
        return not self._closed and self._lost.value != 0

    @property
    def lock_timeout(self) -> float | None:
        """Seconds this handle waits at most for the channel mutex (None: as long as it takes)."""
        return self._lock_timeout

    @lock_timeout.setter
    def lock_timeout(self, value: float | None) -> None:
        self._lock_ns = _lock_ns(value)
        self._lock_timeout = None if self._lock_ns < 0 else value

    @property
    def last_seq(self) -> int:
        """Sequence number of the newest frame in the channel (read without the lock; 0 = empty)."""
        self._enter()
        try:
            return self._q[self._q_last]
        finally:
            self._leave()

    @property
    def layout(self) -> Layout:
        return self._layout

    # -- checks ------------------------------------------------------------------------------------

    def _header_ok(self) -> bool:
        """libach ``check_guards`` plus the geometry validated at open (magic, len, index_cnt, data_size)."""
        q = self._q
        return (q[self._qg_h] == GUARD_HEADER and q[self._qg_i] == GUARD_INDEX
                and _U64.unpack_from(self._mv, self._off_g_d)[0] == GUARD_DATA and q[0] & 0xFFFFFFFF == MAGIC
                and q[_Q_LEN] == self._len and q[_Q_INDEX_CNT] == self._cnt and q[_Q_DATA_SIZE] == self._dsize)

    def _counters_ok(self, index_head: int, index_free: int, data_head: int, data_free: int) -> bool:
        """The ring counters (read once by the caller, under the lock) are in range."""
        return index_head < self._cnt and index_free <= self._cnt and data_head < self._dsize \
            and data_free <= self._dsize

    def _corrupt_detail(self) -> str:
        """Why this handle's calls report ACH_CORRUPT, and the remedy (for the exception; not on the hot path)."""
        if self._lost.value:
            return self._guard.reason(self.name, self._len)
        repair = f"run `mds-ach repair {self.name}`"
        if not self._header_ok():
            try:
                _check_geometry(self._mm, self._layout)
            except AchException as exc:
                problem = exc.detail
            else:
                problem = (f"header changed under this handle (len/index_cnt/data_size now {self._q[_Q_LEN]}/"
                           f"{self._q[_Q_INDEX_CNT]}/{self._q[_Q_DATA_SIZE]}, opened as {self._len}/{self._cnt}/"
                           f"{self._dsize})")
            return f"{problem}; {repair} (it re-creates a channel with a damaged header), then re-open it"
        if self._i32[self._i_dirty]:
            return f"a writer died inside a put (dirty flag set); {repair}"
        q = self._q
        counters = (q[_Q_INDEX_HEAD], q[_Q_INDEX_FREE], q[_Q_DATA_HEAD], q[_Q_DATA_FREE])
        if not self._counters_ok(*counters):
            return (f"ring counters out of range (index_head/index_free {counters[0]}/{counters[1]} for "
                    f"{self._cnt} slots, data_head/data_free {counters[2]}/{counters[3]} for {self._dsize} "
                    f"bytes); {repair}")
        return f"damaged index entry; {repair}"

    def _error(self, status: int, detail: str = "", size: int | None = None, lock_ns: int = -1) -> AchException:
        """The exception for a failed call, with what happened and what to do."""
        if status == _LOCK_TIMED_OUT:
            owner = self._i32[self._i_lock] & _FUTEX_TID_MASK if not self._closed else 0
            return AchException(ACH_LOCKED, f"lock held by another process (thread {owner}) for > {lock_ns / 1e6:g} "
                                            "ms; the call gave up without touching the channel", channel=self.name)
        if status == ACH_CORRUPT and not detail and not self._closed:
            try:
                detail = self._corrupt_detail()
            except (ValueError, AchException):  # closed by another thread meanwhile: the status says enough
                detail = ""
        return AchException(status, detail, channel=self.name, frame_size=size)

    # -- locking -----------------------------------------------------------------------------------

    def _wait_for_lock(self, lock_ns: int) -> int:
        """The channel mutex is busy: wait for it in timed slices (GIL released), at most ``lock_ns`` (< 0: as long
        as it takes). Between slices the header is looked at again, because a waiter parked in the kernel never
        notices that the file was truncated under it (the owner can then never release the lock; see
        ``_shmguard.c``). Returns the pthread result, ETIMEDOUT when it gave up, or _GONE. ``pthread_mutex_timedlock``
        takes a CLOCK_REALTIME deadline (POSIX); a clock step only lengthens or shortens one slice."""
        end = None if lock_ns < 0 else time.monotonic_ns() + lock_ns
        ts = _Timespec()
        ts_ref = ctypes.byref(ts)
        while True:
            span = _LOCK_SLICE_NS if end is None else max(0, min(_LOCK_SLICE_NS, end - time.monotonic_ns()))
            ts.tv_sec, ts.tv_nsec = divmod(time.clock_gettime_ns(time.CLOCK_REALTIME) + span, 1_000_000_000)
            r = self._fn.mutex_timedlock(self._mutex, ts_ref)
            if r != _ETIMEDOUT:
                return r
            if self._lost.value or not self._header_ok():
                return _GONE
            if end is not None and time.monotonic_ns() >= end:
                return _ETIMEDOUT

    def _lock(self, lock_ns: int = -1) -> int:
        """libach ``chan_lock``: lock, recover a dead owner, then refuse a dirty channel."""
        r = self._mutex_trylock(self._mutex)
        if r or self._i32[self._i_dirty]:
            return self._lock_slow(r, lock_ns)
        return ACH_OK

    def _lock_slow(self, r: int, lock_ns: int) -> int:
        """After ``pthread_mutex_trylock`` returned ``r``: wait if busy; EOWNERDEAD -> consistent; the dirty check."""
        if r == errno.EBUSY:
            r = self._wait_for_lock(lock_ns)
        if r == _EOWNERDEAD:
            self._fn.mutex_consistent(self._mutex)
        elif r == _ETIMEDOUT:
            return _LOCK_TIMED_OUT
        elif r in (_ENOTRECOVERABLE, _GONE):
            return ACH_CORRUPT
        elif r:
            return ACH_FAILED_SYSCALL
        if self._i32[self._i_dirty]:
            self._mutex_unlock(self._mutex)
            return ACH_CORRUPT
        return ACH_OK

    def _owned(self) -> bool:
        """True when the PI futex word names this thread as owner (the kernel's view, always accurate)."""
        return self._i32[self._i_lock] & _FUTEX_TID_MASK == threading.get_native_id()

    def _unlock_if_owned(self) -> None:
        if self._owned():
            self._mutex_unlock(self._mutex)

    def _wake_all(self) -> None:
        """Wake every waiter of this channel in every process: futex waiters (this module) and condvar waiters
        (C libach, ``condvar_wait=True``). Called after the unlock, like libach's broadcast."""
        self._syscall(*self._futex_wake_args)
        self._cond_broadcast(self._cond)

    def _wait(self, deadline: float | None, lock_ns: int) -> int:
        """Holding the lock, wait for a frame newer than ``seq_num``. Returns with the lock held on OK / TIMEOUT /
        CANCELED, released on CORRUPT / FAILED_SYSCALL / a lock timeout (``lock_ns`` bounds each re-lock after a
        futex wait; a condvar wait re-locks inside glibc, unbounded)."""
        q = self._q
        ql = self._q_last
        ts = _Timespec()  # per call: threads sharing a handle may wait at the same time
        ts_ref = ctypes.byref(ts)  # the variadic syscall() needs the pointer spelled out
        while True:
            if self._cancel or self._closed:
                return ACH_CANCELED
            if self._lost.value:  # the file was truncated while we waited: nothing will ever come
                self._mutex_unlock(self._mutex)
                return ACH_CORRUPT
            last = q[ql]
            if self._seq != last:
                return ACH_OK
            now = time.clock_gettime(self._clock)
            if deadline is not None and now >= deadline:
                return ACH_TIMEOUT
            if self.condvar_wait:
                end = now + WAIT_SLICE if deadline is None or deadline > now + WAIT_SLICE else deadline
                sec = math.floor(end)
                ts.tv_sec = sec
                ts.tv_nsec = min(int((end - sec) * 1e9), 999_999_999)
                r = self._fn.cond_timedwait(self._cond, self._mutex, ts)  # returns holding the mutex
                if r == _ETIMEDOUT:
                    r = 0
            else:
                # Sleep on the last_seq word without the lock. FUTEX_WAIT returns at once if a put has changed it
                # since we read it under the lock, so no wake-up is lost. A dead sleeper leaves no state behind.
                span = POLL_SLICE if deadline is None or deadline - now > POLL_SLICE else deadline - now
                ts.tv_sec, ts.tv_nsec = divmod(int(span * 1e9), 1_000_000_000)
                self._mutex_unlock(self._mutex)
                self._syscall(*self._futex_wait_args, ctypes.c_uint32(last & 0xFFFFFFFF), ts_ref, None, 0)
                r = self._mutex_trylock(self._mutex)
                if r == errno.EBUSY:
                    r = self._wait_for_lock(lock_ns)
                if r == _ETIMEDOUT:
                    return _LOCK_TIMED_OUT
            if r == _EOWNERDEAD:
                self._fn.mutex_consistent(self._mutex)
            elif r:
                self._unlock_if_owned()
                return ACH_CORRUPT if r in (_ENOTRECOVERABLE, _GONE) else ACH_FAILED_SYSCALL
            if self._i32[self._i_dirty]:
                self._mutex_unlock(self._mutex)
                return ACH_CORRUPT

    # -- put ---------------------------------------------------------------------------------------

    def put(self, buf: object, lock_timeout: float | None = None) -> None:
        """Write one frame (bytes, bytearray, memoryview or ctypes object). Raises AchException on any
        non-OK status (classic binding), e.g. ACH_OVERFLOW when the frame is larger than the channel, ACH_LOCKED
        when the mutex was not acquired within ``lock_timeout`` seconds (None: this handle's ``lock_timeout``)."""
        lock_ns = self._lock_ns if lock_timeout is None else _lock_ns(lock_timeout)
        r = self._put_fast(buf, lock_ns) if self._fast is not None else self._put(_byte_view(buf, False), lock_ns)
        if r:
            detail = f"{_byte_view(buf, False).nbytes} bytes > data_size {self._dsize}" if r == ACH_OVERFLOW else ""
            raise self._error(r, detail, lock_ns=lock_ns)

    def put_status(self, buf: object, lock_timeout: float | None = None) -> int:
        """Like ``put`` but returns the libach status instead of raising (ACH_LOCKED for a lock timeout)."""
        lock_ns = self._lock_ns if lock_timeout is None else _lock_ns(lock_timeout)
        r = self._put_fast(buf, lock_ns) if self._fast is not None else self._put(_byte_view(buf, False), lock_ns)
        return ACH_LOCKED if r == _LOCK_TIMED_OUT else r

    def _put_fast(self, buf: object, lock_ns: int) -> int:
        active = self._active
        active.append(1)
        try:
            if self._closed:
                raise AchException(ACH_CLOSED, channel=self.name)
            try:
                return self._fast.put(buf, lock_ns)
            except (TypeError, BufferError):  # not a plain contiguous buffer: convert it, or say what is wrong
                return self._fast.put(_byte_view(buf, False), lock_ns)
        finally:
            active.pop()
            if self._closed and not active:
                self._release()

    def _put(self, src: memoryview, lock_ns: int = -1) -> int:
        n = src.nbytes
        active = self._active
        active.append(1)  # inlined _enter(): this is the hot path
        try:
            if self._closed:
                raise AchException(ACH_CLOSED, channel=self.name)
            if n == 0:
                return ACH_EINVAL
            if not self._header_ok():
                return ACH_CORRUPT
            if n > self._dsize:
                return ACH_OVERFLOW
            mutex = self._mutex
            try:
                r = self._mutex_trylock(mutex)
                if r or self._i32[self._i_dirty]:
                    r = self._lock_slow(r, lock_ns)
                    if r:
                        return r
                r = self._write_locked(src, n)
                self._mutex_unlock(mutex)
            except BaseException:
                # Interrupted while holding the lock: release it. If the update was half done, dirty stays 1 and
                # the channel reads as CORRUPT everywhere -- exactly what libach does when a writer dies mid-put.
                self._unlock_if_owned()
                self._wake_all()
                raise
            self._wake_all()
            return ACH_CORRUPT if self._lost.value else r
        finally:
            active.pop()
            if self._closed and not active:
                self._release()

    def _write_locked(self, src: memoryview, n: int) -> int:
        """libach ``ach_put`` steps 1-7, literally (see ach-format.md section 4). Caller holds the lock. Every value
        read from the file is read once and checked before use. Returns with dirty = 0, except when an index entry
        turns out damaged half-way: ACH_CORRUPT with dirty = 1, so every client sees the channel corrupt until
        ``mds-ach repair`` (as after a writer died mid-put). Damaged counters are refused before any write."""
        q = self._q
        index_head = q[_Q_INDEX_HEAD]
        index_free = q[_Q_INDEX_FREE]
        data_head = q[_Q_DATA_HEAD]
        data_free = q[_Q_DATA_FREE]
        last = q[self._q_last]
        cnt, dsize = self._cnt, self._dsize
        if index_head >= cnt or index_free > cnt or data_head >= dsize or data_free > dsize or last == _U64_MAX:
            return ACH_CORRUPT  # (_counters_ok inlined; a last_seq that cannot be incremented is damaged too)
        self._i32[self._i_dirty] = 1
        ix = self._ix
        slot = index_head
        if index_free == 0:  # index full: drop the oldest frame, which sits in our slot
            e = ix + 3 * index_head
            size, offset, seq = q[e], q[e + 1], q[e + 2]
            if not (size and offset < dsize and size <= dsize - offset and seq and seq <= last):
                return ACH_CORRUPT
            data_free += q[e]
            index_free += 1
            q[e] = q[e + 1] = q[e + 2] = 0
        if dsize - data_head < n:  # tail wrap: drop the frames after data_head, restart at offset 0
            i = (index_head + index_free) % cnt
            while q[ix + 3 * i + 1] > data_head:
                e = ix + 3 * i
                size, offset, seq = q[e], q[e + 1], q[e + 2]
                if not (size and offset < dsize and size <= dsize - offset and seq and seq <= last):
                    return ACH_CORRUPT
                data_free += size
                index_free += 1
                q[e] = q[e + 1] = q[e + 2] = 0
                i = (i + 1) % cnt
            if i == index_head:
                data_free = dsize
            else:
                e = ix + 3 * ((index_head + index_free) % cnt)
                size, offset, seq = q[e], q[e + 1], q[e + 2]
                if not (size and offset < dsize and size <= dsize - offset and seq and seq <= last):
                    return ACH_CORRUPT
                data_free = offset
            data_head = 0
        i = (index_head + index_free) % cnt
        while data_free < n:  # clear overlap with the oldest frames
            if i == index_head:
                data_free = dsize
            else:
                e = ix + 3 * i
                size, offset, seq = q[e], q[e + 1], q[e + 2]
                if not (size and offset < dsize and size <= dsize - offset and seq and seq <= last):
                    return ACH_CORRUPT
                data_free += size
                index_free += 1
                q[e] = q[e + 1] = q[e + 2] = 0
            i = (i + 1) % cnt
        if dsize - data_head < n:  # libach's sanity check; cannot happen
            q[_Q_DATA_HEAD], q[_Q_DATA_FREE], q[_Q_INDEX_FREE] = data_head, data_free, index_free
            self._i32[self._i_dirty] = 0
            return ACH_BUG
        start = self._d0 + data_head
        self._mv[start:start + n] = src
        seq = last + 1
        q[self._q_last] = seq
        e = ix + 3 * slot
        q[e] = n
        q[e + 1] = data_head
        q[e + 2] = seq
        q[_Q_DATA_HEAD] = (data_head + n) % dsize
        q[_Q_DATA_FREE] = data_free - n
        q[_Q_INDEX_HEAD] = (index_head + 1) % cnt
        q[_Q_INDEX_FREE] = index_free - 1
        self._i32[self._i_dirty] = 0
        return ACH_OK

    # -- get ---------------------------------------------------------------------------------------

    def get(self, buf: object, wait: bool = False, last: bool = False, timeout: float | None = None,
            copy: bool = False, lock_timeout: float | None = None) -> tuple[int, int]:
        """Read one frame into ``buf`` (bytearray, memoryview or ctypes object), in place.

        Default: the next frame in order. ``last``: the newest frame (older ones are skipped). ``copy``: return
        the last frame again even if already seen. ``wait``: block until there is a frame this handle has not
        seen; ``timeout`` (seconds, relative, only with ``wait``) bounds the wait, None = forever.
        ``lock_timeout`` (seconds; None: this handle's ``lock_timeout``) bounds each wait for the channel mutex.

        Returns ``(status, frame_size)`` for ACH_OK, ACH_MISSED_FRAME (data returned, frames were skipped),
        ACH_STALE_FRAMES (nothing new, frame_size 0), ACH_TIMEOUT and ACH_CANCELED. Raises AchException for
        ACH_OVERFLOW (``exc.frame_size`` = needed size; the frame stays unread), for ACH_LOCKED (the mutex was
        not acquired in time; nothing was read) and for every error.
        """
        options = (ACH_O_WAIT if wait else 0) | (ACH_O_LAST if last else 0) | (ACH_O_COPY if copy else 0)
        lock_ns = self._lock_ns if lock_timeout is None else _lock_ns(lock_timeout)
        status, size = self._get_any(buf, options, timeout, lock_ns)
        if status in (ACH_OK, ACH_MISSED_FRAME, ACH_STALE_FRAMES, ACH_TIMEOUT, ACH_CANCELED):
            return status, size
        if status == ACH_OVERFLOW:
            raise self._error(status, f"frame is {size} bytes, buffer holds {_byte_view(buf, True).nbytes}", size)
        raise self._error(status, lock_ns=lock_ns)

    def get_status(self, buf: object, options: int = 0, timeout: float | None = None,
                   lock_timeout: float | None = None) -> tuple[int, int]:
        """libach ``ach_get`` with ACH_O_* ``options``; never raises for a status. ``timeout`` is relative
        seconds (used with ACH_O_WAIT). Returns ``(status, frame_size)``; frame_size is the needed size on
        ACH_OVERFLOW and 0 when no frame was looked at. A lock timeout returns ACH_LOCKED, which equals
        ACH_STALE_FRAMES as in libach's enum: use ``get`` (it raises for it) to tell them apart."""
        lock_ns = self._lock_ns if lock_timeout is None else _lock_ns(lock_timeout)
        status, size = self._get_any(buf, options, timeout, lock_ns)
        return (ACH_LOCKED, 0) if status == _LOCK_TIMED_OUT else (status, size)

    def _get_any(self, buf: object, options: int, timeout: float | None, lock_ns: int) -> tuple[int, int]:
        deadline = None
        if options & ACH_O_WAIT and timeout is not None:
            if timeout != timeout:
                raise ValueError("timeout is NaN")
            if timeout != math.inf:
                deadline = time.clock_gettime(self._clock) + max(0.0, timeout)
        if self._fast is not None:
            return self._get_fast(buf, options, deadline, lock_ns)
        return self._get(_byte_view(buf, True), options, deadline, lock_ns)

    def _slice(self, deadline: float | None) -> tuple[int, bool]:
        """Nanoseconds of the next wait slice, and whether it is the last one before the deadline.

        Python and C-fast-path writers wake waiting readers, so a reader only needs to look again now and then
        (IDLE_SLICE) for cancel and close. Once a frame has turned up without a wake-up (a C libach writer, which
        only broadcasts the condvar) the reader looks every POLL_SLICE, until that many woken frames later."""
        full = int((POLL_SLICE if self._short_slices else IDLE_SLICE) * 1e9)
        if deadline is None:
            return full, False
        left = int((deadline - time.clock_gettime(self._clock)) * 1e9)
        return (full, False) if left > full else (max(0, left), True)

    def _get_fast(self, buf: object, options: int, deadline: float | None, lock_ns: int = -1) -> tuple[int, int]:
        """``_get`` through the C handle: one call per frame; waits in GIL-free futex slices."""
        active = self._active
        active.append(1)
        try:
            if self._closed:
                raise AchException(ACH_CLOSED, channel=self.name)
            if self._cancel:
                return ACH_CANCELED, 0
            get = self._fast.get
            wait = options & ACH_O_WAIT
            span, final = self._slice(deadline) if wait else (0, True)
            try:
                status, size = get(buf, options, span, lock_ns)
            except (TypeError, BufferError):  # not a plain writable buffer: convert it, or say what is wrong
                buf = _byte_view(buf, True)
                status, size = get(buf, options, span, lock_ns)
            while wait and status == ACH_TIMEOUT:  # a slice passed without a new frame
                if self._cancel or self._closed:
                    return ACH_CANCELED, 0
                if final:  # that was the last slice before the deadline
                    return ACH_TIMEOUT, 0
                span, final = self._slice(deadline)
                status, size = get(buf, options, span, lock_ns)
            if wait and status in (ACH_OK, ACH_MISSED_FRAME):
                woken = self._fast.woken
                if woken == _WAIT_TIMED_OUT:  # the frame came without a wake-up
                    self._short_slices = _SHORT_SLICE_FRAMES
                elif woken == _WAIT_WOKEN and self._short_slices:
                    self._short_slices -= 1
            return status, size
        finally:
            active.pop()
            if self._closed and not active:
                self._release()

    def _get(self, dst: memoryview, options: int, deadline: float | None, lock_ns: int = -1) -> tuple[int, int]:
        active = self._active
        active.append(1)  # inlined _enter(): this is the hot path
        try:
            if self._closed:
                raise AchException(ACH_CLOSED, channel=self.name)
            if not self._header_ok():
                return ACH_CORRUPT, 0
            mutex = self._mutex
            try:
                r = self._mutex_trylock(mutex)
                if r or self._i32[self._i_dirty]:
                    r = self._lock_slow(r, lock_ns)
                    if r:
                        return r, 0
                if self._cancel:
                    self._mutex_unlock(mutex)
                    return ACH_CANCELED, 0
                while True:
                    if options & ACH_O_WAIT:
                        r = self._wait(deadline, lock_ns)
                        if r:
                            if r in (ACH_TIMEOUT, ACH_CANCELED):
                                self._mutex_unlock(mutex)
                            return r, 0
                    result = self._read_locked(dst, options)
                    if result[0] != ACH_STALE_FRAMES or not options & ACH_O_WAIT or self._seq != self._q[self._q_last]:
                        break  # (a waiting get finds nothing only in a ring that a repair emptied: wait on)
                self._mutex_unlock(mutex)
                return (ACH_CORRUPT, 0) if self._lost.value else result
            except BaseException:
                self._unlock_if_owned()
                raise
        finally:
            active.pop()
            if self._closed and not active:
                self._release()

    def _read_locked(self, dst: memoryview, options: int) -> tuple[int, int]:
        """libach ``ach_get`` steps 3-7, literally. Caller holds the lock. Values from the file are read once and
        checked before use, as in ``_write_locked``."""
        q = self._q
        last_seq = q[self._q_last]
        index_head = q[_Q_INDEX_HEAD]
        index_free = q[_Q_INDEX_FREE]
        cnt = self._cnt
        dsize = self._dsize
        if index_head >= cnt or index_free > cnt or q[_Q_DATA_HEAD] >= dsize or q[_Q_DATA_FREE] > dsize:
            return ACH_CORRUPT, 0  # (_counters_ok, inlined: this is the hot path)
        seq = self._seq
        if last_seq == 0 or (seq == last_seq and not options & ACH_O_COPY):
            return ACH_STALE_FRAMES, 0
        ix = self._ix
        if options & ACH_O_LAST:
            ri = (index_head + cnt - 1) % cnt
        elif q[ix + 3 * self._next + 2] == seq + 1:
            ri = self._next
        elif seq == last_seq:
            ri = (index_head + cnt - 1) % cnt
        else:
            ri = (index_head + index_free) % cnt
        e = ix + 3 * ri
        size = q[e]
        offset = q[e + 1]
        eseq = q[e + 2]
        if not (size and offset < dsize and size <= dsize - offset and eseq and eseq <= last_seq):
            if size == offset == eseq == 0:  # an empty ring (a repair kept no frame): nothing to miss
                self._seq = last_seq
                return ACH_STALE_FRAMES, 0
            return ACH_CORRUPT, 0
        if seq > eseq:  # libach: the channel was re-created under this handle
            return ACH_BUG, 0
        if dst.nbytes < size:
            return ACH_OVERFLOW, size
        start = self._d0 + offset
        dst[:size] = self._mv[start:start + size]
        self._seq = eseq
        self._next = (ri + 1) % cnt
        return (ACH_MISSED_FRAME if eseq > seq + 1 else ACH_OK), size

    def poll(self, buf: object, timeout: float | None = None, last: bool = True) -> tuple[int, int]:
        """Busy-poll: spin on ``last_seq`` without touching the lock or the condvar, then take the lock and copy
        (newest frame by default). Lowest latency, burns a CPU core while waiting; mind the GIL. Returns like
        ``get``; ACH_TIMEOUT when nothing arrived within ``timeout`` seconds."""
        dst = _byte_view(buf, True)
        if self._fast is not None:
            status, size = self._poll_fast(dst, timeout, ACH_O_LAST if last else 0)
            if status in (ACH_OK, ACH_MISSED_FRAME, ACH_STALE_FRAMES, ACH_CANCELED, ACH_TIMEOUT):
                return status, size
            raise self._error(status, size=size, lock_ns=self._lock_ns)
        self._enter()
        try:
            q = self._q
            ql = self._q_last
            seq = self._seq
            deadline = None if timeout is None else time.monotonic() + timeout
            spins = 0
            while q[ql] == seq:
                spins += 1
                if spins & 0x3FF == 0:
                    if self._cancel or self._closed:
                        return ACH_CANCELED, 0
                    if deadline is not None and time.monotonic() > deadline:
                        return ACH_TIMEOUT, 0
            # last_seq changes while the writer still holds the mutex: locking now would put us to sleep in the
            # kernel (PI futex) and cost a context switch. Spin (briefly) until the futex word is free.
            i32 = self._i32
            il = self._i_lock
            spins = 0
            while i32[il] and spins < 100_000:
                spins += 1
        finally:
            self._leave()
        status, size = self._get(dst, ACH_O_LAST if last else 0, None, self._lock_ns)
        if status in (ACH_OK, ACH_MISSED_FRAME, ACH_STALE_FRAMES, ACH_CANCELED):
            return status, size
        raise self._error(status, size=size, lock_ns=self._lock_ns)

    def _poll_fast(self, dst: memoryview, timeout: float | None, options: int) -> tuple[int, int]:
        """``poll`` through the C handle: it spins with the GIL released, in slices, then gets."""
        self._enter()
        try:
            deadline = None if timeout is None else time.monotonic() + timeout
            poll = self._fast.poll
            while True:
                if self._cancel or self._closed:
                    return ACH_CANCELED, 0
                span = _SPIN_SLICE_NS
                if deadline is not None:
                    span = min(span, max(0, int((deadline - time.monotonic()) * 1e9)))
                status, size = poll(dst, options, span, self._lock_ns)
                if status != ACH_TIMEOUT or span < _SPIN_SLICE_NS:
                    return status, size
        finally:
            self._leave()

    # -- flush / cancel / admin --------------------------------------------------------------------

    def flush(self) -> None:
        """Mark every frame in the channel as seen by this handle (libach ``ach_flush``)."""
        self._enter()
        try:
            if self._fast is not None:
                r = ACH_CANCELED if self._cancel else self._fast.flush()
            else:
                r = self._flush_locked()
        finally:
            self._leave()
        if r:
            raise self._error(r)

    def _flush_locked(self) -> int:
        if not self._header_ok():
            return ACH_CORRUPT
        try:
            r = self._lock()
            if r == ACH_OK:
                q = self._q
                index_head = q[_Q_INDEX_HEAD]
                if self._cancel:
                    r = ACH_CANCELED
                elif not self._counters_ok(index_head, q[_Q_INDEX_FREE], q[_Q_DATA_HEAD], q[_Q_DATA_FREE]):
                    r = ACH_CORRUPT
                else:
                    self._seq = q[self._q_last]
                    self._next = index_head
                self._mutex_unlock(self._mutex)
        except BaseException:
            self._unlock_if_owned()
            raise
        return ACH_CORRUPT if self._lost.value else r

    def cancel(self, *, async_unsafe: bool = False) -> None:
        """Make every current and future get/flush on this handle return ACH_CANCELED (sticky).

        Default: set the flag and wake the waiters without taking the mutex, which is safe from a signal handler
        even if this very thread holds the lock (a waiter that misses the wake-up sees the flag within one wait
        slice). ``async_unsafe=True`` is libach's thread variant: lock, set, unlock, wake.
        """
        self._enter()
        try:
            if async_unsafe:
                try:
                    r = self._mutex_lock(self._mutex)
                    if r == _EOWNERDEAD:
                        self._fn.mutex_consistent(self._mutex)
                    self._cancel = True
                    if r in (0, _EOWNERDEAD):
                        self._mutex_unlock(self._mutex)
                except BaseException:
                    self._unlock_if_owned()
                    raise
            self._cancel = True
            self._wake_all()
        finally:
            self._leave()

    @property
    def canceled(self) -> bool:
        return self._cancel

    def chmod(self, mode: int) -> None:
        """``fchmod`` the channel file (every participant needs read-write access)."""
        self._enter()
        try:
            os.fchmod(self._fd, mode)
        except OSError as exc:
            raise _os_error(exc, self.name, shm_path(self.name)) from None
        finally:
            self._leave()

    def unlink(self) -> None:
        """Remove the channel by name; this handle stays usable (classic binding)."""
        unlink(self.name)

    def snapshot(self) -> ChannelImage:
        """A parsed copy of the whole file taken under the lock (header counters, index, frames)."""
        self._enter()
        try:
            try:
                r = self._lock()
                if r:
                    raise self._error(r)
                data = self._mm[:]
                self._mutex_unlock(self._mutex)
            except BaseException:
                self._unlock_if_owned()
                raise
            if self._lost.value:
                raise self._error(ACH_CORRUPT)
        finally:
            self._leave()
        return parse_image(data, self._layout.arch)

    def fileno(self) -> int:
        return self._fd


def _lock_ns(lock_timeout: float | None) -> int:
    """A ``lock_timeout`` in seconds as the nanoseconds the lock calls take; -1 = no bound (None or inf)."""
    if lock_timeout is None or lock_timeout == math.inf:
        return -1
    if not lock_timeout >= 0:
        raise ValueError(f"lock_timeout must be >= 0 seconds or None, got {lock_timeout!r}")
    return int(lock_timeout * 1e9)
