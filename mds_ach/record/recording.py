"""Reading a recording back: every message of an MCAP file, decoded, in the order it was written.

The file is read front to back (``mcap``'s ``StreamReader``), so a recording that never got its summary (the
recorder was killed with SIGKILL, or the disk filled under it) reads up to its last whole chunk: ``cut`` then says
so. A file that is no MCAP recording at all, or is damaged before its first message, raises
``RecordingError`` with a message for people.

Imports: ``mcap``, ``mcap_ros2``, :mod:`mds_ach.record.schema`.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import InvalidMagic, McapError
from mcap.records import Channel, DataEnd, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory

from mds_ach.record import schema as wire
from mds_ach.robot import contracts
from mds_ach.robot.msgs import Packed

MCAP_SUFFIX = ".mcap"


class RecordingError(ValueError):
    """The file cannot be read as a recording; the message names it and says why."""


def is_recording(path: str | Path) -> bool:
    """An MCAP file (by its magic bytes, whatever its name)."""
    try:
        with open(path, "rb") as f:
            return f.read(8) == b"\x89MCAP0\r\n"
    except OSError:
        return False


@dataclass(frozen=True)
class Recorded:
    """One message: topic, log time (ns, wall clock: when the recorder took it), publish time (ns: the frame's own
    stamp where it has one), the decoded ROS 2 message and its sequence (the frame's Ach sequence number mod 2^32)."""

    topic: str
    log_ns: int
    publish_ns: int
    message: Any
    sequence: int = 0


@dataclass
class Recording:
    """A recording read into memory: messages per topic in file order, its metadata, and whether it was cut."""

    path: Path
    messages: dict[str, list[Recorded]] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    cut: str = ""  # why the file ends early ("" for a complete file)

    @property
    def count(self) -> int:
        return sum(len(v) for v in self.messages.values())

    def channel(self, name: str) -> list[Recorded]:
        return self.messages.get(wire.topic(name), [])

    def frames(self, name: str) -> Iterator[tuple[int, Packed]]:
        """(log ns, frame) of channel ``name``, the frames rebuilt from their messages."""
        ws = wire.wire_schema(contracts.contract(name).struct)
        for r in self.channel(name):
            yield r.log_ns, ws.from_message(r.message)

    @property
    def start_ns(self) -> int | None:
        times = [v[0].log_ns for v in self.messages.values() if v]
        return min(times) if times else None

    @property
    def end_ns(self) -> int | None:
        times = [v[-1].log_ns for v in self.messages.values() if v]
        return max(times) if times else None


def iter_messages(path: str | Path, topics: set[str] | None = None,
                  cut: list[str] | None = None, metadata: dict[str, dict[str, str]] | None = None
                  ) -> Iterator[Recorded]:
    """Every message of ``path`` (only ``topics`` when given), decoded, in file order. A file that ends early is
    read up to its last whole record and the reason appended to ``cut``; ``metadata`` collects Metadata records."""
    path = Path(path)
    if path.exists() and not path.is_dir() and not is_recording(path):
        raise RecordingError(f"{path}: not an MCAP recording (it does not start with the MCAP magic bytes)")
    try:
        f = open(path, "rb")
    except OSError as exc:
        raise RecordingError(f"{path}: cannot open: {exc.strerror or exc}") from None
    factory = DecoderFactory()
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    decoders: dict[int, Any] = {}
    complete = False
    n = 0
    with f:
        try:
            for record in StreamReader(f, skip_magic=False).records:
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Metadata) and metadata is not None:
                    metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Message):
                    ch = channels.get(record.channel_id)
                    if ch is None or (topics is not None and ch.topic not in topics):
                        continue
                    decoder = decoders.get(ch.id)
                    if decoder is None:
                        decoder = factory.decoder_for(ch.message_encoding, schemas.get(ch.schema_id))
                        if decoder is None:
                            continue  # not a ROS 2 message: not ours
                        decoders[ch.id] = decoder
                    n += 1
                    yield Recorded(ch.topic, record.log_time, record.publish_time, decoder(record.data),
                                   record.sequence)
                elif isinstance(record, DataEnd | Footer):
                    complete = True
        except InvalidMagic:
            raise RecordingError(f"{path}: not an MCAP recording (bad magic bytes)") from None
        except (McapError, struct.error, EOFError, ValueError) as exc:
            if n == 0 and not channels:
                raise RecordingError(f"{path}: damaged before its first message ({type(exc).__name__}: {exc})") \
                    from None
            if cut is not None:
                cut.append(f"{path}: the file ends early ({type(exc).__name__}), read up to its last whole record "
                           f"({n} messages): the recorder was killed or the disk was full")
            return
    if not complete and cut is not None:
        cut.append(f"{path}: the file has no summary (the recorder was killed?): read up to its last whole record "
                   f"({n} messages)")


def load(path: str | Path, topics: set[str] | None = None) -> Recording:
    """The whole recording at ``path`` (``topics``: only these)."""
    cut: list[str] = []
    rec = Recording(Path(path))
    for r in iter_messages(path, topics, cut, rec.metadata):
        rec.messages.setdefault(r.topic, []).append(r)
    rec.cut = "; ".join(cut)
    return rec
