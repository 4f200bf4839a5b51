"""``mds-ach``: the command-line front-end (``mds-ach <verb> [options]``).

Verbs live in a registry so that other modules add theirs with one line: ``VERBS[name] = Verb(help,
"module:add_arguments_function", "module:handler_function")``. The target modules are imported only
when their verb runs (or when that verb's ``--help`` is built), which keeps ``mds-ach --help`` and light verbs
fast: nothing here imports rclpy, torch or fcl.

A handler takes the parsed ``argparse.Namespace`` and returns the exit code: 0 success, 1 runtime failure
(message on stderr), 2 usage error (argparse does this itself).
"""

from __future__ import annotations

import argparse
import importlib
import shutil
import signal
import sys
import textwrap
from collections.abc import Callable
from typing import NamedTuple

from mds_ach.nodes.rosargs import strip_ros_args  # cli.strip_ros_args stays importable

PROG = "mds-ach"
EPILOG = """\
Run '{prog} VERB --help' for a verb's options.

Exit codes:
  0    ok
  1    failure (the message says why)
  2    usage error; also check-log: a file could not be audited, changerobot: an unknown robot
  3    status: a node is not running (none running included)
  130  start: interrupted by Ctrl-C (the nodes it had started are stopped again)
  ros, ros-shell: the command's own exit status; 126 it cannot be executed, 127 it is not found"""


class Verb(NamedTuple):
    """One sub-command: one-line help, and "module:function" strings resolved lazily."""

    help: str
    add_arguments: str  # f(parser: argparse.ArgumentParser) -> None
    handler: str  # f(args: argparse.Namespace) -> int


VERBS: dict[str, Verb] = {
    "make": Verb("create every MDS Ach channel (existing ones are checked, not clobbered)",
                 "mds_ach.tools.chantool:add_make_arguments", "mds_ach.tools.chantool:run_make"),
    "rm": Verb("remove Ach channels (default: every MDS channel)",
               "mds_ach.tools.chantool:add_rm_arguments", "mds_ach.tools.chantool:run_rm"),
    "dump": Verb("print the newest frame of a channel, decoded by its type",
                 "mds_ach.tools.chantool:add_dump_arguments", "mds_ach.tools.chantool:run_dump"),
    "repair": Verb("check the channels; repair corrupt ones in place (a writer killed inside a put)",
                   "mds_ach.tools.repair:add_arguments", "mds_ach.tools.repair:run"),
    "limits": Verb("the joint limits each joint can follow (range, velocity, acceleration); --moveit-yaml writes "
                   "MoveIt's joint_limits.yaml",
                   "mds_ach.tools.limitscmd:add_arguments", "mds_ach.tools.limitscmd:run"),
    "py2to3": Verb("convert an original MDS-Ach Python 2 program to Python 3 (print, import ach, raw_input, ...)",
                   "mds_ach.tools.py2to3:add_arguments", "mds_ach.tools.py2to3:run"),
    "check-log": Verb("audit a CAN log: targets finite, in limits, to enabled joints, within speed/acceleration",
                      "mds_ach.tools.checklog:add_arguments", "mds_ach.tools.checklog:run"),
    # operator verbs (mds_ach.tools.launcher, console, read)
    "start": Verb("start every node as its own process ('start nocan': simulated bus); returns when state is live",
                  "mds_ach.tools.launcher:add_start_arguments", "mds_ach.tools.launcher:run_start"),
    "run": Verb("start everything in the foreground; Ctrl-C stops it all ('make run' = 'run --nocan')",
                "mds_ach.tools.launcher:add_run_arguments", "mds_ach.tools.launcher:run_run"),
    "stop": Verb("stop the nodes (SIGTERM, then SIGKILL after a grace time)",
                 "mds_ach.tools.launcher:add_stop_arguments", "mds_ach.tools.launcher:run_stop"),
    "kill": Verb("SIGKILL every node", "mds_ach.tools.launcher:add_kill_arguments", "mds_ach.tools.launcher:run_kill"),
    "killall": Verb("SIGKILL every node and remove every MDS channel",
                    "mds_ach.tools.launcher:add_killall_arguments", "mds_ach.tools.launcher:run_killall"),
    "status": Verb("which nodes run, loop rate, bus load, collision state",
                   "mds_ach.tools.launcher:add_status_arguments", "mds_ach.tools.launcher:run_status"),
    "resetbus": Verb("ask the daemon to reset the CAN bus (bus-off recovery)",
                     "mds_ach.tools.launcher:add_resetbus_arguments", "mds_ach.tools.launcher:run_resetbus"),
    **{name: Verb(text, "mds_ach.tools.boardcmd:add_arguments", "mds_ach.tools.boardcmd:run")
       for name, text in (("enable", "enable joints' nodes (and clear a mode 2/3 follow fault)"),
                          ("home", "home joints: each drives to the middle of its range (the calibrated zero)"),
                          ("zero", "restart joints' encoder count where they stand (unreferenced until 'home')"),
                          ("reset", "reset joints' nodes (their count restarts: unreferenced until 'home')"))},
    "changerobot": Verb("choose the robot variant (isaac, lucas, octavia) for the next start",
                        "mds_ach.tools.launcher:add_changerobot_arguments", "mds_ach.tools.launcher:run_changerobot"),
    "hold": Verb("stop every joint (or JOINT..., left, right, arms) where it is; nothing moves until 'resume'",
                 "mds_ach.tools.holdcmd:add_arguments", "mds_ach.tools.holdcmd:run_hold"),
    "resume": Verb("let held joints go on to their controllers' targets (JOINT..., left, right, arms, all)",
                   "mds_ach.tools.holdcmd:add_arguments", "mds_ach.tools.holdcmd:run_resume"),
    "console": Verb("interactive console: goto, get, get fk, ik (-c CMD for scripts)",
                    "mds_ach.tools.console:add_arguments", "mds_ach.tools.console:run"),
    "read": Verb("live joint table (Joint, Enabled, address, Commanded/Actual Pos, collisions)",
                 "mds_ach.tools.read:add_arguments", "mds_ach.tools.read:run"),
    "remote": Verb("share the robot over the network: 'remote HOST' (operator), 'remote serve' (robot), 'remote kill'",
                   "mds_ach.net.remote:add_arguments", "mds_ach.net.remote:run"),
    "ros-shell": Verb("a shell inside the running system's ROS 2 graph (its network namespace and ROS_DOMAIN_ID)",
                      "mds_ach.tools.rosgraph:add_shell_arguments", "mds_ach.tools.rosgraph:run_shell"),
    "ros": Verb("run one command inside the running system's ROS 2 graph: 'mds-ach ros python examples/...'; "
                "'mds-ach ros topics|echo TOPIC|hz TOPIC' without a ros2 command line",
                "mds_ach.tools.rosgraph:add_ros_arguments", "mds_ach.tools.rosgraph:run_ros"),
    # recordings (mds_ach.record): record the channels to MCAP, plot a recording, replay it onto the channels
    "record": Verb("record every channel of the running system into an MCAP file (Foxglove, mcap, ROS 2 tools)",
                   "mds_ach.record.recorder:add_arguments", "mds_ach.record.recorder:run"),
    "plot": Verb("plot a recording or a CAN log: per joint each stage's command, measured, limits, holds, findings",
                 "mds_ach.record.plot:add_arguments", "mds_ach.record.plot:run"),
    "replay": Verb("write a recording's reported state back onto the channels (--to-channels); refused while a daemon "
                   "is live", "mds_ach.record.replay:add_arguments", "mds_ach.record.replay:run"),
    "sim": Verb("3-D viewer in the browser, in the background (prints the URL); 'sim kill' stops it",
                "mds_ach.tools.viewer:add_sim_arguments", "mds_ach.tools.viewer:run_sim"),
}
ALIASES: dict[str, str] = {"mk": "make", "create": "make", "remove": "rm", "unlink": "rm"}
# Verbs whose arguments are another program's command line: its --ros-args belong to that program.
PASS_THROUGH: frozenset[str] = frozenset({"ros"})


def help_paragraph(text: str) -> str:
    """``text`` wrapped as argparse wraps help, for a verb whose formatter keeps its text as written
    (``RawDescriptionHelpFormatter``, for a laid-out epilog): its description would otherwise be one long line."""
    width = max(shutil.get_terminal_size().columns - 2, 40)
    return textwrap.fill(text, width)


def _resolve(target: str) -> Callable:
    module, _, func = target.partition(":")
    return getattr(importlib.import_module(module), func)


def _selected_verb(argv: list[str]) -> str | None:
    """The first non-option word, if it names a verb (so only that verb's module gets imported)."""
    for word in argv:
        if word == "--":
            return None
        if not word.startswith("-"):
            return ALIASES.get(word, word) if ALIASES.get(word, word) in VERBS else None
    return None


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    """The full parser; only ``selected``'s arguments are built (the others only need their help line)."""
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="MDS-Ach front-end: manage the shared-memory channels and run the system's tools.",
        epilog=EPILOG.format(prog=PROG),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="verb", metavar="VERB")
    for name, verb in VERBS.items():
        aliases = [a for a, v in ALIASES.items() if v == name]
        p = sub.add_parser(name, help=verb.help, aliases=aliases, description=verb.help)
        if name == selected:
            _resolve(verb.add_arguments)(p)
            p.set_defaults(_handler=verb.handler)
    return parser


def _terminate(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if _selected_verb(argv) not in PASS_THROUGH:
        argv = strip_ros_args(argv)
    signal.signal(signal.SIGTERM, _terminate)  # SIGTERM ends a blocking verb as cleanly as Ctrl-C
    selected = _selected_verb(argv)
    parser = build_parser(selected)
    args = parser.parse_args(argv)
    if args.verb is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(_resolve(args._handler)(args) or 0)
    except KeyboardInterrupt:
        return 0
    except BrokenPipeError:  # `mds-ach console -c ... | head -1`: the reader is gone
        return stdout_closed()


SIGPIPE_EXIT = 128 + signal.SIGPIPE
"""Exit status after the reader of stdout went away: what a process killed by SIGPIPE reports."""


def stdout_closed() -> int:
    """The reader of our stdout closed the pipe: stop quietly, as a tool killed by SIGPIPE does, instead of a
    BrokenPipeError traceback (Python ignores SIGPIPE). stdout is pointed at /dev/null first, so the final flush
    at exit does not raise again. Returns the exit status (``SIGPIPE_EXIT``)."""
    import os

    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
    return SIGPIPE_EXIT


if __name__ == "__main__":
    raise SystemExit(main())
