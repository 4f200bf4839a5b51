"""The one ctypes binding to glibc: process-shared pthread objects, futex, absolute sleeps, thread tuning.

Ach channels keep a robust, priority-inheriting pthread mutex and a condvar inside the file, so Python must call
the very glibc functions libach calls; the daemon's loop sleeps to absolute deadlines with ``clock_nanosleep``,
asks for 1 ns timer slack, SCHED_FIFO and ``mlockall``. All of it is bound here once, with argtypes set once
(cached function pointers: these calls sit on hot paths), so the channel code, ``mds-ach repair`` and the daemon
cannot drift apart.

Imports: only :mod:`mds_ach.ach.status`.
"""

from __future__ import annotations

import ctypes
import math
import os
import threading
import time
from collections.abc import Callable
from typing import Any

from mds_ach.ach.status import ACH_FAILED_SYSCALL, AchException

# glibc constants, identical on x86_64 and aarch64
PTHREAD_PROCESS_SHARED = 1
PTHREAD_PRIO_INHERIT = 1
PTHREAD_MUTEX_ROBUST = 1
EOWNERDEAD = 130
ENOTRECOVERABLE = 131
ETIMEDOUT = 110
EINTR = 4
FUTEX_TID_MASK = 0x3FFFFFFF  # the owner's tid in a pthread mutex's lock word
FUTEX_WAIT = 0  # shared (no FUTEX_PRIVATE_FLAG): the word lives in a file mapped by several processes
FUTEX_WAKE = 1
SYS_FUTEX = {"x86_64": 202, "aarch64": 98}
CLOCK_MONOTONIC = 1
TIMER_ABSTIME = 1
PR_SET_TIMERSLACK = 29
PR_SET_NAME = 15
MCL_CURRENT = 1
MCL_FUTURE = 2
CAP_IPC_LOCK = 14


class Timespec(ctypes.Structure):
    """``struct timespec``."""

    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]

    @classmethod
    def at(cls, seconds: float) -> Timespec:
        """A timespec for ``seconds`` on a clock's timeline (e.g. an absolute ``time.monotonic()`` deadline)."""
        sec = math.floor(seconds)
        return cls(int(sec), int((seconds - sec) * 1e9))


_libc: ctypes.CDLL | None = None


def libc() -> ctypes.CDLL:
    """glibc, with errno kept (glibc >= 2.34 has pthread in libc; older ones keep it in libpthread)."""
    global _libc
    if _libc is None:
        try:
            lib = ctypes.CDLL("libc.so.6", use_errno=True)
            lib.pthread_mutex_consistent  # noqa: B018 - probe
        except (OSError, AttributeError):
            lib = ctypes.CDLL("libpthread.so.0", use_errno=True)
        _libc = lib
    return _libc


def _fn(f: Any, argtypes: list[Any]) -> Callable[..., int]:
    f.argtypes = argtypes
    f.restype = ctypes.c_int
    return f  # type: ignore[no-any-return]


def check_zero(r: int, what: str) -> None:
    """A pthread call's return value: nonzero is the errno, raised as ACH_FAILED_SYSCALL."""
    if r != 0:
        raise AchException(ACH_FAILED_SYSCALL, f"{what}: {os.strerror(r)}")


class Pthread:
    """The glibc pthread calls Ach needs, plus ``syscall`` for the futex."""

    def __init__(self) -> None:
        lib = libc()
        vp = [ctypes.c_void_p]
        ts = ctypes.POINTER(Timespec)
        self.mutex_lock = _fn(lib.pthread_mutex_lock, vp)
        self.mutex_trylock = _fn(lib.pthread_mutex_trylock, vp)
        self.mutex_timedlock = _fn(lib.pthread_mutex_timedlock, [ctypes.c_void_p, ts])
        self.mutex_unlock = _fn(lib.pthread_mutex_unlock, vp)
        self.mutex_consistent = _fn(lib.pthread_mutex_consistent, vp)
        self.cond_broadcast = _fn(lib.pthread_cond_broadcast, vp)
        self.cond_timedwait = _fn(lib.pthread_cond_timedwait, [ctypes.c_void_p, ctypes.c_void_p, ts])
        self.mutex_init = _fn(lib.pthread_mutex_init, [ctypes.c_void_p, ctypes.c_void_p])
        self.cond_init = _fn(lib.pthread_cond_init, [ctypes.c_void_p, ctypes.c_void_p])
        self.mutexattr_init = _fn(lib.pthread_mutexattr_init, vp)
        self.mutexattr_destroy = _fn(lib.pthread_mutexattr_destroy, vp)
        self.mutexattr_setpshared = _fn(lib.pthread_mutexattr_setpshared, [ctypes.c_void_p, ctypes.c_int])
        self.mutexattr_setprotocol = _fn(lib.pthread_mutexattr_setprotocol, [ctypes.c_void_p, ctypes.c_int])
        self.mutexattr_setrobust = _fn(lib.pthread_mutexattr_setrobust, [ctypes.c_void_p, ctypes.c_int])
        self.condattr_init = _fn(lib.pthread_condattr_init, vp)
        self.condattr_destroy = _fn(lib.pthread_condattr_destroy, vp)
        self.condattr_setpshared = _fn(lib.pthread_condattr_setpshared, [ctypes.c_void_p, ctypes.c_int])
        self.condattr_setclock = _fn(lib.pthread_condattr_setclock, [ctypes.c_void_p, ctypes.c_int])
        self.syscall = lib.syscall  # variadic: called with explicit ctypes arguments
        self.syscall.restype = ctypes.c_long

    def init_sync(self, mutex_addr: int, cond_addr: int, clock: int) -> None:
        """libach's creation: cond (pshared + clock), then mutex (pshared + PRIO_INHERIT + ROBUST)."""
        cattr = ctypes.create_string_buffer(64)
        check_zero(self.condattr_init(cattr), "pthread_condattr_init")
        try:
            check_zero(self.condattr_setpshared(cattr, PTHREAD_PROCESS_SHARED), "pthread_condattr_setpshared")
            check_zero(self.condattr_setclock(cattr, clock), "pthread_condattr_setclock")
            check_zero(self.cond_init(cond_addr, cattr), "pthread_cond_init")
        finally:
            self.condattr_destroy(cattr)
        mattr = ctypes.create_string_buffer(64)
        check_zero(self.mutexattr_init(mattr), "pthread_mutexattr_init")
        try:
            check_zero(self.mutexattr_setpshared(mattr, PTHREAD_PROCESS_SHARED), "pthread_mutexattr_setpshared")
            check_zero(self.mutexattr_setprotocol(mattr, PTHREAD_PRIO_INHERIT), "pthread_mutexattr_setprotocol")
            check_zero(self.mutexattr_setrobust(mattr, PTHREAD_MUTEX_ROBUST), "pthread_mutexattr_setrobust")
            check_zero(self.mutex_init(mutex_addr, mattr), "pthread_mutex_init")
        finally:
            self.mutexattr_destroy(mattr)


_pthread: Pthread | None = None


def pthread() -> Pthread:
    """The process's one :class:`Pthread` (bound on first use, so importing costs no dlopen)."""
    global _pthread
    if _pthread is None:
        _pthread = Pthread()
    return _pthread


# --- scheduling ------------------------------------------------------------------------------------------------

_clock_nanosleep: Callable[..., int] | None = None
_no_clock_nanosleep = False


def _nanosleep_fn() -> Callable[..., int] | None:
    global _clock_nanosleep, _no_clock_nanosleep
    if _clock_nanosleep is None and not _no_clock_nanosleep:
        try:
            _clock_nanosleep = _fn(libc().clock_nanosleep,
                                   [ctypes.c_int, ctypes.c_int, ctypes.POINTER(Timespec), ctypes.c_void_p])
        except (OSError, AttributeError):  # not glibc: sleep_until falls back to a relative sleep
            _no_clock_nanosleep = True
    return _clock_nanosleep


def sleep_until(deadline: float) -> None:
    """Sleep until ``deadline`` on the CLOCK_MONOTONIC timeline (``time.monotonic()``), absolute, so that
    lateness never accumulates; restarts after signals. The GIL is released while sleeping."""
    fn = _nanosleep_fn()
    if fn is None:
        remaining = deadline - time.monotonic()
        if remaining > 0:
            time.sleep(remaining)
        return
    ts = Timespec.at(deadline)
    while fn(CLOCK_MONOTONIC, TIMER_ABSTIME, ctypes.byref(ts), None) == EINTR:
        pass


def tune_thread(rt_priority: int = 0, name: str | None = None) -> list[str]:
    """Best effort for the calling thread: 1 ns timer slack, its kernel name (``ps -L``, ``/proc/PID/task/TID/comm``;
    at most 15 bytes), optional SCHED_FIFO. Returns what failed.

    SCHED_FIFO comes with SCHED_RESET_ON_FORK: a thread or process this thread creates starts at normal priority,
    so nothing but the thread that asked for it ever runs real-time (a busy real-time helper would starve the
    machine)."""
    problems = []
    try:
        if libc().prctl(PR_SET_TIMERSLACK, ctypes.c_ulong(1), 0, 0, 0) != 0:
            problems.append("timer slack unchanged")
        if name is not None:
            libc().prctl(PR_SET_NAME, ctypes.c_char_p(name.encode()[:15]), 0, 0, 0)
    except (OSError, AttributeError):
        problems.append("no prctl")
    if rt_priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(rt_priority))
        except OSError as exc:
            problems.append(f"SCHED_FIFO {rt_priority} refused ({exc.strerror or exc}); running with normal priority")
    return problems


def thread_scheduling(tid: int = 0) -> tuple[int, int]:
    """(policy, real-time priority) of thread ``tid`` (0: the calling one), the SCHED_RESET_ON_FORK flag removed."""
    return os.sched_getscheduler(tid) & ~os.SCHED_RESET_ON_FORK, os.sched_getparam(tid).sched_priority


def renice_other_threads(nice: int) -> str | None:
    """Give every other thread of this process the nice value ``nice`` (threads they create inherit it). None on
    success, else why not. Python threads share one interpreter lock: a normal-priority thread of a real-time
    process that is preempted while it holds the lock stops the real-time thread too; a negative nice value gets
    it the CPU back sooner (CFS weight), while it stays at normal, never real-time, scheduling."""
    me = threading.get_native_id()
    try:
        for tid in (int(t) for t in os.listdir("/proc/self/task")):
            if tid != me:
                try:
                    os.setpriority(os.PRIO_PROCESS, tid, nice)
                except ProcessLookupError:  # the thread ended meanwhile
                    pass
    except OSError as exc:
        return f"nice {nice} refused ({exc.strerror or exc})"
    return None


def _may_lock_all_memory() -> str | None:
    """None when ``mlockall`` can lock this process's memory now and later without making allocations fail:
    CAP_IPC_LOCK or an unlimited RLIMIT_MEMLOCK. Else why not (with a finite limit, MCL_FUTURE would turn the
    process's growth past the limit into failed allocations)."""
    import resource

    soft, _hard = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("CapEff:") and int(line.split()[1], 16) >> CAP_IPC_LOCK & 1:
                    return None
    except (OSError, ValueError):
        pass
    return f"RLIMIT_MEMLOCK is {soft // 1024} KiB, not unlimited, and no CAP_IPC_LOCK"


def lock_memory() -> str | None:
    """``mlockall(MCL_CURRENT | MCL_FUTURE)`` for the whole process, so no page of it is ever paged out and a page
    fault never delays a real-time loop. None on success, else why not (nothing is locked then)."""
    why = _may_lock_all_memory()
    if why is not None:
        return why
    try:
        fn = _fn(libc().mlockall, [ctypes.c_int])
    except (OSError, AttributeError):
        return "no mlockall"
    if fn(MCL_CURRENT | MCL_FUTURE) != 0:
        return f"mlockall failed ({os.strerror(ctypes.get_errno())})"
    return None
