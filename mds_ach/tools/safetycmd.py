"""``mds-ach mode [collaborative|normal]`` and ``mds-ach estop [reset]``: the operator's safety commands.

Each is one ``MDS_CMD`` on ``mds-cmd`` (the channel only the operators' group may write), waited for until the
daemon echoes its sequence number in ``mds-daemon-status``; without an argument ``mode`` shows the current mode.
``estop`` is the category-1 e-stop (docs/reliability.md): every joint brakes at the bounds, then the daemon sends
DISABLE to every drive; it stays latched -- across restarts of the daemon too -- until ``mds-ach estop reset``, after
which ``mds-ach enable all`` restarts every joint where it stands.
"""

from __future__ import annotations

import argparse
import sys

import mds_ach as mds
from mds_ach import ach
from mds_ach.ach.watch import Latest
from mds_ach.argtypes import seconds
from mds_ach.paths import runtime_dir
from mds_ach.robot.msgs import daemon_status as ds

MAX_TIMEOUT = 600.0  # s
DEFAULT_TIMEOUT = 5.0  # s
MODES = {"collaborative": 1.0, "normal": 0.0}


def add_mode_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("mode", nargs="?", choices=sorted(MODES),
                   help="collaborative: every hand and elbow <= the Cartesian bound (250 mm/s or the joint table's "
                        "lower value) on every target the daemon sends; normal: the joint bounds only. Without it: "
                        "show the mode")
    p.add_argument("--timeout", type=seconds(MAX_TIMEOUT), default=DEFAULT_TIMEOUT,
                   help="seconds to wait for the daemon")


def add_estop_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", nargs="?", choices=["reset", "show"],
                   help="reset: clear a latched e-stop (the drives stay disabled until 'mds-ach enable all'); "
                        "show: its state. Without it: E-STOP")
    p.add_argument("--timeout", type=seconds(MAX_TIMEOUT), default=DEFAULT_TIMEOUT,
                   help="seconds to wait for the daemon")


def run_mode(args: argparse.Namespace) -> int:
    if args.mode is None:
        return _show("mode", args.timeout)
    return _send("mode", mds.MDS_CMD_MODE, MODES[args.mode], args.timeout)


def run_estop(args: argparse.Namespace) -> int:
    if args.action == "show":
        return _show("estop", args.timeout)
    if args.action == "reset":
        return _send("estop reset", mds.MDS_CMD_ESTOP_RESET, 0.0, args.timeout)
    return _send("estop", mds.MDS_CMD_ESTOP, 0.0, args.timeout)


def _show(verb: str, timeout: float) -> int:
    status = Latest(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS)
    try:
        st = status.wait_new(timeout)
    finally:
        status.close()
    if st is None:
        print(f"mds-ach {verb}: no status from the daemon within {timeout:g} s (is it running? 'mds-ach status')",
              file=sys.stderr)
        return 1
    print(ds.safety_text(st))
    return 0


def send(code: int, value: float, timeout: float) -> tuple[bool, str]:
    """One safety command on ``mds-cmd``, waited for: (done, what the daemon's status says or why not)."""
    from mds_ach.tools.boardcmd import _answer
    from mds_ach.tools.launcher import send_command  # (the one writer of mds-cmd)

    status = Latest(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS)
    try:
        status.read()
        try:
            seq = send_command(code, 0, value)
        except ach.AchException as exc:
            return False, (f"cannot write {mds.MDS_CHAN_BOARD_CMD_NAME}: {exc} (is the system started? only the "
                           "operators' group may write it)")
        st = _answer(status, seq, timeout)
    finally:
        status.close()
    if st is None:
        return False, (f"no answer from the daemon within {timeout:g} s (is it running? 'mds-ach status'; its log: "
                       f"{runtime_dir() / 'daemon.log'})")
    if st.cmd_result != ds.CMD_OK:
        return False, f"refused; the daemon's log says why ({runtime_dir() / 'daemon.log'})"
    return True, ds.safety_text(st)


def _send(verb: str, code: int, value: float, timeout: float) -> int:
    ok, text = send(code, value, timeout)
    if not ok:
        print(f"mds-ach {verb}: {text}", file=sys.stderr)
        return 1
    print(f"{verb}: done -- {text}")
    return 0
