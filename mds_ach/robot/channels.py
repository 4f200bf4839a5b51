"""Typed Ach channels: one ctypes struct per frame, newest-frame semantics, and MDS channel management.

Every MDS channel carries exactly one struct type (``mds-state`` -> ``MDS_STATE`` ...). ``StructChannel``
makes the common patterns one call (``latest()`` in a control loop, ``wait()`` in an event loop) and refuses
frames of the wrong size instead of handing out half-filled or truncated structs: a C client built against
an older ``mds.h`` must not silently move joints.

A damaged channel must not kill the node that uses it (docs/reliability.md §2): ``StructChannel`` re-opens a
channel file that ``mds-ach repair`` re-created (a damaged header cannot be repaired in place), and
``ChannelGuard`` turns an unusable channel into "nothing new" for the caller, says what to run, and says when the
channel works again.
"""

from __future__ import annotations

import ctypes
import grp
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any, Generic, TypeVar

import mds_ach as mds
from mds_ach import ach
from mds_ach.robot import access as channel_access
from mds_ach.robot import contracts

T = TypeVar("T", bound=ctypes.Structure)


def replaced(channel: ach.Channel) -> bool:
    """Does the channel's path name another file than the open handle maps (``mds-ach repair`` re-created a
    channel whose header was damaged)? A missing file is not a replacement: the handle is all there is."""
    try:
        mapped = os.fstat(channel.fileno())
        at_path = os.lstat(ach.shm_path(channel.name))
    except (OSError, ach.AchException):
        return False
    return (mapped.st_dev, mapped.st_ino) != (at_path.st_dev, at_path.st_ino)


class StructChannel(Generic[T]):
    """An Ach channel whose frames are instances of ``ctype``.

    ``latest()`` and ``wait()`` return a fresh ``ctype`` instance (callers may keep it) or None. Frames whose
    size differs from ``sizeof(ctype)`` are never returned; they are counted in ``bad_frames``.
    ``lock_timeout`` (seconds; None: no bound) bounds how long ``latest``, ``wait`` and ``put`` wait for the
    channel mutex, each call may override it; past it they raise ``AchException`` with ``ACH_LOCKED`` and leave
    the channel untouched (a real-time loop skips that frame instead of stalling behind a stuck process).
    """

    def __init__(self, name: str, ctype: type[T], create: bool = True,
                 frame_count: int = mds.CHANNEL_FRAME_COUNT, frame_size: int = mds.CHANNEL_FRAME_SIZE,
                 lock_timeout: float | None = None):
        self.name = name
        self.ctype = ctype
        self.size = ctypes.sizeof(ctype)
        self._geometry = (frame_count, frame_size)
        self.channel = self._open(create, lock_timeout)
        # Every frame fits in a buffer of data_size, so a wrong-sized frame is read (and counted) exactly once
        # instead of sticking in the channel as an endless ACH_OVERFLOW.
        self._buf = bytearray(self.channel.data_size)
        self.bad_frames = 0
        self.missed_frames = 0
        self.reopened = 0

    def _open(self, create: bool, lock_timeout: float | None) -> ach.Channel:
        """Open (create) the file at the channel's path: trusted (when enforced) and large enough for ``ctype``."""
        frame_count, frame_size = self._geometry
        channel = ach.Channel(self.name, frame_count, frame_size, create=create,
                              mode=channel_access.channel_mode(self.name), lock_timeout=lock_timeout)
        try:
            if channel_access.enforced():  # a node of the stack: never use a file another user planted
                channel_access.require_trusted(channel)
            if self.size > channel.data_size:
                raise ValueError(f"channel '{self.name}' holds frames of at most {channel.data_size} bytes, but "
                                 f"{self.ctype.__name__} needs {self.size}; remove it (mds-ach rm {self.name}) and "
                                 f"re-create it (mds-ach make)")
        except BaseException:
            channel.close()
            raise
        return channel

    def replaced(self) -> bool:
        """Was the channel file re-created under this handle (``replaced``)?"""
        return replaced(self.channel)

    def reopen(self) -> None:
        """Open the file now at the channel's path and drop the old handle (its reader position starts again:
        the new file's frames are all new). Raises like the constructor; the old handle stays on failure."""
        new = self._open(False, self.channel.lock_timeout)
        old, self.channel = self.channel, new
        self._buf = bytearray(new.data_size)
        self.reopened += 1
        old.close()

    def _io(self, op: Callable[[ach.Channel], Any]) -> Any:
        """``op(self.channel)``; an error on a channel file that was since re-created re-opens it and tries once
        more, so every user of a StructChannel picks up a re-created channel by itself."""
        try:
            return op(self.channel)
        except ach.AchException as exc:
            if exc.status in (ach.ACH_LOCKED, ach.ACH_CLOSED, ach.ACH_CANCELED) or not self.replaced():
                raise
            try:
                self.reopen()
            except (ach.AchException, OSError, ValueError):
                raise exc from None  # not usable yet (e.g. half created): still the original error
        return op(self.channel)

    @classmethod
    def of(cls, name: str, create: bool = True, lock_timeout: float | None = None) -> StructChannel[Any]:
        """Open MDS channel ``name`` with the struct and geometry its contract names (``mds_ach.robot.contracts``);
        ``KeyError`` if it is not an MDS channel."""
        c = contracts.contract(name)
        return StructChannel(name, c.struct, create=create, frame_count=c.frame_count, frame_size=c.frame_size,
                             lock_timeout=lock_timeout)

    def _frame(self, status: int, size: int) -> T | None:
        if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
            return None
        if size != self.size:
            self.bad_frames += 1
            return None
        if status == ach.ACH_MISSED_FRAME:
            self.missed_frames += 1
        return self.ctype.from_buffer_copy(self._buf)

    def latest(self, lock_timeout: float | None = None) -> T | None:
        """The newest frame if one arrived since the last call, else None. Never waits for a frame (only for the
        channel mutex, at most ``lock_timeout`` s if given or set on the channel)."""
        status, size = self._io(lambda ch: ch.get(self._buf, last=True, lock_timeout=lock_timeout))
        return self._frame(status, size)

    def next(self, lock_timeout: float | None = None) -> T | None:
        """The oldest frame not read yet (in order, libach's get without ACH_O_LAST), else None. Never waits."""
        status, size = self._io(lambda ch: ch.get(self._buf, last=False, lock_timeout=lock_timeout))
        return self._frame(status, size)

    def wait_next(self, timeout: float | None = None, lock_timeout: float | None = None) -> T | None:
        """Block until a frame not read yet exists and return the *oldest* one (in order, for request channels
        where every frame counts, e.g. ``mds-hold``); None on timeout, cancel or close."""
        status, size = self._io(lambda ch: ch.get(self._buf, wait=True, last=False, timeout=timeout,
                                                  lock_timeout=lock_timeout))
        if status in (ach.ACH_TIMEOUT, ach.ACH_CANCELED):
            return None
        return self._frame(status, size)

    def wait(self, timeout: float | None = None, lock_timeout: float | None = None) -> T | None:
        """Block until a new frame arrives (newest wins); None on timeout, cancel or close.

        ``timeout`` in seconds; None waits forever (still interruptible with Ctrl-C and ``cancel()``).
        ``lock_timeout`` as for ``latest``.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            status, size = self._io(partial(ach.Channel.get, buf=self._buf, wait=True, last=True,
                                            timeout=remaining, lock_timeout=lock_timeout))
            if status in (ach.ACH_TIMEOUT, ach.ACH_CANCELED):
                return None
            frame = self._frame(status, size)
            if frame is not None:
                return frame
            if deadline is not None and time.monotonic() >= deadline:
                return None

    def put(self, obj: T, lock_timeout: float | None = None) -> None:
        """Publish ``obj``; it must be a ``ctype`` instance (the exact layout is the wire contract).
        ``lock_timeout`` as for ``latest``."""
        if not isinstance(obj, self.ctype):
            raise TypeError(f"channel '{self.name}' carries {self.ctype.__name__}, got {type(obj).__name__}")
        self._io(lambda ch: ch.put(obj, lock_timeout=lock_timeout))

    def flush(self) -> None:
        """Treat everything in the channel as already seen."""
        self._io(lambda ch: ch.flush())

    def cancel(self) -> None:
        """Wake a blocked ``wait()`` for good (e.g. at shutdown, from another thread or a signal handler)."""
        self.channel.cancel()

    def close(self) -> None:
        self.channel.close()

    def __enter__(self) -> StructChannel[T]:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class ChannelGuard:
    """Keeps a node running through an unusable channel and says so: what broke, what fixes it, when it works again.

    A client killed inside a put leaves its channel ACH_CORRUPT until ``mds-ach repair``; bytes scribbled over a
    header make it unusable until ``mds-ach repair`` re-creates it (``StructChannel`` then re-opens it). A node
    that died on either would take the pipeline down with it. ``call`` returns ``default`` instead, logs the error
    at most every ``every`` seconds per channel with the fix, pauses ``pause`` s so a failing wait does not spin,
    and, after an outage it reported, logs once that the channel works again (a flapping channel, e.g. a lock that
    times out now and then, gives at most one pair of lines per ``every`` s). Thread-safe: one guard may serve
    several threads.
    """

    def __init__(self, log: Callable[[str, str], None], stop: threading.Event | None = None, every: float = 5.0,
                 pause: float = 0.05) -> None:
        self._log = log
        self._stop = stop if stop is not None else threading.Event()
        self._every = every
        self._pause = pause
        self._lock = threading.Lock()
        self._last: dict[str, float] = {}
        self._failing: dict[str, int] = {}  # channel -> errors since it last worked
        self._reported: set[str] = set()  # channels whose current outage was logged
        self.errors = 0

    def call(self, name: str, fn: Callable[..., Any], *args: Any, default: Any = None, **kwargs: Any) -> Any:
        try:
            result = fn(*args, **kwargs)
        except ach.AchException as exc:
            self._failed(name, exc)
            return default
        if name in self._failing:
            self._recovered(name)
        return result

    def put(self, channel: StructChannel[Any], frame: Any) -> bool:
        """``channel.put(frame)``; False (reported as ``call`` does) when the frame could not be written."""
        def put() -> bool:
            channel.put(frame)
            return True

        return bool(self.call(channel.name, put, default=False))

    def failing(self, name: str) -> bool:
        """Did the newest call on channel ``name`` fail?"""
        return name in self._failing

    def _failed(self, name: str, exc: ach.AchException) -> None:
        now = time.monotonic()
        with self._lock:
            self.errors += 1
            self._failing[name] = self._failing.get(name, 0) + 1
            due = now - self._last.get(name, -float("inf")) >= self._every
            if due:
                self._last[name] = now
                self._reported.add(name)
        if due:
            locked = exc.status == ach.ACH_LOCKED
            fix = ("`mds-ach repair --check` names the process holding it" if locked
                   else f"run `mds-ach repair {name}`; the node picks it up again by itself")
            self._log("error", f"channel {name}: {exc}; holding until it works again ({fix})")
        self._stop.wait(self._pause)

    def _recovered(self, name: str) -> None:
        with self._lock:
            errors = self._failing.pop(name, None)
            reported = name in self._reported
            self._reported.discard(name)
        if errors is not None and reported:
            self._log("info", f"channel {name} works again (after {errors} failed call(s)); carrying on")


# --- MDS channel set ------------------------------------------------------------------------------


@dataclass
class ChannelReport:
    """What ``make_channels`` did with one channel; ``ok`` False means it needs attention."""

    name: str
    action: str  # "created", "exists", "tightened" (``check_existing``) or "error"
    detail: str = ""

    @property
    def ok(self) -> bool:
        return self.action != "error"


def check_existing(name: str, frame_count: int = mds.CHANNEL_FRAME_COUNT, frame_size: int = mds.CHANNEL_FRAME_SIZE,
                   mode: int = channel_access.CHANNEL_MODE, gid: int | None = None,
                   tighten: bool = False) -> ChannelReport:
    """Is the existing channel ``name`` one the stack may use: trusted (owner, mode, group), an Ach file, of the
    expected geometry? The report's detail says what is wrong and what to do.

    With ``tighten``, a channel of the stack's own user that is too open (the original's ``ach mk`` made 0644,
    its ``chmod 777``) gets the configured mode in place when nobody has it open (``channel_access.tighten``):
    action ``tightened``, the detail says what changed."""
    tightened = ""
    if tighten:
        try:
            tightened = channel_access.tighten(name, mode) or ""
        except channel_access.UntrustedChannelError as exc:
            return ChannelReport(name, "error", str(exc))
        except OSError as exc:
            return ChannelReport(name, "error", f"cannot tighten {ach.shm_path(name)}: {exc.strerror}")
    why = channel_access.path_problem(name, mode, gid)
    if why is not None:
        return ChannelReport(name, "error", f"{why}; {channel_access.recreate_hint(name)}")
    try:
        with ach.Channel(name, create=False) as ch:
            count, size = ch.frame_count, ch.frame_size
    except ach.AchException as exc:
        return ChannelReport(name, "error", exc.reason)
    if (count, size) != (frame_count, frame_size):
        return ChannelReport(name, "error", f"exists as {count} x {size} B, expected {frame_count} x {frame_size} B; "
                                            f"remove it (mds-ach rm {name}) to re-create it")
    if tightened:
        return ChannelReport(name, "tightened", f"{count} x {size} B, {tightened} (it was open to more users than "
                                                "the stack gives access)")
    return ChannelReport(name, "exists", f"{count} x {size} B")


def make_channels(
    names: tuple[str, ...] | list[str] = contracts.ALL_CHANNELS,
    mode: int = channel_access.CHANNEL_MODE,
    group: str | int | None = None,
    frame_count: int = mds.CHANNEL_FRAME_COUNT,
    frame_size: int = mds.CHANNEL_FRAME_SIZE,
) -> list[ChannelReport]:
    """Create every channel of the contracts registry (10 x 3000 B by default) with ``mode``; existing ones are
    validated, never clobbered.

    ``mode`` may only restrict ``CHANNEL_MODE`` (0660); the daemon's input gets it without group write
    (``channel_access.channel_mode``). ``group`` (name or gid) is given to the channels created here, so members
    of that group can run the clients. An existing channel is accepted only when the stack may trust it (owner,
    mode, group: ``channel_access``); one the stack's own user made too open is tightened in place
    (``check_existing``).
    Returns one report per channel; see ``ChannelReport.ok``.
    """
    channel_access.check_configured_mode(mode)
    gid = _resolve_group(group)
    reports = []
    for name in names:
        chan_mode = channel_access.channel_mode(name, mode)
        try:
            ach.create(name, frame_count, frame_size, mode=chan_mode)
        except ach.AchException as exc:
            if exc.status == ach.ACH_EEXIST:
                reports.append(check_existing(name, frame_count, frame_size, mode, gid, tighten=True))
            else:
                reports.append(ChannelReport(name, "error", exc.reason))
            continue
        detail = f"{frame_count} x {frame_size} B, mode {chan_mode:#o}"
        if gid is not None:
            try:
                os.chown(ach.shm_path(name), -1, gid)
                detail += f", group {group}"
            except OSError as exc:
                reports.append(ChannelReport(name, "error", f"created, but chgrp {group} failed: {exc.strerror}"))
                continue
        reports.append(ChannelReport(name, "created", detail))
    return reports


def _resolve_group(group: str | int | None) -> int | None:
    if group is None:
        return None
    if isinstance(group, int):
        return group
    if group.isdigit():
        return int(group)
    try:
        return grp.getgrnam(group).gr_gid
    except KeyError:
        raise ValueError(f"no such group: {group!r}") from None


def remove_channels(names: tuple[str, ...] | list[str] = contracts.ALL_CHANNELS) -> list[str]:
    """Unlink the channels that exist; returns the names removed. Missing ones are skipped silently."""
    removed = []
    for name in names:
        try:
            ach.unlink(name)
        except ach.AchException as exc:
            if exc.status != ach.ACH_ENOENT:
                raise
            continue
        removed.append(name)
    return removed
