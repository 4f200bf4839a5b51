"""The daemon's CAN frames in a recording: taken from its CAN log (``daemon --can-log``) into ``/can/frames``, and
back out as python-can messages for ``mds-ach check-log``.

Why from the log file: the daemon writes every frame it sends and receives there already, off its real-time loop;
the recorder adds no second tap on the bus. The frames whose time stamps fall within the recording are taken when
it ends (each part of a split recording gets its own span).

The message type ``mds_ach_wire/msg/CanFrame`` is the classic ``can_msgs/Frame`` layout plus the direction
(``is_rx``), which check-log needs to tell the host's commands from the nodes' replies.

Imports: python-can, :mod:`mds_ach.bus.canio`.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can

from mds_ach.bus import canio
from mds_ach.record.schema import HEADER_DEFINITIONS

CAN_TOPIC = "/can/frames"
CAN_TYPE = "mds_ach_wire/msg/CanFrame"
CAN_TEXT = f"""std_msgs/Header header
uint32 id
bool is_rtr
bool is_extended
bool is_error
bool is_rx
uint8 dlc
uint8[] data
{HEADER_DEFINITIONS}"""
CAN_SCHEMA = (CAN_TYPE, CAN_TEXT)

WALL_CLOCK_FROM = 1e9
"""Stamps below this (s) are relative to the log's start (.asc), not wall-clock times: they cannot be placed."""


class CanLogError(ValueError):
    """The CAN log cannot be added to the recording; the message says why."""


def frames_between(path: str | Path, start_s: float, end_s: float) -> Iterator[can.Message]:
    """The frames of the CAN log at ``path`` stamped within [start_s, end_s] (wall clock, s)."""
    try:
        for msg in canio.read_log(path):
            if msg.timestamp < WALL_CLOCK_FROM:
                raise CanLogError(f"{path}: its time stamps are relative to the log's start (format "
                                  f"{canio.log_format(path)}); record the daemon's frames with --can-log FILE.log or "
                                  ".blf (wall-clock stamps)")
            if start_s <= msg.timestamp <= end_s:
                yield msg
    except canio.TornLogError:
        return  # the daemon is still writing its last line
    except canio.LogReadError as exc:
        raise CanLogError(str(exc)) from None


def to_message(msg: can.Message) -> dict[str, Any]:
    ns = int(round(msg.timestamp * 1e9))
    return {"header": {"stamp": {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}, "frame_id": ""},
            "id": int(msg.arbitration_id), "is_rtr": bool(msg.is_remote_frame),
            "is_extended": bool(msg.is_extended_id), "is_error": bool(msg.is_error_frame), "is_rx": bool(msg.is_rx),
            "dlc": int(msg.dlc), "data": list(bytes(msg.data))}


def from_message(decoded: Any, log_ns: int) -> can.Message:
    """The python-can message a recorded ``CanFrame`` was made from (stamped by its log time)."""
    return can.Message(timestamp=log_ns / 1e9, arbitration_id=int(decoded.id), is_extended_id=bool(decoded.is_extended),
                       is_remote_frame=bool(decoded.is_rtr), is_error_frame=bool(decoded.is_error),
                       is_rx=bool(decoded.is_rx), dlc=int(decoded.dlc), data=bytes(decoded.data))


def recorded_frames(path: str | Path) -> tuple[list[can.Message], str]:
    """The CAN frames of a recording (``/can/frames``) in file order, and why the file ends early ("" if it does
    not). ``RecordingError`` for a file that is no readable recording."""
    from mds_ach.record.recording import iter_messages  # the reader needs mcap: loaded only for recordings

    cut: list[str] = []
    frames = [from_message(r.message, r.log_ns) for r in iter_messages(path, {CAN_TOPIC}, cut)]
    return frames, "; ".join(cut)
