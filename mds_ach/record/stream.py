"""Every frame of one channel, in order, read as a normal reader: what the recorder takes from each channel.

:class:`mds_ach.ach.watch.Latest` serves monitors (only the newest frame matters); a recording needs every frame a
writer put, so this reader takes them in sequence (``get`` without ``last``) and counts the ones the ring of
``frame_count`` frames overwrote before it came (``missed``). Like every reader it only opens existing channels
(never creates, flushes or writes one) and survives channels that vanish or are re-created (``mds-ach killall``
and a new start while it records): then it opens the new file and takes its frames from the first. It polls
(``poll``) instead of sleeping on the channel: it takes the lock only when a frame is there, for the copy of it,
and a writer's put never wakes it (measured in bench/bench_record.py).

When it first opens a channel it takes the newest frame already there (e.g. ``mds-limits``, published once when
the daemon started), stamped with the time it read it; after that only frames that arrive.

Imports: :mod:`mds_ach.ach` only.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from mds_ach.ach.channel import Channel
from mds_ach.ach.files import exists
from mds_ach.ach.status import ACH_CORRUPT, ACH_MISSED_FRAME, ACH_OK, AchException
from mds_ach.ach.watch import ReplacementCheck

RETRY_S = 0.05
"""How often a missing channel is looked for again (a stat per channel): a re-created channel is found before its
ring (two frames of ``mds-state``) overflows at the rates a restarted daemon starts with."""
REPLACED_S = 0.1
"""How often an idle channel is checked for having been removed or re-created (a stat and an fstat)."""


@dataclass(frozen=True)
class Frame:
    """One frame as read: its bytes, the wall-clock time (ns) the reader took it, its sequence number in the
    channel (Ach's, from 1 when the channel was made), whether it sat in the channel already when the reader opened
    it (``initial``), and how many frames the ring overwrote before it (``missed``)."""

    data: bytes
    wall_ns: int
    seq: int = 0
    initial: bool = False
    missed: int = 0


class FrameStream:
    """Sequential reader of channel ``name``: ``poll()`` returns the frames that arrived since the last call."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._chan: Channel | None = None
        self._check: ReplacementCheck | None = None
        self._buf = bytearray(0)
        self._next_look = 0.0
        self.frames = 0
        self.missed = 0
        self.opened = 0  # times the channel was (re-)opened
        self.error = "not opened yet"
        self._stopped = False

    def _open(self) -> Frame | None:
        """Open the channel if it exists; the newest frame already in it, if any."""
        now = time.monotonic()
        if now < self._next_look:
            return None
        self._next_look = now + RETRY_S
        if not exists(self.name):
            self.error = f"channel {self.name} does not exist"
            return None
        try:
            chan = Channel(self.name, create=False)
        except (OSError, AchException) as exc:
            self.error = f"cannot open {self.name}: {exc}"
            return None
        self._chan, self._check = chan, ReplacementCheck(chan, REPLACED_S)
        self._buf = bytearray(chan.data_size)
        self.opened += 1
        self.error = ""
        if self.opened > 1:  # a re-created channel: every frame in it is new
            return None
        try:
            status, size = chan.get(self._buf, last=True)
        except AchException:
            return None
        if status in (ACH_OK, ACH_MISSED_FRAME):
            self.frames += 1
            return Frame(bytes(self._buf[:size]), time.time_ns(), chan.seq_num, initial=True)
        return None

    def _drop(self, why: str) -> None:
        if self._chan is not None:
            try:
                self._chan.close()
            except AchException:
                pass
        self._chan, self._check = None, None
        self.error = why

    def poll(self) -> list[Frame]:
        """Every frame that arrived since the last call, oldest first; never waits. The channel's lock is taken only
        when its newest sequence number (read without the lock) says a frame is there: an idle poll costs the
        writers nothing, and no reader sleeps on the channel's futex (a writer's wake-up never hands the CPU to
        the recorder in the middle of its put)."""
        if self._stopped:
            return []
        out: list[Frame] = []
        if self._chan is None:
            first = self._open()
            if first is not None:
                out.append(first)
            if self._chan is None:
                return out
        chan = self._chan
        assert chan is not None and self._check is not None
        if chan.last_seq == chan.seq_num:
            if self._check.due_and_replaced():
                self._drop(f"channel {self.name} was removed or re-created")
                self._next_look = 0.0
            return out
        while True:
            before = chan.seq_num
            try:
                status, size = chan.get(self._buf)
            except AchException as exc:
                self._drop(f"{self.name}: {exc}")
                return out
            if status == ACH_CORRUPT:
                self._drop(f"channel {self.name} is corrupt")
                return out
            if status not in (ACH_OK, ACH_MISSED_FRAME):
                return out
            missed = max(0, chan.seq_num - before - 1) if status == ACH_MISSED_FRAME else 0
            self.frames += 1
            self.missed += missed
            out.append(Frame(bytes(self._buf[:size]), time.time_ns(), chan.seq_num, missed=missed))

    def stop(self) -> None:
        """Make ``poll`` return nothing from now on."""
        self._stopped = True

    def close(self) -> None:
        self._drop("closed")
