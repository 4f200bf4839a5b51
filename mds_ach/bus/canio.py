"""The daemon's CAN access: bus creation from python-can's standard configuration, the simulated bus,
traffic recording with python-can's log writers, reading and replaying a recorded log, and frame/bit accounting.

Bus selection follows python-can (``can.util.load_config``): explicit ``--interface/--channel/--bitrate``
win, then ``$CAN_INTERFACE``/``$CAN_CHANNEL``/``$CAN_BITRATE``, then ``~/.canrc``/``/etc/can.conf`` (or the
file given with ``--can-config``). So socketcan, kvaser, pcan, slcan, ... work without code changes.
"""

from __future__ import annotations

import gzip
import logging
import queue
import re
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from mds_ach.bus import mcb
from mds_ach.bus.simbus import SimBus, SimNetwork

log = logging.getLogger(__name__)

DEFAULT_BITRATE = 1_000_000  # the MDS bus
LOG_SUFFIXES = (".asc", ".blf", ".csv", ".log", ".trc", ".txt", ".mf4")


# Suffixes can.LogReader reads (each also gzip-compressed, e.g. run.asc.gz).
READ_SUFFIXES = (".asc", ".blf", ".csv", ".db", ".log", ".mf4", ".trc")
MDS_DUMP = "MDS-Ach text dump"


class BusConfigError(ValueError):
    """No usable CAN configuration; the message says how to give one."""


def bus_config(interface: str | None = None, channel: str | None = None, bitrate: int | None = None,
               config_file: str | None = None, context: str | None = None) -> dict[str, Any]:
    """python-can's merged configuration (explicit values first); refuses an incomplete one clearly."""
    given: dict[str, Any] = {}
    if interface:
        given["interface"] = interface
    if channel:
        given["channel"] = channel
    if bitrate:
        given["bitrate"] = int(bitrate)
    try:
        cfg = dict(can.util.load_config(path=config_file, config=given, context=context))
    except can.CanInterfaceNotImplementedError as exc:
        if '"None"' in str(exc):  # python-can's way of saying that no source named an interface
            raise BusConfigError(_NO_INTERFACE) from None
        raise BusConfigError(f"unknown CAN interface: {exc}") from None
    if not cfg.get("interface"):
        raise BusConfigError(_NO_INTERFACE)
    return cfg


_NO_INTERFACE = ("no CAN interface configured: give --interface and --channel (e.g. socketcan can0), set "
                 "CAN_INTERFACE/CAN_CHANNEL, write a python-can config file (~/.canrc), or run the simulated "
                 "robot with --nocan")


@dataclass
class BusCounters:
    """What crossed the interface, for bus-load and fault accounting (reset only on request)."""

    tx_frames: int = 0
    rx_frames: int = 0
    tx_errors: int = 0  # send() failed (buffer full, bus-off, interface down)
    rx_errors: int = 0  # recv() raised
    error_frames: int = 0
    bits: int = 0  # worst-case wire bits of every frame seen since the last take_bits()
    last_error: str = ""

    def take_bits(self) -> int:
        bits, self.bits = self.bits, 0
        return bits


def message_bits(msg: can.Message) -> int:
    """Worst-case wire bits of one frame (error frames counted as a DLC-8 frame's worth: a conservative guess)."""
    if msg.is_error_frame or (msg.dlc == mcb.DLC and not msg.is_extended_id):
        return mcb.FRAME_BITS
    return mcb.frame_bits(msg.dlc, msg.is_extended_id)


class Recorder:
    """Writes every frame to a python-can log file from a background thread (no file I/O in the RT loop)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if self.path.suffix.lower() not in LOG_SUFFIXES:
            raise ValueError(f"--can-log {self.path}: unknown log format; use one of {', '.join(LOG_SUFFIXES)}")
        self._writer = can.Logger(str(self.path))
        self._queue: queue.SimpleQueue[can.Message | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._run, name="can-log", daemon=True)
        self._thread.start()
        self.written = 0

    def __call__(self, msg: can.Message) -> None:
        self._queue.put(msg)

    def _run(self) -> None:
        while (msg := self._queue.get()) is not None:
            try:
                self._writer.on_message_received(msg)
                self.written += 1
            except Exception as exc:  # a full disk must not stop the robot
                log.error("CAN log %s: %s", self.path, exc)

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(timeout=5.0)
        self._writer.stop()


class LogReadError(ValueError):
    """A log that cannot be read; the message names the file and what is wrong."""


class TornLogError(LogReadError):
    """Raised after the last complete frame when only the file's final line is incomplete: what a recorder killed
    mid-write (a SIGKILLed daemon) leaves. Every frame before it was delivered."""


# A frame line of the original MDS-Ach daemon's text dump (shared/mds-reference/can/logs): time stamp in ms with
# a C 'l' suffix, node, the vendor parser's text, the 8 bytes printed data[7] -> data[0], the CAN ID in hex.
_DUMP_LINE = re.compile(r"^(\d+)l\t.*\t\[((?: [0-9a-fA-F]{2}){8}) \]\t([0-9a-fA-F]+)\s*$")


def log_format(path: str | Path) -> str:
    """How ``read_log`` reads ``path``: ``MDS_DUMP`` when the text looks like the original daemon's dump, else the
    python-can reader its suffix selects; LogReadError for anything else."""
    path = Path(path)
    suffixes = [s.lower() for s in path.suffixes]
    if suffixes[-1:] == [".gz"]:
        suffixes = suffixes[:-1]
    suffix = suffixes[-1] if suffixes else ""
    if suffix not in (".blf", ".db", ".mf4"):  # binary formats are never dumps
        try:
            opener = gzip.open if path.suffix.lower() == ".gz" else open
            with opener(path, "rt", errors="replace") as f:
                head = [f.readline() for _ in range(40)]
        except OSError as exc:
            raise LogReadError(f"{path}: cannot read: {exc.strerror or exc}") from None
        if any(_DUMP_LINE.match(line) for line in head):
            return MDS_DUMP
    if suffix in READ_SUFFIXES:
        return f"python-can {suffix}"
    raise LogReadError(f"{path}: unknown log format (suffix {suffix or 'none'!r}); python-can reads "
                       f"{' '.join(READ_SUFFIXES)} (candump -l writes .log), and the original MDS-Ach text dumps "
                       "are recognised by their content")


def read_log(path: str | Path) -> Iterator[can.Message]:
    """Every frame of a recorded log, in file order: python-can formats by suffix, or an original MDS-Ach text
    dump (``log_format``). Raises LogReadError (naming the file) for an unknown format or a damaged file."""
    path = Path(path)
    fmt = log_format(path)
    if fmt == MDS_DUMP:
        yield from _read_mds_dump(path)
        return
    try:
        reader = can.LogReader(str(path))
    except Exception as exc:  # python-can raises many kinds for a damaged header
        raise LogReadError(f"{path}: not a readable {fmt} log: {exc}") from None
    count = 0
    try:
        for msg in reader:
            count += 1
            yield msg
    except Exception as exc:
        rest = _unread(reader)
        if rest is not None and not rest.strip():
            raise TornLogError(f"{path}: the last line is incomplete after frame {count} (a recorder stopped "
                               "mid-write?)") from None
        raise LogReadError(f"{path}: damaged after frame {count}: {type(exc).__name__}: {exc}") from None
    finally:
        reader.stop()


def _unread(reader: can.io.generic.MessageReader) -> str | bytes | None:
    """What follows the line a text reader failed on (None when that cannot be known)."""
    if not isinstance(reader, can.io.generic.FileIOMessageReader):
        return None  # no file to read on (the SQLite reader)
    try:
        rest: str | bytes = reader.file.read()
        return rest
    except Exception:  # binary readers, closed or unseekable files
        return None


def _read_mds_dump(path: Path) -> Iterator[can.Message]:
    """The original daemon's dump: ms time stamps; the first frame is stamped 0 (no stamp was taken before the
    loop started), so an undated frame gets the time of the next dated one (a query and its replies are
    milliseconds apart). Header and blank lines are skipped; other lines are an error."""
    undated: list[can.Message] = []
    with open(path, errors="replace") as f:
        for lineno, line in enumerate(f, 1):
            if not line.strip() or "\t" not in line:
                continue  # "T = 0.010 sec", "Start MDS Loop", blank lines
            m = _DUMP_LINE.match(line)
            if m is None:
                raise LogReadError(f"{path}:{lineno}: not a frame line of an MDS-Ach dump: {line.strip()[:80]!r}")
            stamp, printed, can_id = m.groups()
            data = bytes(reversed(bytes.fromhex(printed.replace(" ", ""))))
            msg = can.Message(timestamp=int(stamp) / 1000.0, arbitration_id=int(can_id, 16), data=data,
                              is_extended_id=False, check=False)
            if int(stamp) == 0:
                undated.append(msg)
                continue
            for early in undated:
                early.timestamp = msg.timestamp
                yield early
            undated.clear()
            yield msg
    yield from undated


class ReplayBus(can.BusABC):
    """Feeds the node -> host frames of a recorded log back, paced like the recording.

    Host frames in the log (commands) are skipped; frames sent to this bus are accepted and dropped.
    ``speed`` scales the pacing (2.0 = twice as fast, 0 = as fast as they are read).
    """

    def __init__(self, channel: str = "replay", path: str | Path = "", speed: float = 1.0, loop: bool = False,
                 **kwargs: object) -> None:
        if not path:
            raise can.CanInitializationError("ReplayBus needs path=<log file>")
        self.path = Path(path)
        self.speed = speed
        self.loop = loop
        self.frames = [m for m in read_log(self.path) if self._from_nodes(m)]
        if not self.frames:
            raise can.CanInitializationError(f"{self.path}: no node -> host frames to replay")
        self._i = 0
        self._t0_log = self.frames[0].timestamp
        self._t0 = time.monotonic()
        self.sent = 0
        self.channel_info = f"replay of {self.path.name} ({len(self.frames)} frames)"
        super().__init__(channel, can_filters=None, **kwargs)

    @staticmethod
    def _from_nodes(msg: can.Message) -> bool:
        # MCB replies always use ID 0x10 and commands never do, whatever the log format records of direction.
        return msg.is_error_frame or (not msg.is_extended_id and msg.arbitration_id == mcb.HOST_SID)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent += 1

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._i >= len(self.frames):
            if not self.loop:
                if timeout:
                    time.sleep(timeout)
                return None, False
            self._i, self._t0 = 0, time.monotonic()
        msg = self.frames[self._i]
        if self.speed > 0:
            due = self._t0 + (msg.timestamp - self._t0_log) / self.speed
            wait = due - time.monotonic()
            if wait > 0:
                if timeout is not None and wait > timeout:
                    time.sleep(timeout)
                    return None, False
                time.sleep(wait)
        self._i += 1
        out = can.Message(arbitration_id=msg.arbitration_id, data=msg.data, is_extended_id=msg.is_extended_id,
                          is_error_frame=msg.is_error_frame, dlc=msg.dlc, timestamp=time.time(), check=False)
        return out, False

    @property
    def done(self) -> bool:
        return self._i >= len(self.frames) and not self.loop


@dataclass
class CanIO:
    """The daemon's handle on the bus: send/recv that never raise, counters, recording, reopen after bus-off."""

    factory: Callable[[], can.BusABC]
    bitrate: int = DEFAULT_BITRATE
    recorder: Recorder | None = None
    description: str = ""
    counters: BusCounters = field(default_factory=BusCounters)
    # The sender's clock (CLOCK_MONOTONIC; the daemon sets its own): ``last_sent`` and the log's stamps use it.
    clock: Callable[[], float] = time.monotonic

    def __post_init__(self) -> None:
        self.bus: can.BusABC | None = None
        self.last_sent = -float("inf")  # ``clock()`` right after the last frame the interface accepted
        # Wall time minus CLOCK_MONOTONIC, fixed once: sent frames stamped with a monotonic time keep its spacing.
        self.wall_offset = time.time() - time.monotonic()
        self.open()

    def open(self) -> None:
        self.bus = self.factory()
        self.description = self.description or str(getattr(self.bus, "channel_info", type(self.bus).__name__))

    def reopen(self) -> None:
        """Bus-off recovery: shut the interface down and open it again (a controller restart)."""
        self.close_bus()
        self.open()

    def close_bus(self) -> None:
        if self.bus is not None:
            try:
                self.bus.shutdown()
            except Exception as exc:  # a dead interface may fail to shut down cleanly; we reopen anyway
                log.warning("CAN shutdown: %s", exc)
            self.bus = None

    def close(self) -> None:
        self.close_bus()
        if self.recorder is not None:
            self.recorder.close()
            self.recorder = None

    @property
    def state(self) -> can.BusState:
        try:
            return self.bus.state if self.bus is not None else can.BusState.ERROR
        except NotImplementedError:
            return can.BusState.ACTIVE

    def send(self, raw: mcb.RawFrame, at: float | None = None) -> bool:
        """Send one MCB frame; False (and counted) when the interface refuses it.

        ``last_sent`` is ``clock()`` read right after the interface took the frame: never earlier than it went out.
        The log stamps the frame with ``last_sent`` too, unless ``at`` (a time on ``clock``) gives the moment the frame
        stands for: the daemon dates a MOVETO by the time its step was limited for (``DaemonLoop._send``), and makes
        sure the frame reaches the interface within a tolerance of it.
        """
        msg = can.Message(arbitration_id=raw.arbitration_id, data=raw.data, is_extended_id=False, is_rx=False)
        try:
            if self.bus is None:
                raise can.CanOperationError("bus is closed")
            self.bus.send(msg)
        except can.CanError as exc:
            self.counters.tx_errors += 1
            self.counters.last_error = f"send: {exc}"
            return False
        self.last_sent = self.clock()
        self.counters.tx_frames += 1
        self.counters.bits += mcb.FRAME_BITS
        if self.recorder is not None:
            msg.timestamp = (self.last_sent if at is None else at) + self.wall_offset
            self.recorder(msg)
        return True

    def recv(self, timeout: float | None) -> can.Message | None:
        """Next frame or None; interface errors are counted, never raised."""
        try:
            if self.bus is None:
                return None
            msg = self.bus.recv(timeout)
        except can.CanError as exc:
            self.counters.rx_errors += 1
            self.counters.last_error = f"recv: {exc}"
            return None
        if msg is None:
            return None
        self.counters.bits += message_bits(msg)
        if msg.is_error_frame:
            self.counters.error_frames += 1
        else:
            self.counters.rx_frames += 1
        if self.recorder is not None:
            msg.is_rx = True
            self.recorder(msg)
        return msg


def make_canio(*, nocan: bool = False, network: SimNetwork | None = None, interface: str | None = None,
               channel: str | None = None, bitrate: int | None = None, config_file: str | None = None,
               replay: str | None = None, replay_speed: float = 1.0, can_log: str | None = None) -> CanIO:
    """The bus the command line asked for: simulated (``nocan``, ``network`` = a SimNetwork), a replayed log,
    or a real python-can interface."""
    recorder = Recorder(can_log) if can_log else None
    try:
        if replay:
            return CanIO(lambda: ReplayBus(path=replay, speed=replay_speed), bitrate or DEFAULT_BITRATE, recorder,
                         f"replay of {replay}")
        if nocan:
            rate = bitrate or DEFAULT_BITRATE
            return CanIO(lambda: SimBus(network=network), rate, recorder, "simulated MDS bus")
        cfg = bus_config(interface, channel, bitrate, config_file)
        rate = int(cfg.get("bitrate") or DEFAULT_BITRATE)
        try:
            return CanIO(lambda: can.Bus(**cfg), rate, recorder, f"{cfg.get('interface')}:{cfg.get('channel')}")
        except (OSError, can.CanError) as exc:  # say which interface: "[Errno 19] No such device" alone does not
            raise BusConfigError(f"cannot open CAN interface {cfg.get('interface')} {cfg.get('channel')}: {exc}"
                                 ) from None
    except Exception:
        if recorder is not None:
            recorder.close()
        raise
