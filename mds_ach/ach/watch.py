"""Read-only channel watching: the one reader that operator tools, the viewer and achd's links build on.

Why a separate reader: tools must start and stop at any time without disturbing anything, so they only ever
*open* existing channels (never create, flush or write them), survive channels that appear, vanish or are
re-created (``mds-ach killall`` + restart) while they run, and judge freshness by when *they* saw a new frame
arrive (the publisher may be dead while its last frame is still in the channel).

Imports: the rest of :mod:`mds_ach.ach` only.
"""

from __future__ import annotations

import ctypes
import os
import time
from typing import Generic, TypeVar

from mds_ach.ach.channel import Channel
from mds_ach.ach.files import exists, shm_path
from mds_ach.ach.status import ACH_CORRUPT, ACH_MISSED_FRAME, ACH_OK, AchException

T = TypeVar("T", bound=ctypes.Structure)

REPLACED_CHECK_S = 1.0  # how often a quiet handle looks whether its file is still the channel's


def replaced(chan: Channel) -> bool:
    """True when the channel's file was removed or re-created since ``chan`` opened it (e.g. the stack was
    restarted): the handle then reads and writes an orphan nobody else sees any more."""
    try:
        return os.stat(shm_path(chan.name)).st_ino != os.fstat(chan.fileno()).st_ino
    except OSError:
        return True


class ReplacementCheck:
    """``replaced(chan)``, but at most every ``period`` s: a stat per frame would show on a streaming loop."""

    def __init__(self, chan: Channel, period: float = REPLACED_CHECK_S) -> None:
        self.chan = chan
        self.period = period
        self._next = time.monotonic() + period

    def due_and_replaced(self) -> bool:
        now = time.monotonic()
        if now < self._next:
            return False
        self._next = now + self.period
        return replaced(self.chan)


class Latest(Generic[T]):
    """The newest frame of one channel, opened read-only on demand and re-opened when the channel is re-created.

    ``read()`` returns the newest frame (a cached copy when nothing new arrived), or None while the channel is
    missing or empty; ``read_new()`` only a frame that arrived since the previous call. ``age()`` is the time since
    this reader last saw a *new* frame; a frame already in the channel when the reader opened it has unknown age
    (``age()`` None) until the next one arrives. After ``retry`` s without a new frame the reader looks whether
    the file is still the channel's and re-opens it if not.
    """

    def __init__(self, name: str, ctype: type[T], retry: float = REPLACED_CHECK_S) -> None:
        self.name = name
        self.ctype = ctype
        self.size = ctypes.sizeof(ctype)
        self.retry = retry
        self._chan: Channel | None = None
        self._buf: bytearray | None = None
        self._seen = 0  # frames counted when read_new last returned
        self._next_check = 0.0
        self.frame: T | None = None
        self.new_at: float | None = None  # monotonic time a new frame was last seen
        self.frames = 0  # new frames seen since open
        self.bad_frames = 0  # frames of the wrong size (ignored)
        self.error = "not opened yet"  # why the channel is not readable, for display

    @property
    def available(self) -> bool:
        """The channel is open (it exists and could be mapped)."""
        return self._chan is not None

    def _open(self) -> bool:
        if self._chan is not None:
            now = time.monotonic()
            quiet = self.new_at is None or now - self.new_at > self.retry
            if not (quiet and now >= self._next_check):
                return True
            self._next_check = now + self.retry
            if not replaced(self._chan):
                return True
            self._drop(f"channel {self.name} was removed or re-created")
        if not exists(self.name):
            self.error = f"channel {self.name} does not exist"
            return False
        try:
            self._chan = Channel(self.name, create=False)
        except (OSError, AchException) as exc:
            self.error = f"cannot open {self.name}: {exc.reason if isinstance(exc, AchException) else exc}"
            return False
        self._buf = bytearray(max(self._chan.data_size, self.size))
        self._next_check = time.monotonic() + self.retry
        self.error = ""
        return True

    def _drop(self, why: str) -> None:
        if self._chan is not None:
            try:
                self._chan.close()
            except AchException:
                pass
        self._chan = None
        self.error = why

    def _take(self, status: int, size: int, fresh: bool) -> bool:
        """Keep the frame just read into the buffer; True if it was a new, valid frame.

        ``fresh``: it certainly arrived just now (a blocking wait returned it, or it is not the first frame
        this reader saw); the first frame of a non-blocking read may have sat in the channel for hours.
        """
        if status not in (ACH_OK, ACH_MISSED_FRAME):
            return False
        if size != self.size:
            self.bad_frames += 1
            return False
        assert self._buf is not None
        self.frame = self.ctype.from_buffer_copy(self._buf[: self.size])
        if fresh or self.frames:
            self.new_at = time.monotonic()
        self.frames += 1
        return True

    def read(self) -> T | None:
        """Newest frame (new or cached); never blocks."""
        if not self._open():
            return self.frame
        assert self._chan is not None and self._buf is not None
        try:
            status, size = self._chan.get(self._buf, last=True)
        except AchException as exc:
            self._drop(f"{self.name}: {exc.reason}")
            return self.frame
        if status == ACH_CORRUPT:
            self._drop(f"channel {self.name} is corrupt")
            return self.frame
        self._take(status, size, fresh=False)
        return self.frame

    def read_new(self) -> T | None:
        """The newest frame if one arrived since the previous ``read_new``, else None; never blocks."""
        frame = self.read()
        if self.frames == self._seen:
            return None
        self._seen = self.frames
        return frame

    def wait_new(self, timeout: float) -> T | None:
        """Block up to ``timeout`` s for a frame newer than anything seen; None on timeout or missing channel."""
        deadline = time.monotonic() + timeout
        self.read()
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self._open():
                return None
            assert self._chan is not None and self._buf is not None
            try:
                status, size = self._chan.get(self._buf, wait=True, last=True, timeout=min(remaining, 0.2))
            except AchException as exc:
                self._drop(f"{self.name}: {exc.reason}")
                return None
            if self._take(status, size, fresh=True):
                return self.frame

    def age(self) -> float | None:
        """Seconds since a new frame was seen; None if none has been seen arriving yet."""
        return None if self.new_at is None else time.monotonic() - self.new_at

    def close(self) -> None:
        self._drop("closed")
