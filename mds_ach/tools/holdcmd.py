"""``mds-ach hold`` / ``mds-ach resume``: the command lifecycle from the shell (``mds_ach.robot.lifecycle``).

``mds-ach hold`` stops every joint (or the named ones) where the pipeline has them; nothing moves until
``mds-ach resume`` or a new command for a joint. Exit status 0 when the mux acknowledged the request, 1 when
it did not (not running, or it refused the request): the message says which.
"""

from __future__ import annotations

import argparse
import sys

import mds_ach as mds
from mds_ach import ach
from mds_ach.ach.watch import Latest
from mds_ach.argtypes import seconds
from mds_ach.robot import lifecycle
from mds_ach.robot.joints import JOINTS
from mds_ach.robot.msgs import MDS_MUX_STATE
from mds_ach.robot.msgs.mux_state import MUX_CANCELLED, MUX_HELD


def enabled_joints(state: mds.MDS_STATE | None) -> set[int] | None:
    """Addresses of the joints the daemon drives (``mds-state`` ``joint[].enabled``); None without a state."""
    if state is None:
        return None
    return {j.address for j in JOINTS if state.joint[j.address].enabled}


def newest_enabled() -> set[int] | None:
    """:func:`enabled_joints` of the newest ``mds-state`` frame (None when there is none)."""
    watch = Latest(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE)
    try:
        return enabled_joints(watch.read())
    finally:
        watch.close()


def held_summary(st: MDS_MUX_STATE | None, enabled: set[int] | None = None, resume: str = "mds-ach resume") -> str:
    """One line for ``mds-ach status``, ``hold`` and the console: which joints the mux holds (and which are
    cancelled). With ``enabled`` (:func:`enabled_joints`) only those are named: the mux holds the disabled ones too
    ("hold all" holds every address), but they never move anyway, and 43 names hide the ones that matter."""
    if st is None:
        return "unknown (no mds-mux-state: is the mux running?)"
    shown = [j for j in JOINTS if enabled is None or j.address in enabled]

    def names(flag: int) -> str:
        these = [j.short for j in shown if st.held[j.address] == flag]
        if enabled and len(these) == len(shown):
            return f"every enabled joint ({len(these)})"
        return " ".join(these)

    parts = []
    if held := names(MUX_HELD):
        parts.append(f"held {held} ({resume})")
    if cancelled := names(MUX_CANCELLED):
        parts.append(f"cancelled {cancelled} (until a new command)")
    return "; ".join(parts) if parts else "none"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("joints", nargs="*", metavar="JOINT",
                   help="joint names (LSP, LeftShoulderExt), left, right, arms or all (default: all)")
    p.add_argument("--reason", default="", help="why, for the mux's log")
    p.add_argument("--timeout", type=seconds(), default=lifecycle.ACK_TIMEOUT,
                   help="s to wait for the mux's acknowledgement (default %(default)s)")


def _run(args: argparse.Namespace, verb: str) -> int:
    from mds_ach.tools.console import CommandError, Hold, parse  # the console's joint/arm selection: one parser

    try:
        cmd = parse(" ".join([verb, *args.joints]))
    except CommandError as exc:
        print(f"mds-ach {verb}: {exc}", file=sys.stderr)
        return 2
    assert isinstance(cmd, Hold)
    try:
        ack = lifecycle.request(cmd.action, cmd.addresses, source="mds-ach",
                                reason=args.reason or f"mds-ach {verb}", timeout=args.timeout)
    except ach.AchException as exc:  # a channel missing, damaged, planted by another user, a FIFO...
        print(f"mds-ach {verb}: nothing sent: {exc}", file=sys.stderr)
        return 1
    if not ack.ok:
        print(f"mds-ach {verb}: {ack.message}", file=sys.stderr)
        return 1
    print(f"{verb}: {cmd.what}; {ack.message}; held now: {held_summary(ack.state, newest_enabled())}")
    return 0


def run_hold(args: argparse.Namespace) -> int:
    return _run(args, "hold")


def run_resume(args: argparse.Namespace) -> int:
    return _run(args, "resume")
