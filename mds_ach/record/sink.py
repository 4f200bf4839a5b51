"""The MCAP file(s) of a recording: ROS 2 messages through ``mcap-ros2-support``'s writer, split by size or time,
stopped cleanly before the disk (or the process's file-size limit) is full.

Why stop early: an MCAP file is only complete with its summary and footer, written at the end. So the sink looks
at the free space (``statvfs``) and the file-size limit (``RLIMIT_FSIZE``) as it writes and stops while a chunk and
the summary still fit (``headroom``): the file then ends properly and holds everything up to the stop. Should a
write still fail (another process filled the disk in between), the file is cut back to the end of its last whole
record, so it reads up to there (:mod:`mds_ach.record.recording` reads such a file, as it reads one cut by SIGKILL).

Imports: ``mcap``, ``mcap_ros2``, :mod:`mds_ach.record.schema`.
"""

from __future__ import annotations

import errno
import os
import resource
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.records import Schema
from mcap_ros2.writer import Writer

CHUNK_SIZE = 1024 * 1024
"""Bytes of messages per chunk (before compression): what a SIGKILL can lose at most."""
HEADROOM = 2 * CHUNK_SIZE + 1024 * 1024
"""Bytes that must stay free (and below the file-size limit) to finish a file: the chunk in progress, the summary."""
CHECK_EVERY_S = 0.5
PROFILE_LIBRARY = "mds_ach record"


class DiskFullError(Exception):
    """The recording stopped because the disk or the file-size limit left no room; the message says which."""


@dataclass
class Latched:
    """A message every part of a split recording starts with (a channel written once, e.g. ``mds-limits``)."""

    topic: str
    schema: tuple[str, str]
    message: dict[str, Any]
    log_ns: int
    publish_ns: int
    sequence: int = 0


class _CheckedFile:
    """The file object the MCAP writer writes to: unbuffered, each write whole or not at all (a failed write is cut
    back off), so the file always ends at a record boundary."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self.pos = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data)
        start = self.pos
        try:
            while view:
                n = os.write(self.fd, view)
                view = view[n:]
                self.pos += n
        except OSError:
            os.ftruncate(self.fd, start)
            os.lseek(self.fd, start, os.SEEK_SET)
            self.pos = start
            raise
        return len(data)

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass

    def close(self) -> None:
        os.close(self.fd)


def _fsize_limit() -> int | None:
    soft, _hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    return None if soft == resource.RLIM_INFINITY else soft


class RecordingSink:
    """Writes messages to ``path``, or with a split to ``<stem>-0001.mcap``, ``<stem>-0002.mcap``, ... next to it.

    ``split_bytes`` / ``split_seconds``: start a new part when the current one reaches that size or age (each part
    is a complete MCAP file that starts with the latched messages). ``metadata`` is written into every part.
    ``before_finish(sink, start, end)`` may add messages (``write_now``) to a part before it is finished, ``start``
    and ``end`` its span (wall clock, s).
    """

    def __init__(self, path: Path, *, split_bytes: int | None = None, split_seconds: float | None = None,
                 metadata: dict[str, str] | None = None, headroom: int = HEADROOM, chunk_size: int = CHUNK_SIZE,
                 before_finish: Callable[[RecordingSink, float, float], None] | None = None) -> None:
        self.path = path
        self.split_bytes = split_bytes
        self.split_seconds = split_seconds
        self.metadata = dict(metadata or {})
        self.headroom = headroom
        self.chunk_size = chunk_size
        self.before_finish = before_finish
        self.parts: list[Path] = []
        self.messages = 0
        self.bytes_done = 0  # bytes of the finished parts
        self._latched: dict[str, Latched] = {}
        self._file: _CheckedFile | None = None
        self._writer: Writer | None = None
        self._schemas: dict[tuple[str, str], Schema] = {}
        self._part_started = 0.0
        self._part_started_wall = 0.0
        self._next_check = 0.0
        self.broken = ""  # why the current part could not be finished (then it ends at its last whole record)
        self._open_part()

    @property
    def split(self) -> bool:
        return self.split_bytes is not None or self.split_seconds is not None

    def _part_path(self) -> Path:
        if not self.split:
            return self.path
        return self.path.with_name(f"{self.path.stem}-{len(self.parts) + 1:04d}{self.path.suffix or '.mcap'}")

    def _open_part(self) -> None:
        path = self._part_path()
        self._check_room(path.parent, 0)
        self._file = _CheckedFile(path)
        self.parts.append(path)
        self._writer = Writer(self._file, chunk_size=self.chunk_size)  # type: ignore[arg-type]  # a file-like
        self._schemas = {}
        self._part_started = time.monotonic()
        self._part_started_wall = time.time()
        if self.metadata:
            self._writer.add_metadata("mds_ach", self.metadata)
        for latched in self._latched.values():
            self._write(latched.topic, latched.schema, latched.message, latched.log_ns, latched.publish_ns,
                        latched.sequence)

    def _check_room(self, directory: Path, size: int) -> None:
        st = os.statvfs(directory)
        free = st.f_bavail * st.f_frsize
        if free < self.headroom:
            raise DiskFullError(f"{directory}: {free / 1e6:.1f} MB free on the disk, a recording needs "
                           f"{self.headroom / 1e6:.1f} MB to finish its file")
        limit = _fsize_limit()
        if limit is not None and size + self.headroom > limit:
            raise DiskFullError(f"the file-size limit of this process (ulimit -f: {limit} bytes) is reached")

    def _write(self, topic: str, schema: tuple[str, str], message: dict[str, Any], log_ns: int,
               publish_ns: int, sequence: int = 0) -> None:
        assert self._writer is not None
        registered = self._schemas.get(schema)
        if registered is None:
            registered = self._schemas[schema] = self._writer.register_msgdef(*schema)
        self._writer.write_message(topic, registered, message, log_time=log_ns, publish_time=publish_ns,
                                   sequence=sequence % 2**32)

    def write(self, topic: str, schema: tuple[str, str], message: dict[str, Any], log_ns: int, publish_ns: int,
              latch: bool = False, sequence: int = 0) -> None:
        """One message (``schema`` = (ROS 2 type, definition)); ``latch``: also start every later part with it;
        ``sequence``: the MCAP message's sequence (the frame's Ach sequence number, modulo 2^32).
        Raises ``DiskFullError`` (the part is finished first) when there is no room left."""
        now = time.monotonic()
        if now >= self._next_check:
            self._next_check = now + CHECK_EVERY_S
            assert self._file is not None
            try:
                self._check_room(self._file.path.parent, self._file.tell())
            except DiskFullError:
                self.close()
                raise
            if (self.split_seconds is not None and now - self._part_started >= self.split_seconds) or (
                    self.split_bytes is not None and self._file.tell() >= self.split_bytes):
                self._finish_part()
                self._open_part()
        if latch:
            self._latched[topic] = Latched(topic, schema, message, log_ns, publish_ns, sequence)
        try:
            self._write(topic, schema, message, log_ns, publish_ns, sequence)
        except OSError as exc:
            self._fail(exc)
        self.messages += 1

    def write_now(self, topic: str, schema: tuple[str, str], message: dict[str, Any], log_ns: int,
                  publish_ns: int) -> None:
        """One message into the current part, without the room and split checks (``before_finish``)."""
        try:
            self._write(topic, schema, message, log_ns, publish_ns)
        except OSError as exc:
            self._fail(exc)
        self.messages += 1

    def _fail(self, exc: OSError) -> None:
        what = "the disk is full" if exc.errno == errno.ENOSPC else (
            "the file-size limit (ulimit -f) is reached" if exc.errno == errno.EFBIG else str(exc))
        assert self._file is not None
        self.broken = (f"{self._file.path}: {what}; the file ends at its last whole record ({self._file.tell()} "
                       "bytes, no summary): mds-ach plot/check-log/replay read it up to there")
        self._file.close()
        self._file, self._writer = None, None
        raise DiskFullError(self.broken) from exc

    def _finish_part(self) -> None:
        if self._writer is None or self._file is None:
            return
        if self.before_finish is not None:
            self.before_finish(self, self._part_started_wall, time.time())
        try:
            self._writer.finish()
        except (OSError, McapError) as exc:
            if isinstance(exc, OSError):
                self._fail(exc)
            raise
        self.bytes_done += self._file.tell()
        self._file.close()
        self._file, self._writer = None, None

    def size(self) -> int:
        """Bytes written so far, every part."""
        return self.bytes_done + (self._file.tell() if self._file is not None else 0)

    def close(self) -> None:
        """Finish the current part (summary, footer); a part that failed stays as it was cut."""
        self._finish_part()
