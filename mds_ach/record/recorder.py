"""``mds-ach record``: every channel of a running system into an MCAP file that Foxglove, the ``mcap`` readers and
ROS 2 tools open.

One poller thread looks at every channel every ``POLL_S`` (:class:`mds_ach.record.stream.FrameStream`), takes
each new frame and hands it on with the time it took it; one writer (this thread) decodes the frames
(:mod:`mds_ach.record.schema`) and writes them (:mod:`mds_ach.record.sink`). The poller never waits for the
writer: a writer that cannot keep up drops frames from its queue and says how many (``dropped``); the channels'
writers never notice either way.

Each message's log time is when the recorder took the frame (wall clock); its publish time is the frame's own stamp
(``time``/``stamp``, CLOCK_MONOTONIC, moved onto the wall clock) where it has one. ``mds-state`` is also written as
``sensor_msgs/JointState`` on ``/joint_states``. The daemon's CAN frames come from its CAN log (``--can-log``).

Stops on ``--duration``, Ctrl-C or SIGTERM (the file is finished: summary and footer), and before the disk is full
(the file is finished too, with a message). A system that stops or restarts while it records is followed: channels
that vanish are waited for and read again from their first frame once re-created.
"""

from __future__ import annotations

import argparse
import os
import queue
import signal
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mds_ach import ach
from mds_ach.argtypes import bounded
from mds_ach.record import canlog
from mds_ach.record import schema as wire
from mds_ach.record.sink import DiskFullError, RecordingSink
from mds_ach.record.stream import Frame, FrameStream
from mds_ach.robot import contracts
from mds_ach.robot.msgs import MDS_STATE

LATCHED: frozenset[str] = frozenset({contracts.MDS_CHAN_PARAM_NAME, contracts.MDS_CHAN_LIMITS_NAME})
"""Channels written once when the daemon starts: every part of a split recording starts with their newest frame."""
POLL_S = 0.002
"""How often every channel is looked at: mds-state's ring holds two frames, so up to 500 Hz nothing is missed
(a faster daemon's overwritten frames are counted as ``missed``)."""
QUEUE_MAX = 20_000
"""Frames waiting for the writer at most (about 300 MB of mds-state); beyond, frames are dropped and counted."""
PROG = "mds-ach record"


@dataclass
class ChannelStats:
    frames: int = 0  # written
    missed: int = 0  # overwritten in the ring before the reader came
    bad: int = 0  # frames of the wrong size
    reopened: int = 0  # times the channel was re-created while recording


@dataclass
class RecordResult:
    parts: list[Path]
    messages: int
    seconds: float
    bytes: int
    stats: dict[str, ChannelStats] = field(default_factory=dict)
    dropped: int = 0
    can_frames: int = 0
    stopped_by: str = ""  # "duration", "interrupt", "disk full: ..."


class Recorder:
    """Records ``channels`` into ``sink`` until ``stop()`` (or ``duration``)."""

    def __init__(self, sink: RecordingSink, channels: list[str]) -> None:
        self.sink = sink
        self.channels = channels
        self.contracts = {name: contracts.contract(name) for name in channels}
        self.streams = {name: FrameStream(name) for name in channels}
        self.queue: queue.Queue[tuple[str, Frame]] = queue.Queue(maxsize=QUEUE_MAX)
        self.stats = {name: ChannelStats() for name in channels}
        self.dropped = 0
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.offset_ns = time.time_ns() - time.monotonic_ns()  # CLOCK_MONOTONIC -> wall clock

    def _poll(self) -> None:
        """Every ``POLL_S``: the new frames of every channel, onto the writer's queue (never waiting for it)."""
        next_t = time.monotonic()
        while not self._stop.is_set():
            for name, stream in self.streams.items():
                for frame in stream.poll():
                    try:
                        self.queue.put_nowait((name, frame))
                    except queue.Full:
                        self.dropped += 1
            next_t += POLL_S
            delay = next_t - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                next_t = time.monotonic()

    def start(self) -> None:
        t = threading.Thread(target=self._poll, name="record-poll", daemon=True)
        t.start()
        self._threads.append(t)

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        for s in self.streams.values():
            s.stop()
            s.close()

    def write(self, name: str, frame: Frame) -> None:
        c = self.contracts[name]
        st = self.stats[name]
        st.missed += frame.missed
        if len(frame.data) != c.size:
            st.bad += 1
            return
        decoded = c.decode(frame.data)
        ws = wire.wire_schema(c.struct)
        own = wire.frame_time(decoded)
        publish = int(own * 1e9) + self.offset_ns if own is not None else frame.wall_ns
        self.sink.write(wire.topic(name), (ws.name, ws.text), ws.to_message(decoded), frame.wall_ns, publish,
                        latch=name in LATCHED, sequence=frame.seq)
        if c.struct is MDS_STATE:
            self.sink.write(wire.JOINT_STATES_TOPIC, (wire.JOINT_STATE_TYPE, wire.JOINT_STATE_TEXT),
                            wire.joint_state(decoded, publish), frame.wall_ns, publish, sequence=frame.seq)
        st.frames += 1

    def drain(self, until: float) -> bool:
        """Write queued frames until monotonic time ``until``; False when nothing came."""
        got = False
        while True:
            left = until - time.monotonic()
            if left <= 0:
                return got
            try:
                name, frame = self.queue.get(timeout=left)
            except queue.Empty:
                return got
            self.write(name, frame)
            got = True

    def flush_queue(self) -> None:
        while True:
            try:
                name, frame = self.queue.get_nowait()
            except queue.Empty:
                return
            self.write(name, frame)

    def reopened(self) -> None:
        for name, s in self.streams.items():
            self.stats[name].reopened = max(0, s.opened - 1)


def parse_size(text: str) -> int:
    """``500M``, ``2G``, ``100k``, ``1000000`` -> bytes."""
    units = {"": 1, "k": 10**3, "m": 10**6, "g": 10**9}
    t = text.strip().lower().removesuffix("b")
    unit = t[-1:] if t[-1:] in units and t[-1:] else ""
    try:
        value = float(t[: len(t) - len(unit)])
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a size: give e.g. 500M, 2G or 100000 (bytes)") from None
    if not (value > 0 and value * units[unit] >= 1e5):
        raise argparse.ArgumentTypeError(f"{text}: a part must hold at least 100k bytes")
    return int(value * units[unit])


def parse_duration(text: str) -> float:
    """``90``, ``90s``, ``10min``, ``2h`` -> seconds."""
    t = text.strip().lower()
    for suffix, factor in (("min", 60.0), ("h", 3600.0), ("s", 1.0), ("m", 60.0)):
        if t.endswith(suffix):
            t, scale = t[: -len(suffix)], factor
            break
    else:
        scale = 1.0
    try:
        value = float(t) * scale
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a duration: give e.g. 90, 90s, 10min or 2h") from None
    if not (1.0 <= value <= 7 * 86400):
        raise argparse.ArgumentTypeError(f"{text}: give a duration between 1 s and 7 days")
    return value


def parse_split(text: str) -> tuple[int | None, float | None]:
    """``--split``: a size (``500M``) or a time (``10min``); (bytes, None) or (None, seconds)."""
    t = text.strip().lower()
    if t.endswith(("min", "h", "s")) and not t.endswith("kb"):
        return None, parse_duration(t)
    return parse_size(t), None


def channel_list(text: str) -> list[str]:
    names = [n.strip() for n in text.replace(",", " ").split() if n.strip()]
    unknown = [n for n in names if contracts.lookup(n) is None]
    if unknown:
        raise argparse.ArgumentTypeError(f"not MDS channels: {', '.join(unknown)} (known: "
                                         f"{', '.join(contracts.ALL_CHANNELS)})")
    return names


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Record every channel of a running system (state, every reference stage, collision report, mux "
                     "state, daemon status, hold, IK requests and answers, limits, joint table) into an MCAP file: "
                     "each frame as a typed ROS 2 message (mds_ach_wire/msg/*, mds-state also as "
                     "sensor_msgs/JointState on /joint_states) with its own time stamp. Foxglove, the mcap readers "
                     "and ROS 2 tools open it; 'mds-ach plot' draws it. Reads the channels as a normal reader (the "
                     "writers never wait for it); Ctrl-C or SIGTERM ends the file properly; it stops with a message "
                     "before the disk is full; a system that stops or restarts while it records is followed.")
    p.add_argument("file", metavar="FILE.mcap",
                   help="the recording (with --split: FILE-0001.mcap, FILE-0002.mcap, ...)")
    p.add_argument("--duration", type=bounded(0.0, 7 * 86400.0, above=True, unit="s"), metavar="S",
                   help="stop after S seconds (default: until Ctrl-C)")
    p.add_argument("--channels", type=channel_list, metavar="NAMES",
                   help="comma-separated channels to record (default: every MDS channel)")
    p.add_argument("--split", type=parse_split, metavar="SIZE|TIME",
                   help="start a new file at this size (e.g. 500M, 2G) or age (e.g. 10min, 1h); each part is a "
                        "complete recording that starts with the joint table and limits")
    p.add_argument("--can-log", metavar="FILE",
                   help="the daemon's CAN log (daemon --can-log FILE.log or .blf): its frames within the recording's "
                        "time are added on /can/frames when the recording ends (for 'mds-ach check-log FILE.mcap')")
    p.add_argument("--force", action="store_true", help="overwrite FILE if it exists")
    p.add_argument("-q", "--quiet", action="store_true", help="print only the summary")


def record(path: Path, channels: list[str], *, duration: float | None = None,
           split: tuple[int | None, float | None] | None = None, can_log: str | None = None,
           progress: Any = None, stop: threading.Event | None = None) -> RecordResult:
    """Record until ``duration`` s passed, ``stop`` is set, Ctrl-C / SIGTERM (KeyboardInterrupt) or the disk is
    full. ``progress(text)`` gets a status line every few seconds."""
    split_bytes, split_seconds = split if split is not None else (None, None)
    can_frames = [0]

    def add_can_frames(sink: RecordingSink, start: float, end: float) -> None:
        """Before a part is finished: the daemon's CAN frames of its time span."""
        assert can_log is not None
        for msg in canlog.frames_between(can_log, start, end):
            ns = int(round(msg.timestamp * 1e9))
            sink.write_now(canlog.CAN_TOPIC, canlog.CAN_SCHEMA, canlog.to_message(msg), ns, ns)
            can_frames[0] += 1

    meta = {"recorder": PROG, "host": socket.gethostname(), "channels": ",".join(channels),
            "started": f"{time.time():.6f}", "robot": os.environ.get("MDS_ACH_ROBOT", ""),
            "clock": "log_time: wall clock when recorded; publish_time: the frame's own stamp (monotonic->wall)"}
    sink = RecordingSink(path, split_bytes=split_bytes, split_seconds=split_seconds, metadata=meta,
                         before_finish=add_can_frames if can_log else None)
    rec = Recorder(sink, channels)
    t0 = time.monotonic()
    end = t0 + duration if duration is not None else float("inf")
    stopped_by = "duration"
    next_report = t0 + 5.0
    rec.start()
    try:
        try:
            while time.monotonic() < end and not (stop is not None and stop.is_set()):
                rec.drain(min(end, time.monotonic() + 0.2))
                if progress is not None and time.monotonic() >= next_report:
                    next_report += 5.0
                    progress(f"{time.monotonic() - t0:7.1f} s  {sink.messages} messages  {sink.size() / 1e6:.1f} MB"
                             + (f"  dropped {rec.dropped}" if rec.dropped else ""))
            if stop is not None and stop.is_set():
                stopped_by = "stop"
        except KeyboardInterrupt:
            stopped_by = "interrupt"
        finally:
            rec.stop()
        rec.flush_queue()
        sink.close()
    except DiskFullError as exc:
        stopped_by = f"disk full: {exc}"
        rec.stop()
    rec.reopened()
    result = RecordResult(sink.parts, sink.messages, time.monotonic() - t0, sink.size(), rec.stats, rec.dropped,
                          can_frames=can_frames[0], stopped_by=stopped_by)
    return result


def run(args: argparse.Namespace) -> int:
    path = Path(args.file)
    if path.suffix != ".mcap":
        print(f"{PROG}: {path}: the recording's name must end in .mcap", file=sys.stderr)
        return 2
    if path.exists() and not args.force:
        print(f"{PROG}: {path} exists (--force overwrites it)", file=sys.stderr)
        return 1
    if not path.parent.is_dir():
        print(f"{PROG}: {path.parent} is not a directory", file=sys.stderr)
        return 1
    if args.can_log and not Path(args.can_log).exists():
        print(f"{PROG}: --can-log {args.can_log}: no such file (the daemon's --can-log)", file=sys.stderr)
        return 1
    channels = args.channels or list(contracts.ALL_CHANNELS)
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # past ulimit -f a write fails (EFBIG) instead of killing us
    signal.signal(signal.SIGHUP, _interrupt)  # a closed terminal ends the recording like Ctrl-C: the file finished
    say = None if args.quiet else (lambda text: print(f"{PROG}: {text}", file=sys.stderr, flush=True))
    if say is not None:
        say(f"recording {len(channels)} channels to {path}" + (" (split)" if args.split else "")
            + ("; Ctrl-C stops" if args.duration is None else f" for {args.duration:g} s"))
    if say is not None and not any(ach.exists(name) for name in channels):
        say("no channel exists yet (is the system started?): frames are recorded as soon as they appear")
    try:
        result = record(path, channels, duration=args.duration, split=args.split, can_log=args.can_log,
                        progress=say)
    except DiskFullError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 1
    except (OSError, canlog.CanLogError) as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 1
    print(summary(result))
    return 1 if result.stopped_by.startswith("disk full") else 0


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def summary(r: RecordResult) -> str:
    lines = [f"recorded {r.messages} messages in {r.seconds:.1f} s, {r.bytes / 1e6:.2f} MB: "
             + ", ".join(str(p) for p in r.parts)]
    for name, st in r.stats.items():
        if st.frames or st.missed or st.bad:
            extra = "".join(f", {v} {k}" for k, v in (("missed (ring overwritten)", st.missed), ("wrong size", st.bad),
                                                      ("re-created", st.reopened)) if v)
            lines.append(f"  {name:<18} {st.frames} frames{extra}")
    if r.dropped:
        lines.append(f"  {r.dropped} frames dropped: the writer could not keep up")
    if r.can_frames:
        lines.append(f"  {r.can_frames} CAN frames from the daemon's CAN log on {canlog.CAN_TOPIC}")
    if r.stopped_by.startswith("disk full"):
        lines.append(f"stopped: {r.stopped_by.removeprefix('disk full: ')}; the file holds everything up to the stop")
    return "\n".join(lines)
