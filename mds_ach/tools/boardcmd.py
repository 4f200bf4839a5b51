"""``mds-ach enable|home|zero|reset JOINT...``: the daemon's setup commands, sent as an operator.

Each is one ``MDS_CMD`` on ``mds-cmd`` per joint (the channel only the operators' group may write, see
docs/operator.md), waited for until the daemon echoes its sequence number in ``mds-daemon-status``. ``zero``
(ZERO_ENCODER) and ``reset`` (RESET) restart the node's encoder count where the joint stands: the daemon then marks
the joint *unreferenced* and moves it no more until ``home``; the ROS command service refuses them unless the daemon
allows it (``allow_encoder_commands``). ``enable`` also clears a joint's follow fault (mode 2/3).
"""

from __future__ import annotations

import argparse
import sys
import time

import mds_ach as mds
from mds_ach import ach
from mds_ach.ach.watch import Latest
from mds_ach.argtypes import seconds
from mds_ach.paths import runtime_dir
from mds_ach.robot.msgs.daemon_status import CMD_OK, CMD_REFUSED, MDS_DAEMON_STATUS

COMMANDS: dict[str, int] = {"enable": mds.MDS_CMD_ENABLE, "home": mds.MDS_CMD_HOME, "zero": mds.MDS_CMD_ZERO_ENCODER,
                            "reset": mds.MDS_CMD_RESET}  # the verbs (their help: mds_ach.tools.cli.VERBS)
MAX_TIMEOUT = 600.0  # s


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("joints", nargs="+", metavar="JOINT", help="short or long joint names, addresses, or 'all' (every "
                                                              "enabled joint)")
    p.add_argument("--timeout", type=seconds(MAX_TIMEOUT), default=5.0,
                   help="seconds to wait for the daemon's answer to each")


def run(args: argparse.Namespace) -> int:
    verb = args.verb
    code = COMMANDS[verb]
    from mds_ach.nodes.daemon import (
        parse_joint_command,  # lazy: the node module loads rclpy; one parser for CLI and ROS
    )

    try:
        targets = [(label, address) for label, _, address in parse_joint_command(verb, args.joints)]
    except ValueError as exc:
        print(f"mds-ach {verb}: {exc}", file=sys.stderr)
        return 2
    from mds_ach.tools.launcher import send_command  # (the one writer of mds-cmd)

    status = Latest(mds.MDS_CHAN_DAEMON_STATUS_NAME, MDS_DAEMON_STATUS)
    failed = 0
    try:
        status.read()
        for label, address in targets:
            try:
                seq = send_command(code, address)
            except ach.AchException as exc:
                print(f"mds-ach {verb}: cannot write {mds.MDS_CHAN_BOARD_CMD_NAME}: {exc} (is the system started? "
                      "only the operators' group may write it)", file=sys.stderr)
                return 1
            st = _answer(status, seq, args.timeout)
            if st is None:
                print(f"mds-ach {verb}: {label}: no answer from the daemon within {args.timeout:g} s (is it running? "
                      f"'mds-ach status'; its log: {runtime_dir() / 'daemon.log'})", file=sys.stderr)
                return 1
            if st.cmd_result != CMD_OK:
                why = "refused" if st.cmd_result == CMD_REFUSED else "not sent (bus error)"
                print(f"mds-ach {verb}: {label}: {why}; the daemon's log says why ({runtime_dir() / 'daemon.log'})",
                      file=sys.stderr)
                failed += 1
                continue
            note = ""
            if code in (mds.MDS_CMD_ZERO_ENCODER, mds.MDS_CMD_RESET):
                note = f" -- unreferenced: no motion until 'mds-ach home {label}'"
            elif code == mds.MDS_CMD_HOME:
                note = " (it moves to the middle of its range; 'mds-ach read' shows UNREF until it has settled)"
            print(f"{verb} {label}: done{note}")
    finally:
        status.close()
    return 1 if failed else 0


def _answer(status: Latest, seq: int, timeout: float) -> MDS_DAEMON_STATUS | None:
    """The first status frame that echoes ``seq`` (the daemon handled that command), or None after ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        st = status.wait_new(0.2)
        if st is not None and st.cmd_seq == seq:
            return st
    return None

