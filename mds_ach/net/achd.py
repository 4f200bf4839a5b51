"""achd-compatible network bridge: push a local Ach channel to a remote host, pull a remote one here.

It speaks the C ``achd`` protocol (see :mod:`mds_ach.net.protocol`), so either end may be the C tool:
our client talks to ``achd serve`` (inetd), and the C client ``achd push|pull`` talks to our
:class:`Server`. Differences from the C tool, all on the safe side:

* the server is a real listening TCP server, bound to loopback unless told otherwise, and it only lets a
  client write the channels on its allow-list (by default the safe pipeline inputs, ``mds-ref`` included, never the
  daemon's input ``mds-ref-gated``);
* frames whose size does not match the channel's struct, or that fail validation (NaN/Inf references,
  bad modes), are dropped and counted, never written; an ``mds-hold`` request the mux would refuse (a CANCEL
  target past the limits or away from the joint's reference, ``check_cancel``) is not written either, and the
  connection is answered with achd's error block (``ACH_EINVAL`` and the reason) and closed;
* a client reconnects after a drop and re-sends its newest frame, so a reconnect never loses the newest frame.
  Our server, like achd, starts a sending connection with the first frame written after the client connected
  (achd flushes the channel); ``send_latest_on_connect`` (``--newest-on-connect``) starts it with the newest
  frame instead. Neither achd offers a pulling client a frame written before it connected (``get-last`` picks
  the newest of the frames that arrive afterwards): the level channels a station needs at once are re-published
  by their writers (the daemon puts ``mds-param`` every second, the collision gate ``mds-collide`` at 10 Hz);
* queues are bounded and the newest frame wins: the channel ring is the only queue, read newest-first
  with get-last, and the socket send buffer is kept small;
* no peer can lock others out: each remote address may hold a few connections (``max_per_peer``), loopback
  peers (the robot's own tools, every operator coming through an SSH tunnel) have pools of their own that
  remote peers cannot use, one per local user (``mds_ach.net.peeruid``), and a connection that moves no data
  for ``idle_timeout_s`` is closed.

Usage as a tool (same verbs and short options as achd)::

    python -m mds_ach.net.achd [-p PORT] [-t tcp|udp] [-z REMOTE] [-u USEC] [-l] [-r] push|pull HOST CHANNEL
    python -m mds_ach.net.achd serve [--bind ADDR] [--port PORT] [--allow-write CHAN] [--allow-read CHAN]
"""

from __future__ import annotations

import argparse
import ctypes
import fnmatch
import ipaddress
import logging
import math
import select
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from typing import Any, TypedDict

from mds_ach import ach, logformat
from mds_ach.ach.watch import ReplacementCheck, replaced
from mds_ach.net import protocol as ap
from mds_ach.net.peeruid import peer_uid
from mds_ach.ratelog import RateLimitedLog, logger_fn
from mds_ach.robot import contracts
from mds_ach.robot.msgs import MDS_HOLD, MDS_JOINT_COUNT, MDS_REF
from mds_ach.robot.msgs.hold import check_cancel

log = logging.getLogger("mds_ach.net.achd")

POLL_S = 0.2
"""Every blocking wait (channel, socket) wakes at least this often to notice a stop request."""
SEND_BUFFER_BYTES = 128 * 1024
"""Socket send buffer of a sending link: small, so a slow link holds few stale frames (newest wins)."""
HEADER_TIMEOUT_S = 5.0
MAX_HEADER_BYTES = 32 * ap.LINE_LENGTH
MAX_SERVED_STATS = 256
REFUSED_RETRY_S = 2.0
"""Back-off after the server refused a request (missing channel, not allowed): slower than a drop."""
MAX_CLIENTS = 32
"""Connections from remote (non-loopback) peers together."""
MAX_PER_PEER = 8
"""Connections from one remote address: ``mds-ach remote`` opens at most 5, a second tool fits too."""
MAX_LOCAL_CLIENTS = 32
"""Connections from loopback (local tools, SSH-tunnelled operators) per local user (the uid owning the peer's
socket): pools remote peers cannot use, and no local user can use up another's (an operator's SSH forward runs
as the operator's user)."""
IDLE_TIMEOUT_S = 300.0
"""A served connection that sends and receives no frame for this long is closed (the client reconnects if it
still wants the channel). Long enough that a quiet operator link is rarely rebuilt."""

# Channels a client may write through our server unless told otherwise: the pipeline's inputs, so a
# remote reference still passes the mux, filter and collision gate (mds-ref too: the mux's 'direct' input).
# Never the daemon's input (mds-ref-gated) or mds-cmd.
SAFE_WRITABLE: tuple[str, ...] = contracts.REMOTE_WRITABLE


# --------------------------------------------------------------------------------------------------
# What may be written: the channel's contract (struct and validator, mds_ach.robot.contracts)
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FrameRule:
    """What a frame on one channel must be: its contract's struct and validator, or for a channel that is not
    an MDS channel (``contract`` None) any non-empty frame."""

    contract: contracts.Contract[Any] | None = None

    @property
    def ctype(self) -> type[ctypes.Structure] | None:
        return None if self.contract is None else self.contract.struct

    def problem(self, payload: bytes) -> tuple[str, str] | None:
        """``(kind, reason)`` why ``payload`` must not be written, kind ``size`` or ``invalid``; else None."""
        if not payload:
            return "size", "empty frame"
        return None if self.contract is None else self.contract.problem(payload)


def rule_for(channel: str) -> FrameRule:
    """The rule of ``channel`` from its contract (every ``mds-ref-*`` channel carries MDS_REF)."""
    return FrameRule(contracts.lookup(channel))


# --------------------------------------------------------------------------------------------------
# Counters
# --------------------------------------------------------------------------------------------------


@dataclass
class LinkStats:
    """What one link did; read by status reports and tests (plain ints, written by one thread)."""

    sent: int = 0
    written: int = 0
    dropped_size: int = 0
    dropped_invalid: int = 0
    dropped_oversize: int = 0
    dropped_put: int = 0
    stray_datagrams: int = 0
    send_errors: int = 0
    connects: int = 0
    last_error: str = ""
    last_drop: str = ""

    def as_dict(self) -> dict[str, object]:
        return asdict(self)


class ConnectionLostError(Exception):
    """The peer went away (EOF, reset, keepalive or user timeout)."""


class IdleConnectionError(ConnectionLostError):
    """A served connection moved no frame for the server's idle timeout and was closed."""


class FrameRefusedError(Exception):
    """A received request frame was refused (``HoldCheck``): the server tells the client why and closes."""


class RemoteRefusedError(Exception):
    """The server answered the request with a non-OK status."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(f"{ap.status_name(status)}: {message}")
        self.status = status


# --------------------------------------------------------------------------------------------------
# Channel access
# --------------------------------------------------------------------------------------------------


def _geometry(chan) -> tuple[int, int]:
    """``(frame_count, data_size)`` of an open channel: achd reports frame-size as data_size / count."""
    return chan.frame_count, chan.data_size


class _Source:
    """Reads new frames of a local channel for sending; keeps the newest one for a resend."""

    def __init__(self, chan, rule: FrameRule, get_last: bool, stats: LinkStats) -> None:
        self._ach = ach
        self.chan = chan
        self.rule = rule
        self.get_last = get_last
        self.stats = stats
        self.buf = bytearray(max(1, _geometry(chan)[1]))
        self.newest: bytes | None = None
        self.sent: bytes | None = None  # the last frame that went out, and when (monotonic)
        self.sent_at = -math.inf

    def next(self, timeout: float, last: bool | None = None, wait: bool = True) -> bytes | None:
        """The next frame to send (the newest with get-last), or None if none came within ``timeout``."""
        ach = self._ach
        status, size = self.chan.get(
            self.buf, wait=wait, last=self.get_last if last is None else last, timeout=timeout
        )
        if status not in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
            return None
        frame = bytes(self.buf[:size])
        problem = self.rule.problem(frame)
        if problem:
            _count_drop(self.stats, problem, "local frame not sent")
            return None
        self.newest = frame
        return frame


class RefLimitCheck:
    """The one limit authority at the network door (issue #17): a reference frame a peer writes into one of our
    ``mds-ref-*`` inputs is refused when a joint it *changes* is outside the effective limits (``mds-limits``).

    Changed, as the mux counts it: compared with the previous frame this link wrote, the first one with the
    channel's newest frame (read when the link starts), so a read-modify-write client re-sending a pose the robot
    is at (perhaps outside the limits after power-on) is not refused for joints it does not move. Into a channel
    that never had a frame (no mux ran: the mux takes frames waiting at its start as old, never applies them)
    the first frame is only the base.

    Into a *legacy* input (config/mux.yaml ``legacy: true``: ``mds-ref-filter``, ``mds-ref``) the mux clamps an
    out-of-limit value as the original hardware stopped at its limits (issue #26): the same frame pushed over the
    network is then passed on like a local put (``clamps``); only a non-finite value is refused there."""

    def __init__(self, chan, limits: Any, clamps: bool = False) -> None:
        self.limits = limits
        self.clamps = clamps
        self.base: Any = None
        buf = bytearray(max(1, _geometry(chan)[1]))
        status, size = chan.get(buf, last=True)
        if status in (ach.ACH_OK, ach.ACH_MISSED_FRAME) and size == ctypes.sizeof(MDS_REF):
            self.base = MDS_REF.from_buffer_copy(buf)

    @classmethod
    def for_channel(cls, chan, name: str) -> RefLimitCheck | None:
        """A check for the controller inputs (``mds-ref-*`` but the daemon's own input), else None."""
        found = contracts.lookup(name)
        if found is None or found.struct is not MDS_REF or name == contracts.MDS_CHAN_DAEMON_INPUT_NAME:
            return None
        from mds_ach.kinematics.limits import current_limits  # numpy and the URDF only where references come in
        from mds_ach.nodes.mux import load_config  # which inputs the mux clamps: one definition, config/mux.yaml

        try:
            clamps = any(c.channel == name and c.legacy for c in load_config()["controllers"])
        except ValueError:  # no readable mux config: judge as a non-legacy input (refuse rather than pass on)
            clamps = False
        return cls(chan, current_limits(), clamps)

    def problem(self, payload: bytes) -> tuple[str, str] | None:
        """``("invalid", reason)`` when the frame changes a joint to a value outside its limits, else None (then
        the frame is the new base)."""
        ref = MDS_REF.from_buffer_copy(payload)
        base = self.base if self.base is not None else ref
        changed = {a: ref.joint[a].ref for a in range(MDS_JOINT_COUNT)
                   if self.limits.valid[a] and ref.joint[a].ref != base.joint[a].ref}
        if self.clamps:  # the mux clamps finite values on this input; a non-finite one it refuses whole
            changed = {a: v for a, v in changed.items() if not math.isfinite(v)}
        problems = self.limits.problems(changed)
        if problems:
            return "invalid", "refused by the joint limits: " + "; ".join(problems)
        self.base = ref
        return None


class HoldCheck:
    """``check_cancel`` at the network door (issue 25): an ``mds-hold`` request a peer writes is refused when the mux
    would refuse it, judged as the mux judges it: the effective limits (``mds-limits``) and the joint's reference
    now, ``mds-ref-gated`` where it has one, else the mux output (``mds-ref-mux``). A CANCEL stops, it never
    moves; a refused request is not written and the client is told why (``FrameRefusedError``)."""

    def __init__(self, limits: Any) -> None:
        self.limits = limits

    @classmethod
    def for_channel(cls, name: str) -> HoldCheck | None:
        if name != contracts.MDS_CHAN_HOLD_NAME:
            return None
        from mds_ach.kinematics.limits import current_limits  # numpy and the URDF only where requests come in

        return cls(current_limits())

    @staticmethod
    def reference() -> list[float] | None:
        """The reference now by address, as the mux takes it (NaN where unknown); None when neither channel has
        a frame."""
        from mds_ach.robot.channels import StructChannel

        ref: list[float] | None = None
        for name in (contracts.MDS_CHAN_REF_MUX_NAME, contracts.MDS_CHAN_REF_GATED_NAME):  # gated wins
            try:
                with StructChannel.of(name, create=False) as chan:
                    frame = chan.latest()
            except Exception:  # no such channel here, or one the stack must not trust: no reference from it
                continue
            if frame is None:
                continue
            values = [float(j.ref) for j in frame.joint]
            ref = [v if math.isfinite(v) else (ref[a] if ref is not None else math.nan) for a, v in enumerate(values)]
        return ref

    def problem(self, payload: bytes) -> tuple[str, str] | None:
        """``("refused", reason)`` for a request the mux would refuse, else None."""
        hold = MDS_HOLD.from_buffer_copy(payload)
        reason = check_cancel(hold, self.limits, self.reference())
        return None if reason is None else ("refused", reason)


class _Sink:
    """Writes received frames into a local channel, after the size and content checks (and, for the reference
    inputs and the hold requests a peer writes into our server, the limit and cancel checks)."""

    def __init__(self, chan, rule: FrameRule, stats: LinkStats,
                 limits: RefLimitCheck | HoldCheck | None = None) -> None:
        self.chan = chan
        self.rule = rule
        self.stats = stats
        self.limits = limits
        self._ach = ach

    def put(self, payload: bytes) -> None:
        problem = self.rule.problem(payload)
        if problem is None and self.limits is not None:
            problem = self.limits.problem(payload)
        if problem:
            _count_drop(self.stats, problem, "received frame dropped")
            if problem[0] == "refused":
                raise FrameRefusedError(problem[1])
            return
        try:
            self.chan.put(payload)
        except self._ach.AchException as exc:
            self.stats.dropped_put += 1
            self.stats.last_drop = f"put failed: {exc}"
            return
        self.stats.written += 1


CHANNEL_CHECK_S = 1.0
"""How often a streaming loop checks that its channel file is still the one it opened."""


def channel_replaced(chan: ach.Channel) -> bool:
    """True when the channel's file was removed or re-created since ``chan`` opened it."""
    return replaced(chan)


class _ChannelWatch(ReplacementCheck):
    """Raises :class:`ConnectionLostError` from a streaming loop once its channel has been replaced."""

    def __init__(self, chan: ach.Channel) -> None:
        super().__init__(chan, CHANNEL_CHECK_S)

    def check(self) -> None:
        if self.due_and_replaced():
            raise ConnectionLostError(f"channel {self.chan.name} was removed or re-created")


_DROP_LOG = RateLimitedLog(logger_fn(log))


def _count_drop(stats: LinkStats, problem: tuple[str, str], what: str) -> None:
    kind, reason = problem
    if kind == "size":
        stats.dropped_size += 1
        n = stats.dropped_size
    else:
        stats.dropped_invalid += 1
        n = stats.dropped_invalid
    stats.last_drop = f"{kind}: {reason}"
    # A flood must not flood the log: one line per change of kind per link, repeats counted (the exact counts
    # are in the link's stats).
    _DROP_LOG(f"{what}@{id(stats):x}", f"{what} ({kind} #{n}): {reason}", kind=kind)


# --------------------------------------------------------------------------------------------------
# Sockets and the two data loops
# --------------------------------------------------------------------------------------------------


def _tune_tcp(sock: socket.socket, dead_after_s: float, sending: bool) -> None:
    """No Nagle delay; keepalive and a user timeout so a dead link is noticed in ``dead_after_s``."""
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    idle = max(1, int(dead_after_s / 2))
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE, idle)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPINTVL, 1)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT, max(1, int(dead_after_s) - idle))
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_USER_TIMEOUT, int(dead_after_s * 1000))
    if sending:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER_BYTES)


@dataclass
class _Conn:
    """One negotiated connection: TCP (data or control) plus, for UDP, the datagram socket and peer."""

    tcp: socket.socket
    udp: socket.socket | None = None
    udp_peer: tuple[str, int] | None = None
    leftover: bytes = b""
    headers: ap.Headers = field(default_factory=ap.Headers)
    refusal: ap.HeaderParser | None = None  # a client's: the server's error block for a refused frame, as it arrives

    def close(self) -> None:
        for s in (self.tcp, self.udp):
            if s is not None:
                try:
                    s.close()
                except OSError:
                    pass


UDP_RECEIVE_BUFFER_BYTES = 4 * 1024 * 1024
"""Receive buffer of a datagram socket (capped by the kernel's ``net.core.rmem_max``): room for about 150
``mds-state`` datagrams (14 KB, fragmented), so a receiver that was not scheduled for a while (a loaded machine)
finds them queued instead of dropped by the kernel (``RcvbufErrors`` in /proc/net/snmp). The default (208 KiB)
held 7: under CPU load our receiver lost up to 100 of 6,000 frames there where golems' C receiver lost 1."""
UDP_SEND_WAIT_S = 0.05
"""A datagram send that finds the socket buffer full waits this long for room, as golems' achd does (it polls
for POLLOUT before every send), before the datagram is counted as lost."""
PEER_CHECK_S = 0.02
"""How often a sending loop that is busy with frames looks at its TCP connection (a system call): not for every
frame, which at 1 kHz was a quarter of the sender's time."""


def _udp_socket(tcp: socket.socket) -> socket.socket:
    """A datagram socket on the TCP connection's local address, any port (achd binds INADDR_ANY)."""
    udp = socket.socket(tcp.family, socket.SOCK_DGRAM)
    udp.bind((tcp.getsockname()[0], 0))
    udp.setblocking(False)
    try:
        udp.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RECEIVE_BUFFER_BYTES)
    except OSError:  # the kernel caps it at rmem_max; a refusal only leaves the default
        pass
    return udp


def _read_headers(sock: socket.socket, timeout: float) -> tuple[ap.Headers, bytes]:
    """Read one header block from ``sock``; returns it and the bytes that came after it."""
    parser = ap.HeaderParser()
    deadline = time.monotonic() + timeout
    total = 0
    while not parser.done:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise ap.HeaderError(f"no complete header block within {timeout:.0f} s")
        sock.settimeout(remaining)
        try:
            data = sock.recv(4096)
        except TimeoutError as exc:
            raise ap.HeaderError(f"no complete header block within {timeout:.0f} s") from exc
        if not data:
            raise ConnectionLostError("connection closed during the header exchange")
        total += len(data)
        if total > MAX_HEADER_BYTES:
            raise ap.HeaderError(f"header block longer than {MAX_HEADER_BYTES} bytes")
        rest = parser.feed(data)
    return parser.headers(), rest


def _peer_closed(conn: _Conn, refusals: bool = False) -> bool:
    """On a connection where the peer never sends, readable means EOF or reset (achd's rule too). With
    ``refusals`` (a client sending to our server) bytes that arrive are the server's error block for a refused
    frame: raises ``RemoteRefusedError`` with its status and message once the block is complete."""
    readable, _, _ = select.select([conn.tcp], [], [], 0)
    if not readable:
        return False
    try:
        data = conn.tcp.recv(4096)
    except OSError:
        return True
    if data and refusals:
        if conn.refusal is None:
            conn.refusal = ap.HeaderParser()
        try:
            conn.refusal.feed(data)
        except ap.HeaderError:  # not an error block: ignored, as achd ignores what a receiver sends
            conn.refusal = None
            return False
        if conn.refusal.done:
            headers = conn.refusal.headers()
            if headers.status is not None and headers.status != ap.ACH_OK:
                raise RemoteRefusedError(headers.status, headers.message or "frame refused")
    return not data


def _send(conn: _Conn, payload: bytes, stats: LinkStats) -> None:
    if conn.udp is None:
        try:
            conn.tcp.sendall(ap.frame_header(len(payload)) + payload)
        except OSError as exc:
            raise ConnectionLostError(f"send failed: {exc}") from exc
        stats.sent += 1
        return
    if len(payload) > ap.UDP_MAX_PAYLOAD:
        stats.dropped_oversize += 1
        stats.last_drop = f"{len(payload)} bytes do not fit one UDP datagram"
        return
    try:
        assert conn.udp_peer is not None  # set together with conn.udp
        try:
            conn.udp.sendto(payload, conn.udp_peer)
        except BlockingIOError:  # socket buffer full: wait a little for room, as achd waits for POLLOUT
            select.select([], [conn.udp], [], UDP_SEND_WAIT_S)
            conn.udp.sendto(payload, conn.udp_peer)
    except BlockingIOError:
        stats.send_errors += 1  # still full: this datagram is lost, the next one is newer anyway
        return
    except OSError as exc:  # e.g. ENETUNREACH while the link is down: the TCP control link decides
        stats.send_errors += 1
        stats.last_error = f"udp send: {exc}"
        return
    stats.sent += 1


class _IdleWatch:
    """Raises :class:`ConnectionLostError` once a connection moved no frame for ``timeout`` s (None: never)."""

    def __init__(self, timeout: float | None) -> None:
        self.timeout = timeout
        self.last = time.monotonic()

    def active(self) -> None:
        self.last = time.monotonic()

    def check(self) -> None:
        if self.timeout is not None and time.monotonic() - self.last > self.timeout:
            raise IdleConnectionError(f"idle: no frame sent or received for {self.timeout:g} s")


def _run_sender(
    conn: _Conn, source: _Source, stats: LinkStats, stop: threading.Event, period_ns: int, first: bytes | None,
    idle_timeout: float | None = None, refusals: bool = False,
) -> None:
    """Send each new frame of ``source`` until stopped, the connection is lost or it was idle for
    ``idle_timeout`` s; with ``refusals`` (a client) until the server refused a frame (``RemoteRefusedError``)."""
    period = period_ns / 1e9
    last_sent = 0.0
    watch = _ChannelWatch(source.chan)
    idle = _IdleWatch(idle_timeout)
    if first is not None:
        _send(conn, first, stats)
        source.sent, last_sent = first, time.monotonic()
        source.sent_at = last_sent
    checked = -math.inf
    while not stop.is_set():
        watch.check()
        idle.check()
        now = time.monotonic()
        if now - checked >= PEER_CHECK_S:
            checked = now
            if _peer_closed(conn, refusals):
                raise ConnectionLostError("peer closed the connection")
        if period and last_sent:
            remaining = last_sent + period - time.monotonic()
            if remaining > 0:
                stop.wait(min(remaining, POLL_S))
                continue
        frame = source.next(POLL_S)
        if frame is None:
            continue
        _send(conn, frame, stats)
        source.sent, last_sent = frame, time.monotonic()
        source.sent_at = last_sent
        idle.active()


def _run_receiver(conn: _Conn, sink: _Sink, stats: LinkStats, stop: threading.Event, max_size: int,
                  idle_timeout: float | None = None) -> None:
    """Write each frame that arrives into ``sink`` until stopped, the connection is lost or nothing arrived for
    ``idle_timeout`` s."""
    decoder = ap.FrameDecoder(max_size)
    oversize_seen = 0
    watch = _ChannelWatch(sink.chan)
    idle = _IdleWatch(idle_timeout)
    if conn.udp is None and conn.leftover:
        for frame in decoder.feed(conn.leftover):
            sink.put(frame)
    socks = [conn.tcp] + ([conn.udp] if conn.udp is not None else [])
    while not stop.is_set():
        watch.check()
        idle.check()
        readable, _, _ = select.select(socks, [], [], POLL_S)
        if conn.tcp in readable:
            try:
                data = conn.tcp.recv(256 * 1024)
            except OSError as exc:
                raise ConnectionLostError(f"receive failed: {exc}") from exc
            if not data:
                raise ConnectionLostError("peer closed the connection")
            idle.active()
            if conn.udp is None:
                try:
                    frames = decoder.feed(data)
                except ap.FrameError as exc:
                    raise ConnectionLostError(str(exc)) from exc
                stats.dropped_oversize += decoder.oversize - oversize_seen
                oversize_seen = decoder.oversize
                for frame in frames:
                    sink.put(frame)
        if conn.udp is not None and conn.udp in readable and _drain_udp(conn, sink, stats):
            idle.active()


def _drain_udp(conn: _Conn, sink: _Sink, stats: LinkStats) -> bool:
    """Every queued datagram from the announced peer; others are counted as strays (achd ignores them).
    True if one came from the peer."""
    got = False
    for _ in range(1000):
        try:
            assert conn.udp is not None  # only called for a UDP link
            payload, addr = conn.udp.recvfrom(65536)
        except BlockingIOError:
            return got
        except OSError as exc:  # ICMP errors surface here; not fatal for a datagram socket
            stats.last_error = f"udp receive: {exc}"
            return got
        if (addr[0], addr[1]) != conn.udp_peer:
            stats.stray_datagrams += 1
            continue
        got = True
        sink.put(payload)
    return got


# --------------------------------------------------------------------------------------------------
# Client: one link
# --------------------------------------------------------------------------------------------------


class Link:
    """One client link, like ``achd [-r] push|pull HOST CHANNEL``, running on its own thread.

    ``mode`` is ours: ``push`` sends the local ``channel`` to the remote ``remote_channel``, ``pull``
    brings the remote one into the local one (created with the server's sizes when missing).
    """

    def __init__(
        self,
        mode: str,
        host: str,
        channel: str,
        *,
        remote_channel: str | None = None,
        port: int = ap.ACHD_PORT,
        transport: str = "tcp",
        get_last: bool = True,
        period_ns: int = 0,
        reconnect: bool = True,
        resend_on_reconnect: bool = True,
        dead_after_s: float = 5.0,
        connect_timeout_s: float = 3.0,
        max_frame: int = 16 * 1024 * 1024,
    ) -> None:
        if mode not in ap.DIRECTIONS:
            raise ValueError(f"mode must be push or pull, not {mode!r}")
        if transport not in ap.TRANSPORTS:
            raise ValueError(f"transport must be tcp or udp, not {transport!r}")
        for name in (channel, remote_channel or channel):
            if not ap.valid_channel_name(name):
                raise ValueError(f"invalid channel name {name!r}")
        if period_ns < 0:
            raise ValueError("period must not be negative")
        self.mode = mode
        self.host = host
        self.port = port
        self.channel = channel
        self.remote_channel = remote_channel or channel
        self.transport = transport
        self.get_last = get_last
        self.period_ns = period_ns
        self.reconnect = reconnect
        self.resend_on_reconnect = resend_on_reconnect
        self.dead_after_s = dead_after_s
        self.connect_timeout_s = connect_timeout_s
        self.max_frame = max_frame
        self.rule = rule_for(channel)
        self.stats = LinkStats()
        self.connected = threading.Event()
        self.finished = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._chan: ach.Channel | None = None
        self._opened_once = False
        self._source: _Source | None = None
        self._lost_at = -math.inf  # monotonic time the last connection ended
        self.udp_port: int | None = None
        """Our datagram port on the current UDP connection (what the peer must send from/to)."""

    @property
    def name(self) -> str:
        arrow = "->" if self.mode == "push" else "<-"
        return f"{self.channel} {arrow} {self.host}:{self.port}/{self.remote_channel} ({self.transport})"

    def start(self) -> Link:
        self._thread = threading.Thread(target=self.run, name=f"achd {self.mode} {self.channel}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout: float | None = None) -> None:
        if self._thread is not None:
            self._thread.join(timeout)

    def run(self) -> None:
        """Connect, stream, and (with reconnect) start over after a drop, until :meth:`stop`."""
        try:
            while not self._stop.is_set():
                t0 = time.monotonic()
                retry_after = ap.RECONNECT_PERIOD_S
                conn: _Conn | None = None
                try:
                    conn = self._connect()
                    self.stats.connects += 1
                    self.connected.set()
                    log.info("%s: connected", self.name)
                    self._stream(conn)
                except RemoteRefusedError as exc:
                    self.stats.last_error = str(exc)
                    log.error("%s: server refused: %s", self.name, exc)
                    retry_after = REFUSED_RETRY_S
                    if self.connected.is_set() and self._source is not None:
                        self._source.newest = None  # a frame was refused (maybe the newest): never re-sent
                except ach.AchException as exc:  # the local channel cannot be made or opened
                    self.stats.last_error = str(exc)
                    log.error("%s: local channel: %s", self.name, exc)
                    retry_after = REFUSED_RETRY_S
                except (OSError, ConnectionLostError, ap.HeaderError) as exc:
                    self.stats.last_error = str(exc) or type(exc).__name__
                    if self.connected.is_set():
                        log.warning("%s: connection lost: %s", self.name, self.stats.last_error)
                    else:
                        log.debug("%s: connect failed: %s", self.name, self.stats.last_error)
                finally:
                    if self.connected.is_set():  # an established connection ended (not a failed attempt)
                        self._lost_at = time.monotonic()
                    self.connected.clear()
                    if conn is not None:
                        conn.close()
                    if self._chan is not None and channel_replaced(self._chan):
                        self._chan.close()  # reopened (or re-created) at the next connection
                        self._chan = None
                if not self.reconnect:
                    break
                self._stop.wait(max(0.0, t0 + retry_after - time.monotonic()))
        finally:
            if self._chan is not None:
                self._chan.close()
                self._chan = None
            self.finished.set()

    def _connect(self) -> _Conn:
        tcp = socket.create_connection((self.host, self.port), timeout=self.connect_timeout_s)
        conn = _Conn(tcp)
        try:
            _tune_tcp(tcp, self.dead_after_s, sending=self.mode == "push" and self.transport == "tcp")
            udp_port = None
            if self.transport == "udp":
                conn.udp = _udp_socket(tcp)
                udp_port = self.udp_port = conn.udp.getsockname()[1]
            # The server's role is the opposite of ours.
            server_role = "pull" if self.mode == "push" else "push"
            request = ap.encode_request(
                self.remote_channel, self.transport, server_role, self.get_last, self.period_ns, udp_port
            )
            tcp.settimeout(self.connect_timeout_s)
            tcp.sendall(request)
            headers, conn.leftover = _read_headers(tcp, HEADER_TIMEOUT_S)
            conn.headers = headers
            if headers.status is None or headers.status != ap.ACH_OK:
                status = ap.ACH_BAD_HEADER if headers.status is None else headers.status
                raise RemoteRefusedError(status, headers.message or "no status in the response")
            if self.transport == "udp":
                if not headers.remote_port:
                    raise ap.HeaderError("udp response without remote-port")
                conn.udp_peer = (tcp.getpeername()[0], headers.remote_port)
            self._open_local(headers)
            tcp.settimeout(self.dead_after_s)  # a send blocked longer than this means the link is dead
            return conn
        except BaseException:
            conn.close()
            raise

    def _open_local(self, headers: ap.Headers) -> None:
        """Open (or create with the server's sizes) the local channel; flushed the first time, as achd does."""
        if self._chan is not None:
            return
        if not ach.exists(self.channel):
            count = headers.frame_count or 16
            size = headers.frame_size or 512
            try:
                ach.create(self.channel, count, size)
            except ach.AchException as exc:
                if exc.status != ach.ACH_EEXIST:
                    raise
        chan = ach.Channel(self.channel, create=False)
        if not self._opened_once:  # achd: only frames put after the link started; a re-created channel is new
            chan.flush()
            self._opened_once = True
        self._chan = chan
        if self.mode == "push":
            self._source = _Source(chan, self.rule, self.get_last, self.stats)

    def _delivered(self) -> bool:
        """Did the newest frame certainly reach the server before the old connection ended? Over TCP, when
        it was sent and the connection then lived on for more than ``dead_after_s`` (``TCP_USER_TIMEOUT``
        would have killed it had the data stayed unacknowledged). Re-sending it then would only replay an old
        reference over newer ones (e.g. after the server closed a quiet connection as idle)."""
        source = self._source
        return (self.transport == "tcp" and source is not None and source.newest is not None
                and source.sent == source.newest and self._lost_at - source.sent_at > self.dead_after_s)

    def _stream(self, conn: _Conn) -> None:
        if self.mode == "push":
            assert self._source is not None
            first = None
            if self.resend_on_reconnect and self.stats.connects > 1 and not self._delivered():
                first = self._source.newest  # TCP may have dropped it with the old connection
            _run_sender(conn, self._source, self.stats, self._stop, self.period_ns, first, refusals=True)
        else:
            _run_receiver(conn, _Sink(self._chan, self.rule, self.stats), self.stats, self._stop, self.max_frame)


# --------------------------------------------------------------------------------------------------
# Server
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AccessPolicy:
    """Which channels a network client may read (pull) and write (push); shell-style patterns."""

    readable: tuple[str, ...] = ("*",)
    writable: tuple[str, ...] = SAFE_WRITABLE

    def allows(self, channel: str, server_direction: str) -> bool:
        patterns = self.readable if server_direction == "push" else self.writable
        return any(fnmatch.fnmatchcase(channel, p) for p in patterns)


WHY_NOT_WRITABLE: dict[str, str] = {
    contracts.MDS_CHAN_BOARD_CMD_NAME:
        "its setup commands (enable, disable, home, zero, reset) pass no safety stage and are not levels (a "
        "reconnect may send one again); run them on the robot (mds-ach enable|home|zero|reset JOINT, e.g. over "
        "ssh). The original MDS-Ach never read mds-cmd, so this link carried nothing; the other links work",
    contracts.MDS_CHAN_DAEMON_INPUT_NAME:
        "it is what the daemon executes; write mds-ref-filter or mds-ref, whose frames pass the mux, the filter "
        "and the collision gate",
}
"""Why the default write rules refuse these channels, in the refusal a client is sent: golems' achd prints it
(``Server error: ...``) before it exits, ``-r`` or not (a refused request is not a lost connection). No ':' or
'=' in them: golems' header parser ends a value there."""


def refusal_message(channel: str, verb: str) -> str:
    """The message of an ``ACH_EACCES`` refusal for ``channel`` (``verb``: read or written); one line."""
    why = WHY_NOT_WRITABLE.get(channel) if verb == "written" else None
    return f"channel {channel} may not be {verb} from the network" + (f" -- {why}" if why else "")


def is_local_peer(host: str) -> bool:
    """Loopback (127.0.0.0/8, ::1, or IPv4-mapped loopback): this machine's tools and SSH-tunnelled operators."""
    try:
        address = ipaddress.ip_address(host.split("%", 1)[0])
    except ValueError:
        return False
    mapped = getattr(address, "ipv4_mapped", None)
    return address.is_loopback or (mapped is not None and mapped.is_loopback)


class Server:
    """``achd serve`` as a listening TCP server: one thread per accepted connection.

    Binds loopback unless ``binds`` says otherwise; a connection's request decides the channel,
    transport and direction, subject to ``policy``.

    Admission, so that no peer can lock out another or the operator: a remote address holds at most
    ``max_per_peer`` connections and all remote peers together ``max_clients``; loopback peers (local tools, and
    operators coming through an SSH tunnel) have ``max_local_clients`` per local user (the uid owning the peer's
    socket), which remote peers and other local users cannot use. A connection that sends and receives no frame
    for ``idle_timeout_s`` (None: never) is closed, one that does not complete its request within
    ``HEADER_TIMEOUT_S`` too. Refusals answer ``ACH_EAGAIN``.
    """

    def __init__(
        self,
        binds: Iterable[str] = ("127.0.0.1",),
        port: int = ap.ACHD_PORT,
        *,
        policy: AccessPolicy | None = None,
        send_latest_on_connect: bool = False,
        dead_after_s: float = 5.0,
        max_clients: int = MAX_CLIENTS,
        max_per_peer: int = MAX_PER_PEER,
        max_local_clients: int = MAX_LOCAL_CLIENTS,
        idle_timeout_s: float | None = IDLE_TIMEOUT_S,
        max_frame: int = 16 * 1024 * 1024,
    ) -> None:
        for what, value in (("max_clients", max_clients), ("max_per_peer", max_per_peer),
                            ("max_local_clients", max_local_clients)):
            if value < 1:
                raise ValueError(f"{what} must be at least 1, got {value}")
        if idle_timeout_s is not None and not idle_timeout_s > 0:
            raise ValueError(f"idle timeout must be > 0 s, got {idle_timeout_s}")
        self.binds = tuple(binds)
        self.port = port
        self.policy = policy or AccessPolicy()
        self.send_latest_on_connect = send_latest_on_connect
        self.dead_after_s = dead_after_s
        self.max_clients = max_clients
        self.max_per_peer = max_per_peer
        self.max_local_clients = max_local_clients
        self.idle_timeout_s = idle_timeout_s
        self.max_frame = max_frame
        self.stats: dict[str, LinkStats] = {}
        self.refused = 0
        self.refused_busy = 0  # connections refused by the admission limits
        self.refused_frames = 0  # connections closed after a refused request frame (HoldCheck)
        self.idle_closed = 0  # connections closed for being idle
        self._listeners: list[socket.socket] = []
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._per_peer: dict[str, int] = {}  # open connections per remote address
        self._per_uid: dict[int | None, int] = {}  # open loopback connections per local user
        self._remote = 0
        self._local = 0
        self._lock = threading.Lock()

    @property
    def ports(self) -> list[int]:
        return [s.getsockname()[1] for s in self._listeners]

    def start(self) -> Server:
        for address in self.binds:
            family = socket.AF_INET6 if ":" in address else socket.AF_INET
            sock = socket.socket(family, socket.SOCK_STREAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                sock.bind((address, self.port))
            except OSError as exc:
                sock.close()
                for listener in self._listeners:
                    listener.close()
                self._listeners.clear()
                raise OSError(exc.errno, f"cannot listen on {address}:{self.port}: {exc.strerror}") from exc
            sock.listen(16)
            self._listeners.append(sock)
            log.info("serving on %s:%d", address, sock.getsockname()[1])
        thread = threading.Thread(target=self._accept_loop, name="achd accept", daemon=True)
        thread.start()
        self._threads.append(thread)
        return self

    def stop(self) -> None:
        self._stop.set()

    def join(self, timeout: float = 5.0) -> None:
        deadline = time.monotonic() + timeout
        for thread in list(self._threads):
            thread.join(max(0.0, deadline - time.monotonic()))
        for sock in self._listeners:
            sock.close()

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            readable, _, _ = select.select(self._listeners, [], [], POLL_S)
            for listener in readable:
                try:
                    sock, peer = listener.accept()
                except OSError:
                    continue
                busy, slot = self._admit(peer, sock.getsockname())
                if busy:
                    self.refused_busy += 1
                    if self.refused_busy == 1 or self.refused_busy % 100 == 0:  # a flood must not flood the log
                        log.warning("refusing %s (#%d): %s", peer[0], self.refused_busy, busy)
                    _refuse(sock, ap.ACH_EAGAIN, busy)
                    continue
                thread = threading.Thread(target=self._serve_one, args=(sock, peer, slot), daemon=True)
                with self._lock:
                    self._threads = [t for t in self._threads if t.is_alive()]
                    self._threads.append(thread)
                thread.start()

    def _admit(self, peer: tuple, server: tuple) -> tuple[str | None, tuple[bool, Any]]:
        """Count a new connection from ``peer`` (accepted on ``server``) in, or say why it is refused (its pool or
        its share is full). Returns (refusal or None, the slot ``_release`` frees): a loopback peer's slot is its
        local user's (``peer_uid``; None when it cannot be told: the peer closed already, or no /proc), a remote
        peer's its address."""
        host = peer[0]
        local = is_local_peer(host)
        key: Any = peer_uid(peer, server) if local else host
        with self._lock:
            if local:
                mine = self._per_uid.get(key, 0)
                if mine >= self.max_local_clients:
                    who = "an unknown local user" if key is None else f"uid {key}"
                    return (f"too many local connections from {who} ({self.max_local_clients}); close some first",
                            (local, key))
                self._per_uid[key] = mine + 1
                self._local += 1
                return None, (local, key)
            mine = self._per_peer.get(host, 0)
            if mine >= self.max_per_peer:
                return f"too many connections from {host} ({self.max_per_peer}); close some first", (local, key)
            if self._remote >= self.max_clients:
                return f"too many remote clients ({self.max_clients})", (local, key)
            self._per_peer[host] = mine + 1
            self._remote += 1
            return None, (local, key)

    def _release(self, slot: tuple[bool, Any]) -> None:
        local, key = slot
        with self._lock:
            counts = self._per_uid if local else self._per_peer
            left = counts.get(key, 1) - 1
            if left > 0:
                counts[key] = left
            else:
                counts.pop(key, None)
            if local:
                self._local -= 1
            else:
                self._remote -= 1

    def connections(self) -> dict[str, int]:
        """Open connections: ``local``, ``remote`` and one entry per remote address."""
        with self._lock:
            return {"local": self._local, "remote": self._remote, **self._per_peer}

    def local_users(self) -> dict[int | None, int]:
        """Open loopback connections per local user (uid; None: not known)."""
        with self._lock:
            return dict(self._per_uid)

    def _serve_one(self, sock: socket.socket, peer: tuple, slot: tuple[bool, Any]) -> None:
        conn = _Conn(sock)
        chan = None
        who = f"{peer[0]}:{peer[1]}"
        try:
            try:
                headers, conn.leftover = _read_headers(sock, HEADER_TIMEOUT_S)
                headers.check_request()
            except ap.HeaderError as exc:
                self.refused += 1
                log.warning("%s: bad request: %s", who, exc)
                _refuse(sock, exc.status, str(exc))
                return
            name, direction = headers.channel_name, headers.direction
            assert name is not None and direction is not None
            if not self.policy.allows(name, direction):
                self.refused += 1
                verb = "read" if direction == "push" else "written"
                log.warning("%s: refused, channel %s may not be %s from the network", who, name, verb)
                _refuse(sock, ap.ACH_EACCES, refusal_message(name, verb))
                return
            try:
                chan = ach.Channel(name, create=False)
            except ach.AchException as exc:
                self.refused += 1
                _refuse(sock, exc.status, f"cannot open channel {name} ({exc})")
                return
            frame_count, data_size = _geometry(chan)
            _tune_tcp(sock, self.dead_after_s, sending=direction == "push" and headers.transport == "tcp")
            udp_port = None
            if headers.transport == "udp":
                conn.udp = _udp_socket(sock)
                udp_port = conn.udp.getsockname()[1]
                assert headers.remote_port is not None  # validated: a UDP request names its port
                conn.udp_peer = (peer[0], headers.remote_port)
            stats = LinkStats(connects=1)
            rule = rule_for(name)
            source, first = None, None
            if direction == "push":  # before the response, as achd: a frame put once the client is told it is
                source = _Source(chan, rule, bool(headers.get_last), stats)  # connected is never flushed away
                if self.send_latest_on_connect:
                    first = source.next(0.0, last=True, wait=False)
                else:
                    chan.flush()
            sock.sendall(ap.encode_response(frame_count, data_size // frame_count, udp_port))
            sock.settimeout(self.dead_after_s)
            key = f"{who} {direction} {name} ({headers.transport})"
            with self._lock:
                self.stats[key] = stats
                while len(self.stats) > MAX_SERVED_STATS:  # keep the newest connections' counters
                    del self.stats[next(iter(self.stats))]
            log.info("%s: serving %s %s via %s", who, direction, name, headers.transport)
            if source is not None:
                _run_sender(conn, source, stats, self._stop, headers.period_ns or 0, first, self.idle_timeout_s)
            else:
                limits = RefLimitCheck.for_channel(chan, name) or HoldCheck.for_channel(name)  # before the flush
                chan.flush()
                _run_receiver(conn, _Sink(chan, rule, stats, limits), stats, self._stop, self.max_frame,
                              self.idle_timeout_s)
        except FrameRefusedError as exc:  # the client is told why; it reconnects for its next request
            self.refused_frames += 1
            if self.refused_frames == 1 or self.refused_frames % 100 == 0:  # a flood must not flood the log
                log.warning("%s: refused a frame on %s (#%d) and closed: %s", who, name, self.refused_frames, exc)
            _refuse(sock, ap.ACH_EINVAL, str(exc), linger=True)
        except (OSError, ConnectionLostError) as exc:
            self.idle_closed += isinstance(exc, IdleConnectionError)
            log.info("%s: finished: %s", who, exc)
        except Exception:  # one broken connection must never take the server down
            log.exception("%s: connection failed", who)
        finally:
            self._release(slot)  # before the close: a client that saw its connection end finds its slot free
            conn.close()
            if chan is not None:
                chan.close()


def _refuse(sock: socket.socket, status: int, message: str, linger: bool = False) -> None:
    """achd's error reply (status, message, '.'), then close. ``linger``: mid-stream, the client may still be
    sending; read and drop what it sends (at most 1 s) until it closes, so the close is no reset that could
    discard the reply before the client read it."""
    try:
        sock.settimeout(1.0)
        sock.sendall(ap.encode_error(status, message))
        if linger:
            sock.shutdown(socket.SHUT_WR)
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline and sock.recv(65536):
                pass
    except OSError:
        pass
    finally:
        sock.close()


# --------------------------------------------------------------------------------------------------
# Command line (achd's verbs and short options)
# --------------------------------------------------------------------------------------------------


def install_stop_signals(stop: Callable[[], None]) -> None:
    """SIGINT/SIGTERM ask the loops to stop; the main thread then exits 0."""

    def handler(signum, frame):  # noqa: ARG001 - signal API
        stop()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)


def add_server_limit_arguments(p: argparse.ArgumentParser, prefix: str = "") -> None:
    """The admission and idle options of a server (``achd serve``, ``mds-ach remote serve``)."""
    p.add_argument("--max-clients", type=int, default=MAX_CLIENTS,
                   help=f"{prefix}connections from remote peers together (default {MAX_CLIENTS})")
    p.add_argument("--max-per-peer", type=int, default=MAX_PER_PEER,
                   help=f"{prefix}connections from one remote address (default {MAX_PER_PEER})")
    p.add_argument("--max-local", type=int, default=MAX_LOCAL_CLIENTS,
                   help=f"{prefix}connections from loopback per local user (local tools, SSH-tunnelled operators: "
                        f"the uid owning the peer's socket), pools remote peers and other local users cannot use "
                        f"(default {MAX_LOCAL_CLIENTS})")
    p.add_argument("--idle-timeout", type=float, default=IDLE_TIMEOUT_S, metavar="S",
                   help=f"{prefix}close a connection that sends and receives no frame for S seconds "
                        f"(default {IDLE_TIMEOUT_S:g}; 0: never)")


def add_connect_start_arguments(p: argparse.ArgumentParser, prefix: str = "") -> None:
    """Which frame a pulling client gets first: golems' achd's (the first one written after it connected) unless
    ``--newest-on-connect``."""
    first = p.add_mutually_exclusive_group()
    first.add_argument("--newest-on-connect", action="store_true",
                       help=f"{prefix}start each pull with the channel's newest frame, even one written before "
                            "the client connected (default: like golems' achd, the first frame written after)")
    first.add_argument("--flush-on-connect", action="store_true",
                       help=f"{prefix}like golems' achd, never send a frame written before the client connected "
                            "(the default)")


class ServerLimits(TypedDict):
    """The connection limits of ``Server`` that the command line sets."""

    max_clients: int
    max_per_peer: int
    max_local_clients: int
    idle_timeout_s: float | None


def server_limits(args: argparse.Namespace) -> ServerLimits:
    """``Server`` keyword arguments from ``add_server_limit_arguments`` options."""
    return {"max_clients": args.max_clients, "max_per_peer": args.max_per_peer,
            "max_local_clients": args.max_local, "idle_timeout_s": args.idle_timeout or None}


def build_parser() -> argparse.ArgumentParser:
    ap_ = argparse.ArgumentParser(
        prog="python -m mds_ach.net.achd",
        description="Forward Ach channels over the network, compatible with golems/ach's achd.",
        epilog=(
            "examples:\n"
            "  python -m mds_ach.net.achd serve                      serve on 127.0.0.1:8076\n"
            "  python -m mds_ach.net.achd serve --bind 10.0.0.2      serve on that address\n"
            "  python -m mds_ach.net.achd -r pull robot mds-state    robot's mds-state -> local mds-state\n"
            "  python -m mds_ach.net.achd -r -t udp -u 100000 pull robot mds-state   at most 10 Hz over UDP\n"
            "  python -m mds_ach.net.achd -r push robot mds-ref-filter\n"
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap_.add_argument("verb", choices=("serve", "push", "pull"), help="serve, or the direction of this link")
    ap_.add_argument("host", nargs="?", help="remote host (push/pull)")
    ap_.add_argument("channel", nargs="?", help="local channel (push/pull)")
    ap_.add_argument("-p", "--port", type=int, default=ap.ACHD_PORT, help="TCP port (default 8076)")
    ap_.add_argument("-t", "--transport", choices=ap.TRANSPORTS, default="tcp", help="data transport")
    ap_.add_argument("-z", "--remote-channel", help="remote channel name (default: the local name)")
    ap_.add_argument("-u", "--period-us", type=int, default=0, help="send period in microseconds (implies -l)")
    ap_.add_argument("-l", "--get-last", action="store_true", help="send only the newest frame")
    ap_.add_argument("-r", "--reconnect", action="store_true", help="reconnect when the connection drops")
    ap_.add_argument("--bind", action="append", help="serve: address to listen on (repeatable; default 127.0.0.1)")
    ap_.add_argument("--allow-read", action="append", help="serve: channel pattern clients may pull (default *)")
    ap_.add_argument(
        "--allow-write",
        action="append",
        help=f"serve: channel pattern clients may push into (default {', '.join(SAFE_WRITABLE)})",
    )
    add_connect_start_arguments(ap_, "serve: ")
    add_server_limit_arguments(ap_, "serve: ")
    ap_.add_argument("-v", "--verbose", action="store_true", help="log every connection")
    return ap_


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logformat.setup_python_logging("achd", logging.INFO if args.verbose else logging.WARNING)
    stop = threading.Event()
    install_stop_signals(stop.set)
    if args.verb == "serve":
        if args.host or args.channel:
            print("achd: serve takes no HOST or CHANNEL", file=sys.stderr)
            return 2
        policy = AccessPolicy(
            readable=tuple(args.allow_read or ("*",)), writable=tuple(args.allow_write or SAFE_WRITABLE)
        )
        try:
            server = Server(
                args.bind or ("127.0.0.1",), args.port, policy=policy,
                send_latest_on_connect=args.newest_on_connect, **server_limits(args),
            ).start()
        except ValueError as exc:
            print(f"achd: {exc}", file=sys.stderr)
            return 2
        except OSError as exc:
            print(f"achd: {exc.strerror or exc}", file=sys.stderr)
            return 1
        print(f"achd: serving on {', '.join(args.bind or ['127.0.0.1'])} port {server.ports[0]}", file=sys.stderr)
        while not stop.wait(POLL_S):
            pass
        server.stop()
        server.join()
        return 0
    if not args.host or not args.channel:
        print("achd: push/pull need HOST and CHANNEL", file=sys.stderr)
        return 2
    try:
        link = Link(
            args.verb, args.host, args.channel, remote_channel=args.remote_channel, port=args.port,
            transport=args.transport, get_last=args.get_last or args.period_us > 0,
            period_ns=args.period_us * 1000, reconnect=args.reconnect,
        ).start()
    except ValueError as exc:
        print(f"achd: {exc}", file=sys.stderr)
        return 2
    while not stop.wait(POLL_S):
        if link.finished.is_set():
            break
    link.stop()
    link.join(5.0)
    if link.finished.is_set() and not stop.is_set():
        print(f"achd: {link.name}: {link.stats.last_error or 'finished'}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
