"""Channel files in ``/dev/shm``: names, creation (laid out as libach's ``ach_create`` does), removal, and the
SIGBUS guard every mapping of a channel file is registered with.

Imports: :mod:`mds_ach.ach.status`, :mod:`mds_ach.ach.layout`, :mod:`mds_ach.ach.glibc`.
"""

from __future__ import annotations

import ctypes
import errno
import mmap
import os
import stat
import struct
import threading
from collections.abc import Callable
from types import ModuleType

from mds_ach.ach.glibc import pthread
from mds_ach.ach.layout import (
    GUARD_DATA,
    GUARD_HEADER,
    GUARD_INDEX,
    MAGIC,
    NAME_MAX,
    OFF_CLOCK,
    OFF_INDEX_CNT,
    OFF_MAGIC,
    OFF_NAME,
    Layout,
    native_layout,
)
from mds_ach.ach.status import (
    ACH_BAD_SHM_FILE,
    ACH_DEFAULT_FRAME_COUNT,
    ACH_DEFAULT_FRAME_SIZE,
    ACH_EACCES,
    ACH_EEXIST,
    ACH_EINVAL,
    ACH_ENOENT,
    ACH_FAILED_SYSCALL,
    ACH_INVALID_NAME,
    CLOCK_MONOTONIC,
    AchException,
)

SHM_DIR = "/dev/shm"
SHM_PREFIX = "achshm-"
_NAME_CHARS = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_.-")


def _load_guard() -> ModuleType | None:
    """The SIGBUS guard for channel mappings. Both paths use it, so MDS_ACH_PURE_PYTHON does not turn it off."""
    try:  # in a function: the C extension is optional (pure-Python installs lack it)
        from mds_ach.ach import _shmguard
    except ImportError:
        return None
    return _shmguard


_shmguard = _load_guard()
GUARD_AVAILABLE = _shmguard is not None  # a truncated channel file cannot kill this process


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
    """True when something exists at the channel's path (its contents are not checked; a symbolic link counts,
    dangling or not: the name is taken, and opening it is refused)."""
    return os.path.lexists(shm_path(name))


def unlink(name: str) -> None:
    """Remove the channel (``shm_unlink``); processes that have it open keep the orphaned memory."""
    path = shm_path(name)
    try:
        os.unlink(path)
    except FileNotFoundError:
        raise AchException(ACH_ENOENT, path, channel=name) from None
    except OSError as exc:  # EACCES/EPERM, a directory at the path (EISDIR), ...
        raise os_error(exc, name, path) from None


# --- read-only parsing (any arch, no locking) ------------------------------------------------------


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
        raise os_error(exc, name, tmp) from None
    try:
        try:
            os.ftruncate(fd, length)
            reserve(fd, length, name, "create")
            initialise(fd, length, layout, name, count, count * size, clock)
            os.fchmod(fd, mode)
            if truncate:
                os.replace(tmp, path)
            else:
                os.link(tmp, path)
        except FileExistsError:
            raise AchException(ACH_EEXIST, path, channel=name) from None
        except OSError as exc:
            raise os_error(exc, name, path) from None
    finally:
        os.close(fd)
        if os.path.exists(tmp):
            os.unlink(tmp)




def initialise(fd: int, length: int, layout: Layout, name: str, count: int, dsize: int, clock: int) -> None:
    """Fill a zeroed file the way libach's ``ach_create`` does: sync objects, counters, guards, magic, name."""
    mm = mmap.mmap(fd, length)
    try:
        anchor = ctypes.c_char.from_buffer(mm)
        try:
            base = ctypes.addressof(anchor)
            pthread().init_sync(base + layout.mutex, base + layout.cond, clock)
        finally:
            del anchor
        struct.pack_into("<IxxxxQ", mm, OFF_MAGIC, MAGIC, length)
        mm[OFF_NAME:OFF_NAME + len(name)] = name.encode("ascii")
        # index_cnt, data_size, data_head, data_free, index_head, index_free
        struct.pack_into("<QQQQQQ", mm, OFF_INDEX_CNT, count, dsize, 0, dsize, 0, count)
        struct.pack_into("<i", mm, OFF_CLOCK, clock)
        struct.pack_into("<Q", mm, layout.header_size, GUARD_HEADER)
        struct.pack_into("<Q", mm, layout.guard_index_offset(count), GUARD_INDEX)
        struct.pack_into("<Q", mm, layout.guard_data_offset(count, dsize), GUARD_DATA)
    finally:
        mm.close()


def reserve(fd: int, length: int, name: str, what: str) -> None:
    """Allocate every page of the channel file now (``posix_fallocate``; a no-op for pages that exist), so a full
    ``/dev/shm`` is a clear error here and not a SIGBUS in whichever process first writes a fresh page later."""
    try:
        os.posix_fallocate(fd, 0, length)
    except OSError as exc:
        if exc.errno in (errno.EOPNOTSUPP, errno.ENODEV):  # not tmpfs: that file system reserves nothing
            return
        if exc.errno not in (errno.ENOSPC, errno.ENOMEM, errno.EFBIG, errno.EDQUOT):
            raise os_error(exc, name, shm_path(name)) from None
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
        size = _shmguard.state(self._slot)[1] if _shmguard is not None and self._slot >= 0 else -1
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
        if _shmguard is None or self._slot < 0:  # a slot is only ever taken with the guard there
            return True
        if self.lost:
            MappingGuard._kept.append((mm, fd))
            return False
        _shmguard.forget(self._slot)
        self._slot = -1
        self._flag = ctypes.c_int(0)
        return True


OpenCheck = Callable[[str, str, os.stat_result], str | None]
"""``check(name, path, st) -> why not | None``: who may own a channel file this process opens (see
:func:`set_open_check`)."""

_open_check: OpenCheck | None = None


def set_open_check(check: OpenCheck | None) -> None:
    """Install the ownership rule every channel open applies (after the file is known to be a regular file).

    This layer knows channel files, not who the robot's users are: ``mds_ach.robot.access`` installs its client
    rule (owned by root, this user or the stack's user) when the package is imported, so every client -- the
    CLI tools, the legacy ``import mds_ach as mds`` API, the examples -- refuses a file another user planted."""
    global _open_check
    _open_check = check


_KINDS = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISDIR, "a directory"), (stat.S_ISSOCK, "a socket"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"))


def open_channel_file(name: str, path: str) -> int:
    """Open the channel file ``path`` read-write and return the descriptor, refusing what a channel never is.

    ``O_NOFOLLOW``: a symbolic link at the channel's path is refused, never followed (another user can plant a
    link in ``/dev/shm`` to a file of theirs: a client would then read their data and write into it).
    ``O_NONBLOCK`` then ``fstat``: a FIFO (or anything but a regular file) is refused instead of blocking the open
    or failing later with a traceback. Then the installed ownership rule (:func:`set_open_check`)."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_CLOEXEC | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError as exc:
        raise os_error(exc, name, path) from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = next((what for test, what in _KINDS if test(st.st_mode)), "not a regular file")
            raise AchException(ACH_BAD_SHM_FILE, f"{path} is {kind}, not a channel file", channel=name)
        os.set_blocking(fd, True)
        why = _open_check(name, path, st) if _open_check is not None else None
        if why is not None:
            raise AchException(ACH_EACCES, why, channel=name)
    except BaseException:
        os.close(fd)
        raise
    return fd


def os_error(exc: OSError, name: str, path: str) -> AchException:
    if exc.errno == errno.ENOENT:
        return AchException(ACH_ENOENT, path, channel=name)
    if exc.errno == errno.ELOOP:
        return AchException(ACH_BAD_SHM_FILE, f"{path} is a symbolic link: a channel is never opened through one "
                             "(another user may have planted it); remove it (mds-ach repair --recreate "
                             f"{name})", channel=name)
    if exc.errno == errno.EISDIR:
        return AchException(ACH_BAD_SHM_FILE, f"{path} is a directory, not a channel file", channel=name)
    if exc.errno in (errno.EACCES, errno.EPERM):
        return AchException(ACH_EACCES, f"{path}: {exc.strerror}", channel=name)
    if exc.errno == errno.EEXIST:
        return AchException(ACH_EEXIST, path, channel=name)
    return AchException(ACH_FAILED_SYSCALL, f"{path}: {exc.strerror}", channel=name)


# --- channel handle --------------------------------------------------------------------------------

