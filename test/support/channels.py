"""The one "newest frame" reader of the tests (and benchmarks).

Two needs, two forms: ``newest(name, ctype)`` opens the channel, reads its newest frame whether or not anyone
saw it before, and closes it again (read-only: it never consumes a frame for another handle); ``Newest`` keeps
a handle open and remembers the last frame, for a loop that asks "what is the state now?" many times
(the last one again when nothing new was published).
"""

from __future__ import annotations

import ctypes
from typing import Generic, TypeVar

import mds_ach as mds
from mds_ach import ach
from mds_ach.robot.channels import StructChannel

T = TypeVar("T", bound=ctypes.Structure)


def newest(name: str, ctype: type[T]) -> T | None:
    """The newest frame of channel ``name`` (even if seen before), or None if it has none of ``ctype``'s size."""
    obj = ctype()
    with ach.Channel(name, create=False) as chan:
        status, size = chan.get(obj, last=True, copy=True)
    return obj if status in (ach.ACH_OK, ach.ACH_MISSED_FRAME) and size == ctypes.sizeof(ctype) else None


def state() -> mds.MDS_STATE:
    """The newest mds-state frame; fails if the daemon never published one."""
    st = newest(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE)
    assert st is not None, "no frame on mds-state"
    return st


class Newest(Generic[T]):
    """An open reader of one channel: ``get()`` is the newest frame, or the last one seen if nothing new came."""

    def __init__(self, name: str, ctype: type[T]) -> None:
        self.name = name
        self.channel: StructChannel[T] = StructChannel(name, ctype)
        self.last: T | None = None

    def get(self) -> T | None:
        frame = self.channel.latest()
        if frame is not None:
            self.last = frame
        return self.last

    def require(self) -> T:
        """``get()``, failing if the channel never had a frame."""
        frame = self.get()
        assert frame is not None, f"no frame on {self.name}"
        return frame

    def close(self) -> None:
        self.channel.close()
