"""Pure-Python Ach, the bottom layer: shared-memory channels byte- and lock-compatible with C libach.

A channel is the file ``/dev/shm/achshm-<name>`` laid out exactly as libach 2.0 lays it out (described once, in
:mod:`mds_ach.ach.layout`). Readers and writers synchronise through the process-shared, robust,
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
  wake it directly (``FUTEX_WAKE`` after the unlock) and still broadcast the condvar for C readers; the
  project's libach for C clients (``libach/``, sharing ``achcore.h`` with the C fast path) does the same. Frames
  from golems' libach writers, which only broadcast, are noticed by a re-check: with the C fast path an idle
  reader re-checks every ``IDLE_SLICE`` inside C (returning to Python only every ``IDLE_RETURN``) until it has
  seen such a frame, then every ``UNWOKEN_POLL`` for ``UNWOKEN_HOLD`` seconds after the last one (and for
  ``UNWOKEN_PROBE`` after a wake-up that found several frames: on a channel a waking writer streams to as well, the
  broadcast-only frames arrive just before a woken one); the pure-Python path re-checks every ``POLL_SLICE``.
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

This package owns the channel format and everything that touches channel files: status codes
(``status``), the byte layout (``layout``), the one glibc binding (``glibc``), read-only image parsing
(``image``), channel files, creation and the SIGBUS guard (``files``), the ``Channel`` handle (``channel``,
with the C twins ``_achfast`` and ``_shmguard``) and the read-only watcher (``watch``); ``mds-ach repair``, which
applies the MDS channel list and access rules to these files, lives in ``mds_ach.tools.repair``. It re-exports
the public API, so ``from mds_ach import ach; ach.Channel(...)`` is all a client needs.

Imports: the standard library only; nothing else of mds_ach (it is the bottom layer; ``test_layers.py`` checks).
"""

from __future__ import annotations

from mds_ach.ach.channel import (
    _LOCK_TIMED_OUT,
    FAST_AVAILABLE,
    IDLE_RETURN,
    IDLE_SLICE,
    POLL_SLICE,
    UNWOKEN_HOLD,
    UNWOKEN_POLL,
    UNWOKEN_PROBE,
    WAIT_SLICE,
    Channel,
    _achfast,
)
from mds_ach.ach.files import (
    GUARD_AVAILABLE,
    SHM_DIR,
    SHM_PREFIX,
    MappingGuard,
    _shmguard,
    create,
    exists,
    open_channel_file,
    set_open_check,
    shm_path,
    unlink,
    validate_name,
)
from mds_ach.ach.image import ChannelImage, IndexEntry, detect_layout, parse_image
from mds_ach.ach.layout import (
    GUARD_DATA,
    GUARD_HEADER,
    GUARD_INDEX,
    LAYOUT_AARCH64,
    LAYOUT_X86_64,
    LAYOUTS,
    MAGIC,
    NAME_MAX,
    Layout,
    native_layout,
)
from mds_ach.ach.status import (
    ACH_BAD_HEADER,
    ACH_BAD_SHM_FILE,
    ACH_BUG,
    ACH_CANCELED,
    ACH_CLOSED,
    ACH_CORRUPT,
    ACH_DEFAULT_FRAME_COUNT,
    ACH_DEFAULT_FRAME_SIZE,
    ACH_EACCES,
    ACH_EAGAIN,
    ACH_EEXIST,
    ACH_EFAULT,
    ACH_EINTR,
    ACH_EINVAL,
    ACH_ENOENT,
    ACH_ENOTSUP,
    ACH_FAILED_SYSCALL,
    ACH_INVALID_NAME,
    ACH_LOCKED,
    ACH_MISSED_FRAME,
    ACH_O_ABSTIME,
    ACH_O_COPY,
    ACH_O_FIRST,
    ACH_O_LAST,
    ACH_O_NONBLOCK,
    ACH_O_RELTIME,
    ACH_O_WAIT,
    ACH_OK,
    ACH_OVERFLOW,
    ACH_STALE_FRAMES,
    ACH_TIMEOUT,
    CLOCK_MONOTONIC,
    CLOCK_REALTIME,
    AchException,
    explain,
    result_string,
)

__all__ = [
    "ACH_BAD_HEADER", "ACH_BAD_SHM_FILE", "ACH_BUG", "ACH_CANCELED", "ACH_CLOSED", "ACH_CORRUPT",
    "ACH_DEFAULT_FRAME_COUNT", "ACH_DEFAULT_FRAME_SIZE", "ACH_EACCES", "ACH_EAGAIN", "ACH_EEXIST", "ACH_EFAULT",
    "ACH_EINTR", "ACH_EINVAL", "ACH_ENOENT", "ACH_ENOTSUP", "ACH_FAILED_SYSCALL", "ACH_INVALID_NAME", "ACH_LOCKED",
    "ACH_MISSED_FRAME", "ACH_OK", "ACH_OVERFLOW", "ACH_O_ABSTIME", "ACH_O_COPY", "ACH_O_FIRST", "ACH_O_LAST",
    "ACH_O_NONBLOCK", "ACH_O_RELTIME", "ACH_O_WAIT", "ACH_STALE_FRAMES", "ACH_TIMEOUT", "CLOCK_MONOTONIC",
    "CLOCK_REALTIME", "FAST_AVAILABLE", "GUARD_AVAILABLE", "GUARD_DATA", "GUARD_HEADER", "GUARD_INDEX",
    "IDLE_RETURN", "IDLE_SLICE", "LAYOUTS", "LAYOUT_AARCH64", "LAYOUT_X86_64", "MAGIC", "NAME_MAX", "POLL_SLICE",
    "SHM_DIR", "SHM_PREFIX", "UNWOKEN_HOLD", "UNWOKEN_POLL", "UNWOKEN_PROBE", "WAIT_SLICE", "AchException",
    "Channel", "ChannelImage", "IndexEntry", "Layout", "MappingGuard",
    "create", "detect_layout", "exists", "explain", "native_layout", "open_channel_file", "parse_image",
    "result_string", "set_open_check", "shm_path", "unlink", "validate_name",
    "_LOCK_TIMED_OUT", "_achfast", "_shmguard",
]
