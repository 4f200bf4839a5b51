"""``mds-ach hold`` / ``mds-ach resume``: the command lifecycle from the shell (``mds_ach.robot.lifecycle``).

``mds-ach hold`` stops every joint (or the named ones) where the pipeline has them; nothing moves until
``mds-ach resume`` or a new command for a joint. Exit status 0 when the mux acknowledged the request, 1 when
it did not (not running, or it refused the request): the message says which.
"""

from __future__ import annotations

import argparse
import sys

from mds_ach import ach
from mds_ach.argtypes import seconds
from mds_ach.robot import lifecycle
from mds_ach.robot.joints import JOINTS
from mds_ach.robot.msgs import MDS_MUX_STATE
from mds_ach.robot.msgs.mux_state import MUX_CANCELLED, MUX_HELD


def held_summary(st: MDS_MUX_STATE | None) -> str:
    """One line for ``mds-ach status`` and the console: which joints the mux holds (and which are cancelled)."""
    if st is None:
        return "unknown (no mds-mux-state: is the mux running?)"
    held = [j.short for j in JOINTS if st.held[j.address] == MUX_HELD]
    cancelled = [j.short for j in JOINTS if st.held[j.address] == MUX_CANCELLED]
    parts = []
    if held:
        parts.append(f"held {' '.join(held)} (mds-ach resume)")
    if cancelled:
        parts.append(f"cancelled {' '.join(cancelled)} (until a new command)")
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
    print(f"{verb}: {cmd.what}; {ack.message}; held now: {held_summary(ack.state)}")
    return 0


def run_hold(args: argparse.Namespace) -> int:
    return _run(args, "hold")


def run_resume(args: argparse.Namespace) -> int:
    return _run(args, "resume")
