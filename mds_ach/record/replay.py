"""``mds-ach replay FILE.mcap --to-channels``: a recording's observed state back onto the channels, for the viewer,
``mds-ach read``, plots and clients -- on a system that runs no daemon. A recording never drives a robot.

What it writes: only what the stack *reports* (``REPLAYED``: state, joint table, limits, collision report, daemon
status, mux state, IK answers), never a reference stage (``mds-ref*``: ``mds-ref-gated`` is what a daemon executes),
a board command, an IK request or a hold request. And only while no daemon is live:

* before it starts: no daemon in the runtime dir (the launcher's pid file), and no new frame on
  ``mds-daemon-status`` or ``mds-state`` within ``LIVE_WINDOW_S`` (a daemon started any other way, or another
  replay);
* while it runs: its own frames are the only ones on the channels it writes (their sequence number moves only by
  its puts) and no daemon appears in the runtime dir; otherwise it stops at once and says why.

Frames keep their recorded bytes (time stamps included) and their recorded spacing (``--speed`` scales it).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from mds_ach import ach
from mds_ach.ach.watch import Latest
from mds_ach.argtypes import bounded
from mds_ach.record import schema as wire
from mds_ach.record.recording import RecordingError, iter_messages
from mds_ach.robot import contracts
from mds_ach.robot.channels import make_channels

PROG = "mds-ach replay"
REPLAYED: tuple[str, ...] = (contracts.MDS_CHAN_STATE_NAME, contracts.MDS_CHAN_PARAM_NAME,
                             contracts.MDS_CHAN_LIMITS_NAME, contracts.MDS_CHAN_COLLIDE_NAME,
                             contracts.MDS_CHAN_DAEMON_STATUS_NAME, contracts.MDS_CHAN_MUX_STATE_NAME,
                             contracts.MDS_CHAN_IK_STATE_NAME)
"""The channels a replay writes: reports only. A daemon executes none of them."""
LIVE_WINDOW_S = 1.0
"""A daemon publishes mds-daemon-status and mds-state every cycle (at least 10 Hz): one second without a new
frame on either means none runs."""
CHECK_EVERY_S = 0.5


class DaemonLive(Exception):  # noqa: N818 - a condition, said to the user
    """A daemon (or another writer) is live on the channels: the replay must not write them."""


def daemon_live(window: float = LIVE_WINDOW_S) -> str:
    """Why a daemon counts as live ("" if none is): its pid file, or new frames on its channels within ``window``."""
    from mds_ach.tools.launcher import read_pid  # the launcher's own test of a running node

    pid = read_pid("daemon")
    if pid is not None:
        return f"the daemon runs (pid {pid}; 'mds-ach stop' stops it)"
    watched = [Latest(name, contracts.contract(name).struct)
               for name in (contracts.MDS_CHAN_DAEMON_STATUS_NAME, contracts.MDS_CHAN_STATE_NAME)]
    try:
        for w in watched:
            w.read()  # what is there already does not count: only frames that arrive
        deadline = time.monotonic() + window
        while time.monotonic() < deadline:
            for w in watched:
                if w.read_new() is not None and w.frames > 1:
                    return (f"{w.name} is being written (a daemon, or another replay): stop it first")
            time.sleep(0.02)
    finally:
        for w in watched:
            w.close()
    return ""


@dataclass
class ReplayResult:
    frames: int
    seconds: float
    stopped: str = ""  # why it stopped early


def replay(path: Path, channels: tuple[str, ...] = REPLAYED, speed: float = 1.0, check_daemon: bool = True
           ) -> ReplayResult:
    """Write the recorded frames of ``channels`` onto them, spaced as recorded (``/ speed``). Raises DaemonLive
    before writing anything when a daemon is live; stops (``stopped``) when one appears."""
    if check_daemon and (why := daemon_live()):
        raise DaemonLive(why)
    topics = {wire.topic(c): c for c in channels}
    make_channels(list(channels))
    handles = {c: ach.Channel(c, create=False) for c in channels}
    ours = {c: h.last_seq for c, h in handles.items()}
    frames, t_start = 0, time.monotonic()
    first_ns: int | None = None
    next_check = 0.0
    stopped = ""
    try:
        for r in iter_messages(path, set(topics)):
            name = topics[r.topic]
            if first_ns is None:
                first_ns = r.log_ns
            due = t_start + (r.log_ns - first_ns) / 1e9 / speed
            while (wait := due - time.monotonic()) > 0:
                time.sleep(min(wait, CHECK_EVERY_S))
                if check_daemon and time.monotonic() >= next_check:
                    next_check = time.monotonic() + CHECK_EVERY_S
                    stopped = _foreign(handles, ours)
                    if stopped:
                        return ReplayResult(frames, time.monotonic() - t_start, stopped)
            if check_daemon and (why := _foreign({name: handles[name]}, ours)):
                return ReplayResult(frames, time.monotonic() - t_start, why)
            frame = wire.wire_schema(contracts.contract(name).struct).from_message(r.message)
            handles[name].put(frame)
            ours[name] = handles[name].last_seq
            frames += 1
    finally:
        for h in handles.values():
            h.close()
    return ReplayResult(frames, time.monotonic() - t_start, stopped)


def _foreign(handles: dict[str, ach.Channel], ours: dict[str, int]) -> str:
    """Why the replay must stop: another writer put a frame on a channel it writes, or a daemon started."""
    for name, h in handles.items():
        if h.last_seq != ours[name]:
            return f"another writer (a daemon?) put a frame on {name}: the replay stopped"
    from mds_ach.tools.launcher import read_pid

    pid = read_pid("daemon")
    return f"a daemon started (pid {pid}): the replay stopped" if pid is not None else ""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Write a recording's reported state (" + ", ".join(REPLAYED) + ") back onto the channels, "
                     "spaced as recorded, for the viewer, 'mds-ach read', plots and clients. Refuses while a daemon "
                     "is live and stops if one starts: a recording never drives a robot (no reference, command, IK "
                     "or hold request is ever replayed).")
    p.add_argument("file", metavar="FILE.mcap", help="a recording of 'mds-ach record'")
    p.add_argument("--to-channels", action="store_true", required=True,
                   help="write onto this machine's Ach channels (required: says what the replay does)")
    p.add_argument("--speed", type=bounded(0.01, 100.0, unit="x"), default=1.0, metavar="X",
                   help="play X times as fast as recorded (default 1)")
    p.add_argument("--channels", metavar="NAMES",
                   help=f"comma-separated subset of {', '.join(REPLAYED)} (default: all of them)")


def run(args: argparse.Namespace) -> int:
    channels = REPLAYED
    if args.channels:
        names = tuple(n.strip() for n in args.channels.replace(",", " ").split() if n.strip())
        bad = [n for n in names if n not in REPLAYED]
        if bad:
            print(f"{PROG}: {', '.join(bad)}: not replayed (a replay writes only {', '.join(REPLAYED)}; never a "
                  "reference, command or request)", file=sys.stderr)
            return 2
        channels = names
    path = Path(args.file)
    try:
        result = replay(path, channels, args.speed)
    except DaemonLive as exc:
        print(f"{PROG}: refused: {exc}; a recording never drives a robot", file=sys.stderr)
        return 1
    except RecordingError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 1
    except (ach.AchException, OSError, ValueError) as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return 1
    print(f"replayed {result.frames} frames in {result.seconds:.1f} s")
    if result.stopped:
        print(f"{PROG}: {result.stopped}", file=sys.stderr)
        return 1
    return 0
