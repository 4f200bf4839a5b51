"""The achd wire protocol, without any I/O: header blocks and ``achpipe`` framing.

achd (golems/ach) bridges Ach channels over the network. A connection starts with a text header block
from each side, then carries frames: over TCP each frame is ``b"achpipe\\0"`` + little-endian u64 length +
payload; over UDP each datagram is one raw payload. Keeping the byte rules here, free of sockets and
shared memory, lets the parser be tested against a captured C session and reused by client and server.

Header rules (as achd's ``achd_parse_headers``): one ``key: value`` (or ``key=value``) per line, ``#``
starts a comment, CR is ignored, a line holds at most 1023 bytes before its ``\\n``, blank lines are
skipped, a line ``.`` ends the block, keys are case-insensitive, keys and values contain neither ``:``
nor ``=``, and an unknown key is an error.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass, field

ACHD_PORT = 8076
"""achd's TCP port (inetd ``achd serve``)."""

RECONNECT_PERIOD_S = 0.25
"""achd's ``ACHD_RECONNECT_NS``: a client retries a lost connection this often."""

LINE_LENGTH = 1024
"""achd's ``ACHD_LINE_LENGTH``: buffer for one header line, so at most 1023 bytes before ``\\n``."""

PIPE_MAGIC = b"achpipe\0"
PIPE_HEADER_SIZE = 16  # magic (8) + little-endian u64 payload length (8)
UDP_MAX_PAYLOAD = 65507
"""Largest payload one IPv4 UDP datagram can carry (achd checks 65535 and then fails in sendto)."""

# Ach status codes used on the wire (numbers from libach's ``enum ach_status``).
ACH_OK = 0
ACH_INVALID_NAME = 2
ACH_FAILED_SYSCALL = 4
ACH_EAGAIN = 5
ACH_ENOENT = 9
ACH_EINVAL = 12
ACH_BAD_HEADER = 14
ACH_EACCES = 15
STATUS_NAMES = {
    0: "ACH_OK", 1: "ACH_OVERFLOW", 2: "ACH_INVALID_NAME", 3: "ACH_BAD_SHM_FILE", 4: "ACH_FAILED_SYSCALL",
    5: "ACH_EAGAIN", 6: "ACH_MISSED_FRAME", 7: "ACH_TIMEOUT", 8: "ACH_EEXIST", 9: "ACH_ENOENT",
    10: "ACH_CLOSED", 11: "ACH_BUG", 12: "ACH_EINVAL", 13: "ACH_CORRUPT", 14: "ACH_BAD_HEADER",
    15: "ACH_EACCES", 16: "ACH_CANCELED", 17: "ACH_EFAULT", 18: "ACH_EINTR", 19: "ACH_ENOTSUP",
}

TRUE_WORDS = ("yes", "true", "1", "t", "y", "+", "aye")
FALSE_WORDS = ("no", "false", "0", "f", "n", "-", "nay")
TRANSPORTS = ("tcp", "udp")
DIRECTIONS = ("push", "pull")

_NAME_RE = re.compile(r"[A-Za-z0-9_.\-]{1,63}")
_INT_RE = re.compile(r"[+-]?[0-9]+")


class HeaderError(ValueError):
    """A header block achd would refuse; ``status`` is the Ach status to report (usually ACH_BAD_HEADER)."""

    def __init__(self, message: str, status: int = ACH_BAD_HEADER) -> None:
        super().__init__(message)
        self.status = status


class FrameError(ValueError):
    """The TCP byte stream is not achpipe framing any more (bad magic): the connection must be dropped."""


def status_name(status: int) -> str:
    return STATUS_NAMES.get(status, f"ACH_UNKNOWN_{status}")


def parse_bool(value: str) -> bool:
    """achd's boolean words, case-insensitive."""
    word = value.strip().lower()
    if word in TRUE_WORDS:
        return True
    if word in FALSE_WORDS:
        return False
    raise HeaderError(f"invalid boolean {value!r} (expected one of {'/'.join(TRUE_WORDS + FALSE_WORDS)})")


def valid_channel_name(name: str) -> bool:
    """libach's name rule: 1-63 of ``[A-Za-z0-9_.-]``, not starting with ``.``.

    A remote peer picks the name, and it becomes part of a ``/dev/shm`` path, so it is checked here.
    """
    return bool(_NAME_RE.fullmatch(name)) and not name.startswith(".")


def _parse_int(key: str, value: str, minimum: int, maximum: int) -> int:
    text = value.strip()
    if not _INT_RE.fullmatch(text):
        raise HeaderError(f"invalid {key} {value!r}: not an integer")
    number = int(text)
    if not minimum <= number <= maximum:
        raise HeaderError(f"invalid {key} {number}: outside {minimum}..{maximum}")
    return number


@dataclass
class Headers:
    """One side's header block. ``None`` means "not sent".

    ``direction`` is from the point of view of the side that reads the request: a client that wants to
    pull sends ``direction: push`` (the server pushes).
    """

    channel_name: str | None = None
    transport: str | None = None
    direction: str | None = None
    get_last: bool | None = None
    period_ns: int | None = None
    remote_port: int | None = None
    local_port: int | None = None
    remote_host: str | None = None
    frame_count: int | None = None
    frame_size: int | None = None
    tcp_nodelay: bool | None = None
    retry: bool | None = None
    status: int | None = None
    message: str | None = None
    extra: dict[str, str] = field(default_factory=dict)
    """Only for error reports: never filled by :func:`Headers.from_fields` (unknown keys are refused)."""

    @classmethod
    def from_fields(cls, fields: list[tuple[str, str]]) -> Headers:
        """Typed headers from parsed ``(key, value)`` pairs; later duplicates win, as in achd."""
        h = cls()
        for key, value in fields:
            h._set(key.lower(), value)
        return h

    def _set(self, key: str, value: str) -> None:
        if key == "channel-name":
            self.channel_name = value
        elif key == "transport":
            self.transport = value.lower()
        elif key == "direction":
            word = value.lower()
            if word not in DIRECTIONS:
                raise HeaderError(f"invalid direction {value!r} (expected push or pull)")
            self.direction = word
        elif key == "get-last":
            self.get_last = parse_bool(value)
        elif key == "period-ns":
            self.period_ns = _parse_int(key, value, 0, 2**63 - 1)
        elif key == "remote-port":
            self.remote_port = _parse_int(key, value, 0, 65535)
        elif key == "local-port":
            self.local_port = _parse_int(key, value, 0, 65535)
        elif key == "remote-host":
            self.remote_host = value
        elif key == "frame-count":
            self.frame_count = _parse_int(key, value, 0, 2**31 - 1)
        elif key == "frame-size":
            self.frame_size = _parse_int(key, value, 0, 2**31 - 1)
        elif key == "tcp-nodelay":
            self.tcp_nodelay = parse_bool(value)
        elif key == "retry":
            self.retry = parse_bool(value)
        elif key == "status":
            self.status = _parse_int(key, value, -(2**31), 2**31 - 1)
        elif key == "message":
            self.message = value
        else:
            raise HeaderError(f"invalid header {key!r}")

    def check_request(self) -> None:
        """What a server needs before it can serve: a valid channel name, transport and direction."""
        if not self.channel_name:
            raise HeaderError("no channel-name header")
        if not valid_channel_name(self.channel_name):
            raise HeaderError(f"invalid channel name {self.channel_name!r}", ACH_INVALID_NAME)
        if not self.transport:
            raise HeaderError("no transport header")
        if self.transport not in TRANSPORTS:
            raise HeaderError(f"transport {self.transport!r} not supported (tcp or udp)")
        if not self.direction:
            raise HeaderError("no direction header")
        if self.transport == "udp" and not self.remote_port:
            raise HeaderError("udp transport needs the client's remote-port header")


def _clean_value(value: str) -> str:
    """A value achd can parse back: no ``#``, ``:``, ``=`` or line breaks (its value pattern forbids them)."""
    return re.sub(r"[#:=\r\n]", " ", value).strip()


def _line(key: str, value: object, comment: str = "") -> bytes:
    text = f"{key}: {value}" + (f" # {comment}" if comment else "") + "\n"
    raw = text.encode("ascii", "replace")
    if len(raw) > LINE_LENGTH:
        raise HeaderError(f"header line for {key!r} longer than {LINE_LENGTH} bytes")
    return raw


def _checked(key: str, value: str) -> str:
    if value != _clean_value(value) or not value:
        raise HeaderError(f"{key} {value!r} cannot be sent in an achd header")
    return value


def encode_request(
    channel_name: str,
    transport: str,
    direction: str,
    get_last: bool = False,
    period_ns: int = 0,
    udp_port: int | None = None,
) -> bytes:
    """A client's request, byte for byte in achd's order.

    ``direction`` is the *server's* role (``push`` when this client pulls). A UDP client announces
    ``udp_port`` (its own datagram port) first, as achd's client does.
    """
    if transport not in TRANSPORTS:
        raise HeaderError(f"transport {transport!r} not supported (tcp or udp)")
    if direction not in DIRECTIONS:
        raise HeaderError(f"direction {direction!r} must be push or pull")
    if not valid_channel_name(channel_name):
        raise HeaderError(f"invalid channel name {channel_name!r}", ACH_INVALID_NAME)
    out = b""
    if transport == "udp":
        if udp_port is None:
            raise HeaderError("a udp request needs the client's udp_port")
        out += _line("remote-port", int(udp_port))
    out += _line("channel-name", channel_name)
    out += _line("transport", transport)
    out += _line("get-last", int(bool(get_last)))
    out += _line("direction", direction)
    if period_ns:
        out += _line("period-ns", int(period_ns))
    return out + b".\n"


def encode_response(frame_count: int, frame_size: int, udp_port: int | None = None) -> bytes:
    """A server's success response (achd: ``remote-port`` first for UDP, then sizes and status)."""
    out = b"" if udp_port is None else _line("remote-port", int(udp_port))
    out += _line("frame-count", int(frame_count))
    out += _line("frame-size", int(frame_size))
    out += _line("status", ACH_OK, status_name(ACH_OK))
    return out + b".\n"


def encode_error(status: int, message: str) -> bytes:
    """A server's refusal: status with its name as comment, then a message the C client can parse."""
    return _line("status", int(status), status_name(status)) + _line("message", _clean_value(message)) + b".\n"


def encode_headers(pairs: list[tuple[str, object]]) -> bytes:
    """Any block from ``(key, value)`` pairs; values are checked to be parseable by achd."""
    return b"".join(_line(_checked("key", k), _checked(k, str(v))) for k, v in pairs) + b".\n"


class HeaderParser:
    """Incremental header-block reader: feed bytes as they arrive, stop exactly after the ``.`` line.

    Bytes after the terminator belong to the data stream and are returned by :meth:`feed`, never eaten.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.fields: list[tuple[str, str]] = []
        self.done = False
        self.lines = 0

    def feed(self, data: bytes) -> bytes:
        """Consume ``data``; returns what follows the block once it is complete (else ``b""``)."""
        if self.done:
            return bytes(data)
        self._buf += data
        while not self.done:
            nl = self._buf.find(b"\n")
            if nl < 0:
                if len(self._buf.replace(b"\r", b"")) >= LINE_LENGTH:
                    raise HeaderError(f"header line {self.lines + 1} longer than {LINE_LENGTH - 1} bytes", 1)
                return b""
            raw = bytes(self._buf[:nl]).replace(b"\r", b"")
            del self._buf[: nl + 1]
            self.lines += 1
            if len(raw) >= LINE_LENGTH:
                raise HeaderError(f"header line {self.lines} longer than {LINE_LENGTH - 1} bytes", 1)
            self._line(raw)
        rest = bytes(self._buf)
        self._buf.clear()
        return rest

    def _line(self, raw: bytes) -> None:
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise HeaderError(f"header line {self.lines} is not text") from exc
        text = text.split("#", 1)[0].strip()
        if not text:
            return
        if text == ".":
            self.done = True
            return
        parts = re.split(r"[:=]", text)
        if len(parts) != 2 or not parts[0].strip():
            raise HeaderError(f"malformed header line {self.lines}: {raw[:80]!r}")
        self.fields.append((parts[0].strip().lower(), parts[1].strip()))

    def headers(self) -> Headers:
        if not self.done:
            raise HeaderError("header block not terminated by '.'")
        return Headers.from_fields(self.fields)


def parse_headers(data: bytes) -> tuple[Headers, bytes]:
    """Parse one complete block from ``data``; returns the headers and the bytes after it."""
    parser = HeaderParser()
    rest = parser.feed(data)
    if not parser.done:
        raise HeaderError("header block not terminated by '.'")
    return parser.headers(), rest


def encode_frame(payload: bytes | bytearray | memoryview) -> bytes:
    """One achpipe frame: magic, little-endian u64 length, payload."""
    return PIPE_MAGIC + struct.pack("<Q", len(payload)) + bytes(payload)


def frame_header(size: int) -> bytes:
    """The 16 bytes in front of a payload of ``size`` bytes (to send header and payload separately)."""
    return PIPE_MAGIC + struct.pack("<Q", size)


class FrameDecoder:
    """Incremental achpipe decoder for a TCP byte stream.

    Payloads larger than ``max_size`` are skipped (their bytes still consumed, so the stream stays in
    step) and counted in ``oversize``: a peer cannot make us allocate without bound. A bad magic means
    the stream is out of step and raises :class:`FrameError`.
    """

    def __init__(self, max_size: int = 16 * 1024 * 1024) -> None:
        self.max_size = max_size
        self.oversize = 0
        self._buf = bytearray()
        self._skip = 0

    @property
    def pending(self) -> int:
        """Bytes held for an incomplete frame."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[bytes]:
        """Add bytes; return every payload completed by them, in order."""
        self._buf += data
        frames: list[bytes] = []
        while True:
            if self._skip:
                n = min(self._skip, len(self._buf))
                del self._buf[:n]
                self._skip -= n
                if self._skip:
                    return frames
            if len(self._buf) < PIPE_HEADER_SIZE:
                if self._buf and not PIPE_MAGIC.startswith(bytes(self._buf[:8])):
                    raise FrameError(f"bad achpipe magic {bytes(self._buf[:8])!r}")
                return frames
            if self._buf[:8] != PIPE_MAGIC:
                raise FrameError(f"bad achpipe magic {bytes(self._buf[:8])!r}")
            (size,) = struct.unpack_from("<Q", self._buf, 8)
            if size > self.max_size:
                self.oversize += 1
                del self._buf[:PIPE_HEADER_SIZE]
                self._skip = size
                continue
            end = PIPE_HEADER_SIZE + size
            if len(self._buf) < end:
                return frames
            frames.append(bytes(self._buf[PIPE_HEADER_SIZE:end]))
            del self._buf[:end]
