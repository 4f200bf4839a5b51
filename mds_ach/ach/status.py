"""Ach status codes, ``get``/``put`` option flags, defaults and the exception every ``ach`` call raises.

The numbers are libach's (``enum ach_status``, ``ACH_O_*``), so status codes mean the same in C and Python.

Imports: nothing of mds_ach (the bottom of the ``ach`` package).
"""

from __future__ import annotations

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
    ACH_BAD_SHM_FILE: "not an Ach channel file (a link, a FIFO, a directory, a bad magic number or too short)",
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

CLOCK_REALTIME = 0
CLOCK_MONOTONIC = 1


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
