"""``mds-ach read``: the live joint table of the original ``mds_read.py``, over any plain terminal.

Columns as in the original (short name, Joint, Enabled, address ``0x%04x``, Commanded Pos, Actual Pos) plus
whether each joint's reading is fresh, the ``[ Collisions ]`` block, the state's age and the daemon's loop
rate and bus load. Redrawn at ~20 Hz with ANSI escapes (no curses: it works on any terminal and through a
pseudo-terminal, and degrades to plain snapshots when the output is not a terminal). ``q`` or Ctrl-C quits.

Strictly read-only: channels are only opened, never created, flushed or written, so the monitor can start
and stop at any time without disturbing the system.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import select
import shutil
import signal
import sys
import termios
import time
import tty
from collections.abc import Sequence

import mds_ach as mds
from mds_ach.kinematics.limits import read_published
from mds_ach.nodes.rosargs import strip_ros_args
from mds_ach.robot.joints import BY_ADDRESS, JOINTS, lookup
from mds_ach.robot.msgs import get_name
from mds_ach.robot.msgs.daemon_status import MDS_DAEMON_STATUS
from mds_ach.tools.cli import help_paragraph
from mds_ach.tools.monitor import (
    Latest,
    collision_block,
    collision_summary,
    daemon_line,
    joint_fresh,
    recorded_table,
    table_line,
)

REFRESH = 0.05  # s (the original's 20 Hz)
HEADER = f"{'':<6}{'Joint':<24}{'Enabled':>8}  {'address':<8}{'Commanded Pos':>15}{'Actual Pos':>13}  {'Fresh':<5}"
STALE_AFTER = 1.0  # s without a new state frame before the whole table is marked stale

# ANSI: alternate screen, hide/show cursor, home, clear to end of line / of screen
ALT_ON, ALT_OFF = "\x1b[?1049h", "\x1b[?1049l"
CURSOR_OFF, CURSOR_ON = "\x1b[?25l", "\x1b[?25h"
HOME, CLEAR_EOL, CLEAR_EOS = "\x1b[H", "\x1b[K", "\x1b[J"


class Sources:
    """The channels the monitor shows, each opened read-only on demand."""

    def __init__(self) -> None:
        self.state = Latest(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE)
        self.collide = Latest(mds.MDS_CHAN_COLLIDE_NAME, mds.MDS_COLLIDE)
        self.daemon = Latest(mds.MDS_CHAN_DAEMON_STATUS_NAME, MDS_DAEMON_STATUS)

    def read(self) -> None:
        self.state.read()
        self.collide.read()
        self.daemon.read()

    def close(self) -> None:
        self.state.close()
        self.collide.close()
        self.daemon.close()


def table_rows(state: mds.MDS_STATE | None, daemon: ctypes.Structure | None, show_all: bool) -> list[str]:
    """One row per joint: enabled joints only (like ``read``) or every named joint (``read all``)."""
    rows = []
    for j in JOINTS:
        js = state.joint[j.address] if state is not None else None
        enabled = bool(js.enabled) if js is not None else False
        if js is not None and not show_all and not enabled:
            continue
        short = (get_name(js.nameshort) if js is not None else "") or j.short
        name = (get_name(js.name) if js is not None else "") or j.name
        if js is None:
            rows.append(f"{short:<6}{name:<24}{'-':>8}  0x{j.address:04x}  {'-':>15}{'-':>13}  {'-':<5}")
            continue
        fresh = joint_fresh(daemon, j.address)
        rows.append(f"{short:<6}{name:<24}{int(enabled):>8}  0x{j.address:04x}  {js.ref:>15.5f}{js.pos:>13.5f}  "
                    f"{fresh:<5}")
    return rows


def render(src: Sources, show_all: bool, width: int, height: int) -> list[str]:
    """The screen as lines, fitted to ``width`` x ``height`` (the joint rows are cut first, with a note)."""
    state = src.state.frame
    age = src.state.age()
    if state is None:
        state_text = f"waiting for {mds.MDS_CHAN_STATE_NAME} ({src.state.error or 'no frames yet'})"
    elif age is None:
        state_text = f"state time {state.time:.3f}  (waiting for a new frame)"
    elif age > STALE_AFTER:
        state_text = f"state time {state.time:.3f}  STALE: no new state for {age:.1f} s"
    else:
        state_text = f"state time {state.time:.3f}  age {age:.2f} s"
    top = [f"MDS-Ach read   {state_text}   [q quits]",
           f"daemon: {daemon_line(src.daemon.frame, src.daemon.age())}   collision: "
           f"{collision_summary(src.collide.frame)}",
           HEADER]
    rows = table_rows(state, src.daemon.frame, show_all)
    block = [""] + collision_block(src.collide.frame)
    room = height - len(top)
    if room >= len(rows) + len(block):
        lines = top + rows + block
    elif room >= len(rows):
        lines = top + rows
    else:
        keep = max(0, room - 1)
        lines = top + rows[:keep] + [f"... {len(rows) - keep} more joints: enlarge the terminal"]
    return [line[: max(1, width - 1)].rstrip() for line in lines[: max(1, height)]]


def snapshot(src: Sources, show_all: bool, wait: float = 1.0) -> list[str]:
    """One full table for scripts (``--once``): waits up to ``wait`` s for a new state frame first."""
    src.read()
    src.state.wait_new(wait)
    src.read()
    return render(src, show_all, 10_000, 10_000)


class _QuitError(Exception):
    pass


def _on_signal(signum: int, frame: object) -> None:
    raise _QuitError


def live(src: Sources, show_all: bool) -> int:
    """Redraw until q/Q, Ctrl-C or SIGTERM; always restores the terminal."""
    out = sys.stdout
    stdin_tty = sys.stdin.isatty()
    old_attrs = None
    previous = {s: signal.signal(s, _on_signal) for s in (signal.SIGTERM, signal.SIGHUP)}
    if stdin_tty:
        old_attrs = termios.tcgetattr(sys.stdin.fileno())
        tty.setcbreak(sys.stdin.fileno())
    out.write(ALT_ON + CURSOR_OFF)
    try:
        while True:
            src.read()
            size = shutil.get_terminal_size((100, 40))
            lines = render(src, show_all, size.columns, size.lines)
            out.write(HOME + "".join(line + CLEAR_EOL + "\r\n" for line in lines[:-1]) + lines[-1] + CLEAR_EOL
                      + CLEAR_EOS)
            out.flush()
            if _key_pressed(REFRESH, stdin_tty) in ("q", "Q"):
                break
    except (KeyboardInterrupt, _QuitError):
        pass
    finally:
        out.write(CURSOR_ON + ALT_OFF)
        out.flush()
        if old_attrs is not None:
            termios.tcsetattr(sys.stdin.fileno(), termios.TCSADRAIN, old_attrs)
        for s, handler in previous.items():
            signal.signal(s, handler)
    return 0


def _key_pressed(timeout: float, stdin_tty: bool) -> str:
    """Wait up to ``timeout`` s for one key on a terminal stdin; '' if none (or stdin is not a terminal)."""
    if not stdin_tty:
        time.sleep(timeout)
        return ""
    ready, _, _ = select.select([sys.stdin], [], [], timeout)
    if not ready:
        return ""
    data = os.read(sys.stdin.fileno(), 32)
    if not data:  # the terminal went away
        raise _QuitError
    return data.decode("utf-8", "replace")[-1:]


# --------------------------------------------------------------------------------------------- param


def param_lines(param: mds.MDS_JOINT_PARAM, address: int) -> list[str]:
    """Every field of one joint's ``mds_jnt_param_t``, like the original ``read param N``."""
    p = param.joint[address]
    lines = [f"param of address {address} (0x{address:04x})"]
    for name, _ctype in p._fields_:
        value = getattr(p, name)
        if isinstance(value, bytes):
            value = get_name(value)
        elif isinstance(value, float):
            value = f"{value:.6g}"
        lines.append(f"  {name:<28} {value}")
    return lines


def _address(text: str) -> int:
    try:
        value = int(text, 0)
    except ValueError:
        return lookup(text).address
    if not 0 <= value < mds.MDS_JOINT_COUNT:
        raise KeyError(f"address {value} is outside 0..{mds.MDS_JOINT_COUNT - 1}")
    return value


def show_param(which: str) -> int:
    try:
        address = _address(which)
    except KeyError as exc:
        print(f"read param: {exc.args[0]}", file=sys.stderr)
        return 2
    chan = Latest(mds.MDS_CHAN_PARAM_NAME, mds.MDS_JOINT_PARAM)
    try:
        param = chan.read()
        why = chan.error or "no frames"
    finally:
        chan.close()
    if param is None:
        print(f"read param: nothing on {mds.MDS_CHAN_PARAM_NAME} ({why}); the daemon publishes it at start",
              file=sys.stderr)
        return 1
    joint = BY_ADDRESS.get(address)
    print("\n".join(param_lines(param, address)) + ("" if joint else "\n  (no MDS joint at this address)"))
    print(f"  joint table: {table_line(read_published(), recorded_table())}")
    return 0


# --------------------------------------------------------------------------------------------- entry points


USAGE_EPILOG = """\
views:
  read            enabled joints (default)
  all             every joint of the table
  param N         every parameter of joint N (address such as 95 or 0x5f, or a name such as LSP)
keys: q quits (Ctrl-C too). Output that is not a terminal gets one snapshot, as with --once."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.description = help_paragraph(
        "Live joint table of the running system at ~20 Hz: Joint, Enabled, address, Commanded Pos, Actual Pos, "
        "freshness, the collision block and the daemon's rate and bus load. Read-only: it can start and stop at any "
        "time without disturbing anything.")
    p.epilog = USAGE_EPILOG
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.add_argument("view", nargs="*", default=["read"], metavar="VIEW", help="read | all | param N | help")
    p.add_argument("--once", action="store_true",
                   help="print one snapshot and exit: status 0 if the state is live (a new frame within 1 s), else 1")


def run(args: argparse.Namespace, parser: argparse.ArgumentParser | None = None) -> int:
    view = [w.lower() for w in args.view] or ["read"]
    if view[0] in ("help", "-h", "h"):
        (parser.print_help() if parser else print(USAGE_EPILOG))
        return 0
    if view[0] == "param":
        if len(view) != 2:
            print("read: usage: read param N", file=sys.stderr)
            return 2
        return show_param(args.view[1])
    if view not in (["read"], ["all"]):
        print(f"read: unknown view {' '.join(args.view)!r}\n{USAGE_EPILOG}", file=sys.stderr)
        return 2
    show_all = view == ["all"]
    src = Sources()
    try:
        if args.once or not sys.stdout.isatty():
            lines = snapshot(src, show_all)
            print("\n".join(lines))
            return 0 if src.state.frame is not None and src.state.age() is not None else 1
        return live(src, show_all)
    finally:
        src.close()


def main(argv: Sequence[str] | None = None) -> int:
    argv = strip_ros_args(list(sys.argv[1:] if argv is None else argv))
    parser = argparse.ArgumentParser(prog="read")
    add_arguments(parser)
    return run(parser.parse_args(argv), parser)


if __name__ == "__main__":
    raise SystemExit(main())
