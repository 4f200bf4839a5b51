"""Read-only views of a running system, shared by the operator tools (console, read monitor, status).

Why a separate reader: the tools must start and stop at any time without disturbing anything, so they only
ever *open* existing channels (never create, flush or write them), survive channels that appear or vanish
while they run, and judge freshness by when *they* saw a new frame arrive (the publisher may be dead while
its last frame is still in the channel).
"""

from __future__ import annotations

import ctypes
import time
from typing import Generic, TypeVar

import mds_ach as mds
from mds_ach import ach

T = TypeVar("T", bound=ctypes.Structure)


class Latest(Generic[T]):
    """The newest frame of one channel, opened read-only on demand.

    ``read()`` returns the newest frame (a cached copy when nothing new arrived), or None while the channel is
    missing or empty. ``age()`` is the time since this reader last saw a *new* frame; a frame already in the
    channel when the reader opened it has unknown age (``age()`` None) until the next one arrives.
    """

    def __init__(self, name: str, ctype: type[T]) -> None:
        self.name = name
        self.ctype = ctype
        self.size = ctypes.sizeof(ctype)
        self._chan: ach.Channel | None = None
        self._buf: bytearray | None = None
        self.frame: T | None = None
        self.new_at: float | None = None  # monotonic time a new frame was last seen
        self.frames = 0  # new frames seen since open
        self.bad_frames = 0  # frames of the wrong size (ignored)
        self.error = ""  # why the channel is not readable, for display

    def _open(self) -> bool:
        if self._chan is not None:
            return True
        if not ach.exists(self.name):
            self.error = f"channel {self.name} does not exist"
            return False
        try:
            self._chan = ach.Channel(self.name, create=False)
        except ach.AchException as exc:
            self.error = f"cannot open {self.name}: {exc.reason}"
            return False
        self._buf = bytearray(max(self._chan.data_size, self.size))
        self.error = ""
        return True

    def _drop(self, why: str) -> None:
        if self._chan is not None:
            try:
                self._chan.close()
            except ach.AchException:
                pass
        self._chan = None
        self.error = why

    def _take(self, status: int, size: int, fresh: bool) -> bool:
        """Keep the frame just read into the buffer; True if it was a new, valid frame.

        ``fresh``: it certainly arrived just now (a blocking wait returned it, or it is not the first frame
        this reader saw); the first frame of a non-blocking read may have sat in the channel for hours.
        """
        if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
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
        except ach.AchException as exc:
            self._drop(f"{self.name}: {exc.reason}")
            return self.frame
        if status == ach.ACH_CORRUPT:
            self._drop(f"channel {self.name} is corrupt")
            return self.frame
        self._take(status, size, fresh=False)
        return self.frame

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
            except ach.AchException as exc:
                self._drop(f"{self.name}: {exc.reason}")
                return None
            if self._take(status, size, fresh=True):
                return self.frame

    def age(self) -> float | None:
        """Seconds since a new frame was seen; None if none has been seen arriving yet."""
        return None if self.new_at is None else time.monotonic() - self.new_at

    def close(self) -> None:
        self._drop("closed")


# --------------------------------------------------------------------------------------------- formatting


COLLIDE_PARTS: tuple[str, ...] = ("Hand", "Wrist", "Forearm", "Elbow", "Shoulder")
# (right index, left index) of each part in mds_collide_t.joint[]
COLLIDE_INDEX: dict[str, tuple[int, int]] = {
    "Hand": (mds.COLLIDE_R_HAND, mds.COLLIDE_L_HAND),
    "Wrist": (mds.COLLIDE_R_WRIST, mds.COLLIDE_L_WRIST),
    "Forearm": (mds.COLLIDE_R_FOREARM, mds.COLLIDE_L_FOREARM),
    "Elbow": (mds.COLLIDE_R_ELBOW, mds.COLLIDE_L_ELBOW),
    "Shoulder": (mds.COLLIDE_R_SHOULDER, mds.COLLIDE_L_SHOULDER),
}


def collision_parts(collide: mds.MDS_COLLIDE) -> list[str]:
    """Names of the parts flagged in a collide frame, e.g. ['L_HAND', 'R_HAND']."""
    return [mds.COLLIDE_PART_NAMES[i] for i in range(mds.MDS_COLLIDE_JNT_NUM) if collide.joint[i].isCollide]


def collision_summary(collide: mds.MDS_COLLIDE | None) -> str:
    """One line per ``isCollide`` value of the gate (mds_ach.nodes.collision): 1 held, 2 expert override, 3 in
    contact while moving out of it."""
    if collide is None:
        return f"unknown (nothing on {mds.MDS_CHAN_COLLIDE_NAME})"
    parts = " ".join(collision_parts(collide))
    if collide.isCollide == 2:
        return "EXPERT OVERRIDE passes a predicted collision: " + (parts or "-")
    if collide.isCollide == 3:
        return "CONTACT, only moves out of it pass (nothing held): " + (parts or "-")
    if collide.isCollide or parts:
        return "BLOCKED: " + (parts or "collision predicted")
    return "clear"


def collision_block(collide: mds.MDS_COLLIDE | None) -> list[str]:
    """The original read utility's ``[ Collisions ]`` table (rows Right/Left, 0/1 per part)."""
    lines = ["[ Collisions ]", "          " + "".join(f"{p:>10}" for p in COLLIDE_PARTS)]
    for side, k in (("Right", 0), ("Left", 1)):
        if collide is None:
            cells = "".join(f"{'-':>10}" for _ in COLLIDE_PARTS)
        else:
            cells = "".join(f"{int(bool(collide.joint[COLLIDE_INDEX[p][k]].isCollide)):>10}" for p in COLLIDE_PARTS)
        lines.append(f"{side:<10}{cells}")
    if collide is None:
        lines.append(f"Collide: unknown (no frames on {mds.MDS_CHAN_COLLIDE_NAME})")
    else:
        lines.append(f"Collide: {bool(collide.isCollide)!s:<6}  dt = {collide.time_dt:.7f}")
    return lines


def daemon_line(status: ctypes.Structure | None, age: float | None) -> str:
    """The daemon's health in one line (``mds-daemon-status``), flagged when it stopped publishing."""
    from mds_ach.robot.msgs.daemon_status import summary_line

    if status is None:
        return f"unknown (nothing on {mds.MDS_CHAN_DAEMON_STATUS_NAME})"
    line = summary_line(status)
    if age is not None and age > 1.0:
        line += f"  STALE: no update for {age:.1f} s"
    return line


def joint_fresh(status: ctypes.Structure | None, address: int) -> str:
    """'yes' when the daemon heard the joint's node recently, 'STALE' when not, 'BAD' when the node answers with
    implausible positions (not trusted), '-' for joints it does not poll, '?' without daemon status."""
    from mds_ach.robot.msgs.daemon_status import JOINT_BAD_REPLY, JOINT_ENABLED, JOINT_FRESH, JOINT_STALE

    if status is None:
        return "?"
    flags = status.joint_flags[address]
    if flags & JOINT_FRESH:
        return "yes"
    if flags & JOINT_STALE:
        return "STALE"
    if flags & JOINT_BAD_REPLY:
        return "BAD"
    return "-" if not flags & JOINT_ENABLED else "?"
