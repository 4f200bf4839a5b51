"""``Channel``: an open channel handle, libach's put/get/flush algorithms over the mapped file (the package
docstring says why they look the way they do), with the optional C twin ``_achfast`` for the hot calls.

The wait tunables (``WAIT_SLICE``, ``POLL_SLICE``, ``IDLE_SLICE``) and ``_achfast`` are globals of *this* module,
read at call time: patch them here (``mds_ach.ach.channel``), not on the package.

Imports: the rest of :mod:`mds_ach.ach` (status, layout, glibc, image, files).
"""

from __future__ import annotations

import ctypes
import errno
import math
import mmap
import os
import struct
import threading
import time
from types import ModuleType
from typing import TYPE_CHECKING

from mds_ach.ach.files import MappingGuard, open_channel_file, os_error, reserve, shm_path, validate_name
from mds_ach.ach.files import create as _create  # Channel.__init__ has a parameter called ``create``
from mds_ach.ach.files import unlink as _unlink_file
from mds_ach.ach.glibc import (
    ENOTRECOVERABLE,
    EOWNERDEAD,
    ETIMEDOUT,
    FUTEX_TID_MASK,
    FUTEX_WAIT,
    FUTEX_WAKE,
    SYS_FUTEX,
    Timespec,
    pthread,
)
from mds_ach.ach.image import ChannelImage, check_geometry, parse_image
from mds_ach.ach.layout import (
    GUARD_DATA,
    GUARD_HEADER,
    GUARD_INDEX,
    MAGIC,
    OFF_CLOCK,
    Q_DATA_FREE,
    Q_DATA_HEAD,
    Q_DATA_SIZE,
    Q_INDEX_CNT,
    Q_INDEX_FREE,
    Q_INDEX_HEAD,
    Q_LEN,
    Layout,
    entry_ok,
    native_layout,
)
from mds_ach.ach.status import (
    ACH_BAD_SHM_FILE,
    ACH_BUG,
    ACH_CANCELED,
    ACH_CLOSED,
    ACH_CORRUPT,
    ACH_EEXIST,
    ACH_EINVAL,
    ACH_ENOENT,
    ACH_FAILED_SYSCALL,
    ACH_LOCKED,
    ACH_MISSED_FRAME,
    ACH_O_COPY,
    ACH_O_LAST,
    ACH_O_WAIT,
    ACH_OK,
    ACH_OVERFLOW,
    ACH_STALE_FRAMES,
    ACH_TIMEOUT,
    AchException,
    result_string,
)

if TYPE_CHECKING:  # the C extension is optional at run time (see _load_fast)
    from mds_ach.ach._achfast import Handle as _FastHandle

WAIT_SLICE = 0.1  # s per condvar wait slice (condvar_wait=True), so Ctrl-C / cancel / close are seen promptly
POLL_SLICE = 0.005  # pure-Python path: s per futex wait slice, how late a frame from a C libach writer can be seen
IDLE_SLICE = 0.05  # C fast path: how often an idle wait looks at last_seq (inside C: a broadcast-only writer's frame)
IDLE_RETURN = 1.0  # C fast path: an idle wait returns to Python this often (cancel and close wake it; signals end it)
UNWOKEN_POLL = 0.0003  # C fast path: after a frame came without a wake-up, look at last_seq this often (in C) ...
UNWOKEN_HOLD = 10.0  # ... for this many seconds after the last such frame (golems' libach writers only broadcast)
UNWOKEN_PROBE = 0.3  # ... and for this long after a wake-up that found several frames (one may have come unwoken)
# _achfast.Handle.woken: how the last get's futex wait ended (0: no wait; achcore.h WAIT_*)
_WAIT_WOKEN, _WAIT_UNWOKEN, _WAIT_SEVERAL = 1, 2, 3

_U64 = struct.Struct("<Q")
_U64_MAX = 2**64 - 1
_SPIN_SLICE_NS = 10_000_000  # a busy-poll returns to Python this often to see cancel, close and Ctrl-C


def _load_fast() -> ModuleType | None:
    """The optional C extension, unless it is missing or MDS_ACH_PURE_PYTHON is set."""
    if os.environ.get("MDS_ACH_PURE_PYTHON", "") not in ("", "0"):
        return None
    try:  # in a function: the extension is optional and MDS_ACH_PURE_PYTHON may refuse it
        from mds_ach.ach import _achfast
    except ImportError:
        return None
    return _achfast


_achfast = _load_fast()
FAST_AVAILABLE = _achfast is not None  # the C fast path is built and not disabled
_LOCK_TIMED_OUT = -1  # internal status (not libach's): the mutex was not acquired within lock_timeout
_LOCK_SLICE_NS = 50_000_000  # a busy channel lock is waited for in timed slices this long (Channel._wait_for_lock)
_GONE = -2  # _wait_for_lock: the header changed (e.g. the file was truncated) while waiting for the lock



def _byte_view(buf: object, writable: bool) -> memoryview:
    """A flat unsigned-byte view of any contiguous buffer (bytes, bytearray, memoryview, ctypes object)."""
    if type(buf) is memoryview:
        mv = buf
    else:
        try:
            mv = memoryview(buf)  # type: ignore[arg-type]  # any object: a non-buffer raises, reworded below
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
        return memoryview((ctypes.c_ubyte * mv.nbytes).from_buffer(buf)).cast("B")  # type: ignore[arg-type]  # mv is a view of it


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

    def __init__(self, name: str | None = None, frame_count: int = 0, frame_size: int = 0, *, create: bool = True,
                 mode: int = 0o660, condvar_wait: bool = False, fast: bool = True, lock_timeout: float | None = None):
        self.name = ""
        self._condvar_wait = condvar_wait
        self._want_fast = fast
        self._create_missing = create
        self._mode = mode
        self._closed = True  # until fully open, so __del__ / close() are harmless
        self._active: list[int] = []
        self.lock_timeout = lock_timeout
        if name is not None:  # the classic binding: Channel() is a handle to open() later
            self.open(name, frame_count, frame_size)

    def open(self, name: str, frame_count: int = 0, frame_size: int = 0) -> None:
        """The classic binding's ``open``: open channel ``name`` in this handle, made without a name or closed;
        a missing channel is created first (``frame_count`` x ``frame_size``, 0: 16 x 512) unless the handle was
        made with ``create=False``."""
        if not self._closed:
            raise AchException(ACH_EINVAL, f"this handle has channel {self.name!r} open: close() it first",
                               channel=self.name)
        self.name = validate_name(name)
        try:
            self._open()
        except AchException as exc:
            if exc.status != ACH_ENOENT or not self._create_missing:
                raise
            try:
                _create(name, frame_count, frame_size, mode=self._mode)
            except AchException as exc2:
                if exc2.status != ACH_EEXIST:  # lost a creation race: fine, open theirs
                    raise
            self._open()

    @staticmethod
    def result_string(status: int) -> str:
        """The classic binding's ``result_string``: the status name, e.g. ``"ACH_OK"`` (``status.result_string``)."""
        return result_string(status)

    # -- open / close ------------------------------------------------------------------------------

    def _open(self) -> None:
        """libach ``ach_open``: map the whole file, check magic/length/guards, reset the reader state. Also reserve
        the file's memory and guard the mapping (module docstring)."""
        layout = native_layout()
        path = shm_path(self.name)
        fd = open_channel_file(self.name, path)  # never through a symlink, never a FIFO; the ownership rule
        try:
            size = os.fstat(fd).st_size
            head = os.pread(fd, 4, 0)
            if len(head) < 4 or struct.unpack("<I", head)[0] != MAGIC:
                raise AchException(ACH_BAD_SHM_FILE, f"{path}: bad magic number ({size} bytes)", channel=self.name)
            if size < layout.header_size + 24:
                raise AchException(ACH_BAD_SHM_FILE, f"{path}: truncated, {size} bytes", channel=self.name)
            reserve(fd, size, self.name, "open")  # a sparse file (made by libach's ach mk) gets its pages now
            mm = mmap.mmap(fd, size)
        except BaseException:
            os.close(fd)
            raise
        guard = MappingGuard(mm, fd)  # before the first access: the file may shrink at any time
        try:
            cnt, dsize = check_geometry(mm, layout)
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
        self._ix = layout.index_offset() // 8  # u64 index of index[0].size
        self._d0 = layout.data_offset(cnt)  # byte offset of the data ring
        self._qg_h = h // 8
        self._qg_i = layout.guard_index_offset(cnt) // 8
        self._off_g_d = layout.guard_data_offset(cnt, dsize)  # may be unaligned
        self._q_last = layout.last_seq // 8
        self._i_dirty = layout.dirty // 4
        self._i_lock = layout.mutex // 4
        self._clock = self._i32[OFF_CLOCK // 4]
        self._fn = pthread()
        self._mutex_lock = self._fn.mutex_lock  # cached: attribute lookups show up on the hot path
        self._mutex_trylock = self._fn.mutex_trylock
        self._mutex_unlock = self._fn.mutex_unlock
        self._cond_broadcast = self._fn.cond_broadcast
        sys_futex = ctypes.c_long(SYS_FUTEX[layout.arch])
        last_seq_word = ctypes.c_void_p(base + layout.last_seq)  # low 32 bits of last_seq (little-endian)
        self._futex_wait_args = (sys_futex, last_seq_word, ctypes.c_int(FUTEX_WAIT))
        self._futex_wake_args = (sys_futex, last_seq_word, ctypes.c_int(FUTEX_WAKE), ctypes.c_int(0x7FFFFFFF))
        self._syscall = self._fn.syscall
        # reader state (libach ach_open): seq_num = 0, next_index = 1; kept in the C handle when there is one
        self._seq = 0
        self._next = 1
        self._fast: _FastHandle | None = None
        self._unwoken_until = 0.0  # monotonic s: until then a writer that does not wake the futex is assumed
        if _achfast is not None and self._want_fast and not self._condvar_wait:
            try:
                self._fast = _achfast.Handle(base, layout.mutex, layout.cond, layout.dirty, layout.last_seq,
                                             layout.header_size, cnt, dsize, size, guard.flag_address)
            except ValueError:  # a libc whose mutex size differs from the layout: stay in Python
                self._fast = None
        self._cancel = False
        self._active = []
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
                and q[Q_LEN] == self._len and q[Q_INDEX_CNT] == self._cnt and q[Q_DATA_SIZE] == self._dsize)

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
                check_geometry(self._mm, self._layout)
            except AchException as exc:
                problem = exc.detail
            else:
                problem = (f"header changed under this handle (len/index_cnt/data_size now {self._q[Q_LEN]}/"
                           f"{self._q[Q_INDEX_CNT]}/{self._q[Q_DATA_SIZE]}, opened as {self._len}/{self._cnt}/"
                           f"{self._dsize})")
            return f"{problem}; {repair} (it re-creates a channel with a damaged header), then re-open it"
        if self._i32[self._i_dirty]:
            return f"a writer died inside a put (dirty flag set); {repair}"
        q = self._q
        counters = (q[Q_INDEX_HEAD], q[Q_INDEX_FREE], q[Q_DATA_HEAD], q[Q_DATA_FREE])
        if not self._counters_ok(*counters):
            return (f"ring counters out of range (index_head/index_free {counters[0]}/{counters[1]} for "
                    f"{self._cnt} slots, data_head/data_free {counters[2]}/{counters[3]} for {self._dsize} "
                    f"bytes); {repair}")
        return f"damaged index entry; {repair}"

    def _error(self, status: int, detail: str = "", size: int | None = None, lock_ns: int = -1) -> AchException:
        """The exception for a failed call, with what happened and what to do."""
        if status == _LOCK_TIMED_OUT:
            owner = self._i32[self._i_lock] & FUTEX_TID_MASK if not self._closed else 0
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
        ts = Timespec()
        ts_ref = ctypes.byref(ts)
        while True:
            span = _LOCK_SLICE_NS if end is None else max(0, min(_LOCK_SLICE_NS, end - time.monotonic_ns()))
            ts.tv_sec, ts.tv_nsec = divmod(time.clock_gettime_ns(time.CLOCK_REALTIME) + span, 1_000_000_000)
            r = self._fn.mutex_timedlock(self._mutex, ts_ref)
            if r != ETIMEDOUT:
                return r
            if self._lost.value or not self._header_ok():
                return _GONE
            if end is not None and time.monotonic_ns() >= end:
                return ETIMEDOUT

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
        if r == EOWNERDEAD:
            self._fn.mutex_consistent(self._mutex)
        elif r == ETIMEDOUT:
            return _LOCK_TIMED_OUT
        elif r in (ENOTRECOVERABLE, _GONE):
            return ACH_CORRUPT
        elif r:
            return ACH_FAILED_SYSCALL
        if self._i32[self._i_dirty]:
            self._mutex_unlock(self._mutex)
            return ACH_CORRUPT
        return ACH_OK

    def _owned(self) -> bool:
        """True when the PI futex word names this thread as owner (the kernel's view, always accurate)."""
        return self._i32[self._i_lock] & FUTEX_TID_MASK == threading.get_native_id()

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
        ts = Timespec()  # per call: threads sharing a handle may wait at the same time
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
                if r == ETIMEDOUT:
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
                if r == ETIMEDOUT:
                    return _LOCK_TIMED_OUT
            if r == EOWNERDEAD:
                self._fn.mutex_consistent(self._mutex)
            elif r:
                self._unlock_if_owned()
                return ACH_CORRUPT if r in (ENOTRECOVERABLE, _GONE) else ACH_FAILED_SYSCALL
            if self._i32[self._i_dirty]:
                self._mutex_unlock(self._mutex)
                return ACH_CORRUPT

    # -- put ---------------------------------------------------------------------------------------

    def put(self, buf: object, lock_timeout: float | None = None) -> None:
        """Write one frame (bytes, bytearray, memoryview or ctypes object). Raises AchException on any
        non-OK status (classic binding), e.g. ACH_OVERFLOW when the frame is larger than the channel, ACH_LOCKED
        when the mutex was not acquired within ``lock_timeout`` seconds (None: this handle's ``lock_timeout``)."""
        lock_ns = self._lock_ns if lock_timeout is None else _lock_ns(lock_timeout)
        fast = self._fast
        r = self._put_fast(fast, buf, lock_ns) if fast is not None else self._put(_byte_view(buf, False), lock_ns)
        if r:
            detail = f"{_byte_view(buf, False).nbytes} bytes > data_size {self._dsize}" if r == ACH_OVERFLOW else ""
            raise self._error(r, detail, lock_ns=lock_ns)

    def put_status(self, buf: object, lock_timeout: float | None = None) -> int:
        """Like ``put`` but returns the libach status instead of raising (ACH_LOCKED for a lock timeout)."""
        lock_ns = self._lock_ns if lock_timeout is None else _lock_ns(lock_timeout)
        fast = self._fast
        r = self._put_fast(fast, buf, lock_ns) if fast is not None else self._put(_byte_view(buf, False), lock_ns)
        return ACH_LOCKED if r == _LOCK_TIMED_OUT else r

    def _put_fast(self, fast: _FastHandle, buf: object, lock_ns: int) -> int:
        active = self._active
        active.append(1)
        try:
            if self._closed:
                raise AchException(ACH_CLOSED, channel=self.name)
            try:
                return fast.put(buf, lock_ns)
            except (TypeError, BufferError):  # not a plain contiguous buffer: convert it, or say what is wrong
                return fast.put(_byte_view(buf, False), lock_ns)
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
        index_head = q[Q_INDEX_HEAD]
        index_free = q[Q_INDEX_FREE]
        data_head = q[Q_DATA_HEAD]
        data_free = q[Q_DATA_FREE]
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
            if not entry_ok(size, offset, seq, dsize, last):
                return ACH_CORRUPT
            data_free += q[e]
            index_free += 1
            q[e] = q[e + 1] = q[e + 2] = 0
        if dsize - data_head < n:  # tail wrap: drop the frames after data_head, restart at offset 0
            i = (index_head + index_free) % cnt
            while q[ix + 3 * i + 1] > data_head:
                e = ix + 3 * i
                size, offset, seq = q[e], q[e + 1], q[e + 2]
                if not entry_ok(size, offset, seq, dsize, last):
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
                if not entry_ok(size, offset, seq, dsize, last):
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
                if not entry_ok(size, offset, seq, dsize, last):
                    return ACH_CORRUPT
                data_free += size
                index_free += 1
                q[e] = q[e + 1] = q[e + 2] = 0
            i = (i + 1) % cnt
        if dsize - data_head < n:  # libach's sanity check; cannot happen
            q[Q_DATA_HEAD], q[Q_DATA_FREE], q[Q_INDEX_FREE] = data_head, data_free, index_free
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
        q[Q_DATA_HEAD] = (data_head + n) % dsize
        q[Q_DATA_FREE] = data_free - n
        q[Q_INDEX_HEAD] = (index_head + 1) % cnt
        q[Q_INDEX_FREE] = index_free - 1
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
        if (fast := self._fast) is not None:
            return self._get_fast(fast, buf, options, deadline, lock_ns)
        return self._get(_byte_view(buf, True), options, deadline, lock_ns)

    def _slice(self, deadline: float | None) -> tuple[int, bool]:
        """Nanoseconds of the next wait slice, and whether it is the last one before the deadline.

        Writers of this package and of its libach wake waiting readers, and so do ``cancel`` and ``close``; a signal
        ends the futex wait too. So a C wait returns to Python only every IDLE_RETURN (or at the deadline): the look
        at last_seq for a broadcast-only writer's frame is made inside C every IDLE_SLICE (``_poll_ns``), without
        taking the interpreter lock -- a Python round every 50 ms in each waiting thread was a tenth of the whole
        system's CPU at rest."""
        full = int(max(IDLE_RETURN, IDLE_SLICE) * 1e9)
        if deadline is None:
            return full, False
        left = int((deadline - time.clock_gettime(self._clock)) * 1e9)
        return (full, False) if left > full else (max(0, left), True)

    def _poll_ns(self) -> int:
        """How often (ns) the C wait looks at last_seq by itself: every IDLE_SLICE, so a frame from a writer that
        does not wake the futex (golems' libach writers only broadcast the condvar, which futex sleepers do not
        hear) is seen within IDLE_SLICE. Such a frame makes the reader look every UNWOKEN_POLL for UNWOKEN_HOLD
        seconds after the last such frame, also on channels where other writers do wake it."""
        return int((UNWOKEN_POLL if time.monotonic() < self._unwoken_until else IDLE_SLICE) * 1e9)

    def _get_fast(self, fast: _FastHandle, buf: object, options: int, deadline: float | None,
                  lock_ns: int = -1) -> tuple[int, int]:
        """``_get`` through the C handle: one call per frame; waits in GIL-free futex slices."""
        active = self._active
        active.append(1)
        try:
            if self._closed:
                raise AchException(ACH_CLOSED, channel=self.name)
            if self._cancel:
                return ACH_CANCELED, 0
            get = fast.get
            wait = options & ACH_O_WAIT
            span, final = self._slice(deadline) if wait else (0, True)
            poll_ns = self._poll_ns() if wait else 0
            try:
                status, size = get(buf, options, span, lock_ns, poll_ns)
            except (TypeError, BufferError):  # not a plain writable buffer: convert it, or say what is wrong
                buf = _byte_view(buf, True)
                status, size = get(buf, options, span, lock_ns, poll_ns)
            while wait and status == ACH_TIMEOUT:  # a slice passed without a new frame
                if self._cancel or self._closed:
                    return ACH_CANCELED, 0
                if final:  # that was the last slice before the deadline
                    return ACH_TIMEOUT, 0
                span, final = self._slice(deadline)
                status, size = get(buf, options, span, lock_ns, self._poll_ns())
            if wait and status in (ACH_OK, ACH_MISSED_FRAME) and fast.woken >= _WAIT_UNWOKEN:
                now = time.monotonic()
                if fast.woken == _WAIT_UNWOKEN:  # the frame came without a wake-up
                    self._unwoken_until = now + UNWOKEN_HOLD
                else:  # one of the frames may have: look briefly (achcore_wait says why)
                    self._unwoken_until = max(self._unwoken_until, now + UNWOKEN_PROBE)
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
        index_head = q[Q_INDEX_HEAD]
        index_free = q[Q_INDEX_FREE]
        cnt = self._cnt
        dsize = self._dsize
        if index_head >= cnt or index_free > cnt or q[Q_DATA_HEAD] >= dsize or q[Q_DATA_FREE] > dsize:
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
        if not entry_ok(size, offset, eseq, dsize, last_seq):
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
        if (fast := self._fast) is not None:
            status, size = self._poll_fast(fast, dst, timeout, ACH_O_LAST if last else 0)
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

    def _poll_fast(self, fast: _FastHandle, dst: memoryview, timeout: float | None, options: int) -> tuple[int, int]:
        """``poll`` through the C handle: it spins with the GIL released, in slices, then gets."""
        self._enter()
        try:
            deadline = None if timeout is None else time.monotonic() + timeout
            poll = fast.poll
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
                index_head = q[Q_INDEX_HEAD]
                if self._cancel:
                    r = ACH_CANCELED
                elif not self._counters_ok(index_head, q[Q_INDEX_FREE], q[Q_DATA_HEAD], q[Q_DATA_FREE]):
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
                    if r == EOWNERDEAD:
                        self._fn.mutex_consistent(self._mutex)
                    self._cancel = True
                    if r in (0, EOWNERDEAD):
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
            raise os_error(exc, self.name, shm_path(self.name)) from None
        finally:
            self._leave()

    def unlink(self) -> None:
        """Remove the channel by name; this handle stays usable (classic binding)."""
        _unlink_file(self.name)

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
