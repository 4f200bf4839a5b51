"""``daemon`` (``ros2 run mds_ach daemon``): the MDS CAN driver node.

Reads references from ``mds-ref-gated`` (the collision gate's output), drives the Xitome MCB nodes over any
python-can bus (``--nocan``: the simulated MDS bus in this process), publishes ``mds-state`` every cycle,
``mds-param`` at start and ``mds-daemon-status``; loop statistics and bus load go to ``/diagnostics`` (WARN
above 60 % bus load).

Setup commands reach it two ways:

* the ``mds-cmd`` Ach channel (``MDS_CMD``: seq, cmd = ``MDS_CMD_*``, address (0 = every enabled joint));
  the result is echoed in ``mds-daemon-status`` (``cmd_seq``, ``cmd_result``);
* the ROS service ``~/command`` (``/mds_daemon/command``) of type ``mds_ach_interfaces/srv/Command``:
  ``command`` (enable | disable | home | reset | zero | resetbus) for a list of ``joints`` (short names; empty or
  ``all``: every enabled joint), run joint by joint; ``success`` when all succeeded, ``message`` one line per
  joint, ``failed`` the joints that did not. Example: ``ros2 service call /mds_daemon/command
  mds_ach_interfaces/srv/Command "{command: home, joints: [LEP, REP]}"``. ``zero`` and ``reset`` are refused there
  unless the parameter ``allow_encoder_commands`` is true (``refused_from_ros``).

Its health goes to ``mds/daemon_status`` (``mds_ach_interfaces/msg/DaemonStatus``) with ``/diagnostics``.

ROS parameters ``robot``, ``rate``, ``nocan`` and ``rt_priority`` (defaults from the command line) serve launch files.
The real-time loop runs on its own thread (see :mod:`mds_ach.nodes.daemon_loop`); the executor only serves the
service and the diagnostics timer.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from collections.abc import Sequence
from dataclasses import dataclass

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from mds_ach_interfaces.msg import DaemonStatus
from mds_ach_interfaces.srv import Command
from rclpy.node import Node

import mds_ach as mds
from mds_ach import logformat
from mds_ach.bus import budget, canio
from mds_ach.bus.canio import CanIO
from mds_ach.bus.simbus import FaultControl, SimNetwork
from mds_ach.nodes.collaborative import ModeLog
from mds_ach.nodes.daemon_loop import (
    MAX_RATE_HZ,
    STALE_AFTER,
    DaemonChannels,
    DaemonLoop,
    lock_timeout_for,
    rate_problem,
)
from mds_ach.nodes.estop import InputWatcher, default_latch_path, open_input
from mds_ach.nodes.rosargs import strip_ros_args
from mds_ach.nodes.rosnode import Param, declare, find, run_node
from mds_ach.nodes.status_msgs import DAEMON_STATUS_TOPIC, DIAGNOSTICS_TOPIC, daemon_status_msg
from mds_ach.robot import access as channel_access
from mds_ach.robot import config, motion
from mds_ach.robot.joints import BY_ADDRESS, lookup
from mds_ach.robot.msgs import daemon_status as ds

log = logging.getLogger("mds_ach.nodes.daemon")

BUS_LOAD_WARN = 60.0  # percent
# SCHED_FIFO priority of the loop thread by default: with 3 CPU hogs beside it the loop stalled up to 0.26 s at 50
# against 19.5 s at normal priority (issue #25). Refused where the user may not (it then says so once).
DEFAULT_RT_PRIORITY = 50
COMMAND_CODES = {"enable": mds.MDS_CMD_ENABLE, "disable": mds.MDS_CMD_DISABLE, "home": mds.MDS_CMD_HOME,
                 "reset": mds.MDS_CMD_RESET, "zero": mds.MDS_CMD_ZERO_ENCODER,
                 "zero_encoder": mds.MDS_CMD_ZERO_ENCODER, "resetbus": mds.MDS_CMD_RESET_BUS,
                 "reset_bus": mds.MDS_CMD_RESET_BUS}
# The safety commands of the Command service (issue #31): whole-robot, no joints; (code, value).
SAFETY_COMMANDS = {"collaborative": (mds.MDS_CMD_MODE, 1.0), "normal": (mds.MDS_CMD_MODE, 0.0),
                   "estop": (mds.MDS_CMD_ESTOP, 0.0), "estop_reset": (mds.MDS_CMD_ESTOP_RESET, 0.0)}
# Commands that restart a node's encoder count: the joint leaves its calibrated frame (unreferenced until HOME).
ENCODER_COMMANDS = {mds.MDS_CMD_ZERO_ENCODER: "zero", mds.MDS_CMD_RESET: "reset"}


def _rate_option(text: str) -> float | None:
    """``--rate HZ|max``: a number (judged by ``rate_problem``, one message for every bad rate) or ``max`` (None)."""
    if text.strip().lower() == "max":
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a rate in Hz or 'max', got {text!r}") from None


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="daemon",
        description="MDS CAN daemon: mds-ref-gated -> Xitome MCB nodes -> mds-state. The CAN bus is any python-can "
                    "interface chosen by python-can's configuration (--interface/--channel/--bitrate, "
                    "$CAN_INTERFACE/$CAN_CHANNEL/$CAN_BITRATE, ~/.canrc or --can-config); --nocan simulates "
                    "the robot's bus in-process.",
        epilog="Examples: daemon --nocan | daemon -i socketcan -c can0 | daemon -i pcan -c PCAN_USBBUS1 -b 1000000 "
               "--can-log run.asc | daemon --replay run.asc. ROS arguments (--ros-args ...) are accepted.",
    )
    bus = ap.add_argument_group("CAN bus")
    bus.add_argument("--nocan", action="store_true", help="simulated MDS bus: every joint-table node answers")
    bus.add_argument("-i", "--interface", help="python-can interface (socketcan, kvaser, pcan, slcan, virtual...)")
    bus.add_argument("-c", "--channel", help="python-can channel (e.g. can0)")
    bus.add_argument("-b", "--bitrate", type=int, help="bit/s (default: config, else 1000000); also for bus load")
    bus.add_argument("--can-config", metavar="FILE", help="python-can config file (default ~/.canrc, /etc/can.conf)")
    bus.add_argument("--can-log", metavar="FILE",
                     help="record all traffic; format by suffix: .asc .blf .csv .log .trc .txt (.mf4 needs asammdf)")
    bus.add_argument("--replay", metavar="FILE", help="feed the node replies of a recorded log back (no robot)")
    bus.add_argument("--replay-speed", type=float, default=1.0, help="replay pacing factor; 0 = as fast as read")
    loop = ap.add_argument_group("loop")
    loop.add_argument("-r", "--rate", type=_rate_option, default=1.0 / mds.MDS_LOOP_PERIOD, metavar="HZ|max",
                      help=f"loop rate in Hz (10; {motion.MIN_RATE_HZ:g} to {MAX_RATE_HZ:g}), or 'max': the highest "
                           "rate whose worst-case CAN traffic fits 60 %% of the bus (mds_ach.bus.budget; printed at "
                           "start); a rate over the budget is refused unless --over-budget")
    loop.add_argument("--over-budget", action="store_true",
                      help="run a rate whose worst-case CAN traffic exceeds the budget anyway (tests of the motion "
                           "bounds under overload): replies come late and joints may go stale")
    loop.add_argument("--robot", help="robot variant (isaac, lucas, octavia, default); else $MDS_ACH_ROBOT or the "
                                      "choice saved by `mds-ach changerobot`")
    loop.add_argument("--config", metavar="FILE", help="joint table YAML (default: the calibration XML when there "
                                                       "is one, else config/joints.yaml)")
    loop.add_argument("--anatomy", metavar="FILE", help="Xitome anatomy.xml to read the joint table from (default: "
                                                        "$MDS_ACH_ANATOMY, else /etc/mds-ach's, else the YAML)")
    loop.add_argument("--overlay", metavar="FILE", help="MDS-Ach mdsach.xml for the anatomy (default: "
                                                        "$MDS_ACH_OVERLAY, else /etc/mds-ach/configs/mdsach.xml, "
                                                        "else the one beside the anatomy)")
    loop.add_argument("--reply-wait", type=float, help="s to wait for position replies per cycle (half a period)")
    loop.add_argument("--stale-after", type=float, help=f"s without a reply before a joint is stale ({STALE_AFTER:g})")
    loop.add_argument("--filter-length", type=float, help="L of the mode-0 filter (default: 95%% in 4.0 s)")
    loop.add_argument("--no-collide-gate", action="store_true",
                      help="do not hold the robot while mds-collide reports a collision (expert use only)")
    loop.add_argument("--allow-encoder-commands", action="store_true",
                      help="let the ROS command service send zero and reset (default: only mds-cmd, i.e. `mds-ach "
                           "zero|reset`, may)")
    loop.add_argument("--estop-input", metavar="PATH",
                      help="an e-stop button's line input (a FIFO, a serial line such as /dev/ttyUSB0): a line '1', "
                           "'estop', 'stop' or 'press' latches the e-stop; the input ending or failing does too")
    loop.add_argument("--rt-priority", type=rt_priority, default=DEFAULT_RT_PRIORITY, metavar="N",
                      help="SCHED_FIFO priority (1-99) of the loop thread, with the daemon's memory locked (default "
                           f"{DEFAULT_RT_PRIORITY}); 0 = normal scheduling. Needs root, CAP_SYS_NICE or an rtprio "
                           "limit (docs/operator.md); refused: said once at start, the loop runs at normal priority")
    sim = ap.add_argument_group("simulated bus (--nocan)")
    sim.add_argument("--sim-pose", metavar="J=RAD,...", default="",
                     help="where the simulated joints start, e.g. LEP=-1.0,RSR=-0.5 (default: home pose)")
    sim.add_argument("--sim-ideal", action="store_true", help="no wire time: replies arrive at once")
    sim.add_argument("--sim-faults", metavar="SOCKET",
                     help="test-only: take fault-injection requests (offline node, bogus position replies, bus-off) "
                          "on this Unix socket (mds_ach.bus.simbus.FaultControl)")
    ap.add_argument("--no-ros", action="store_true", help="run without rclpy (no /diagnostics, no service)")
    ap.add_argument("--duration", type=float, help="stop after this many seconds (tests, benchmarks)")
    ap.add_argument("-d", "--debug", action="store_true", help="debug logging")
    return ap


def rt_priority(text: str) -> int:
    """``--rt-priority``: an integer 0-99 (argparse turns the ValueError into a usage error)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer 0-99, got {text!r}") from None
    if not 0 <= value <= 99:
        raise argparse.ArgumentTypeError(f"{value} is outside 0-99 (0 = normal scheduling)")
    return value


def parse_pose(text: str) -> dict[str, float]:
    """'LEP=-1.0,RSR=-0.5' -> {'LEP': -1.0, 'RSR': -0.5}; bad input raises ValueError naming the item."""
    pose: dict[str, float] = {}
    for item in filter(None, (p.strip() for p in text.replace(" ", ",").split(","))):
        name, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--sim-pose: expected JOINT=RAD, got {item!r}")
        try:
            pose[lookup(name).short] = float(value)
        except KeyError as exc:
            raise ValueError(f"--sim-pose: {exc.args[0]}") from None
        except ValueError:
            raise ValueError(f"--sim-pose: {item!r}: not a number") from None
    return pose


@dataclass
class Daemon:
    """Everything a running daemon owns (so tests and the node tear it down the same way)."""

    loop: DaemonLoop
    io: CanIO
    channels: DaemonChannels
    network: SimNetwork | None = None
    faults: FaultControl | None = None  # --sim-faults
    estop_input: InputWatcher | None = None  # --estop-input

    def close(self) -> None:
        if self.estop_input is not None:
            self.estop_input.close()
        self.loop.stop()
        if self.faults is not None:
            self.faults.close()
        self.io.close()
        self.channels.close()


def max_loop_rate(table: config.JointTable, bitrate: int) -> float:
    """``--rate max``: the highest rate whose worst-case CAN traffic fits 60 % of the bus, within the daemon's range."""
    return min(max(budget.CycleBudget.for_table(table, bitrate).max_rate(), motion.MIN_RATE_HZ), MAX_RATE_HZ)


def say_budget(table: config.JointTable, bitrate: int | None, rate: float, over_budget: bool = False) -> None:
    """The CAN budget at start. A rate whose worst-case traffic the bus cannot carry is refused (ValueError with the
    highest rate it can), unless ``over_budget`` (``--over-budget``: testing the bounds under overload; the motion
    bounds still hold, a late reply or a refused send never moves a joint, but replies come late and joints go
    stale). ``bitrate`` None is the simulated bus without wire time (``--sim-ideal``): nothing to refuse."""
    cycle = budget.CycleBudget.for_table(table, bitrate or canio.DEFAULT_BITRATE)
    log.info(cycle.describe(rate))
    problem = cycle.problem(rate) if bitrate is not None else None
    if problem and not over_budget:
        raise ValueError(f"{problem}; --over-budget runs it anyway (replies late, joints stale: for tests)")
    if problem:
        log.warning("%s; running at %g Hz anyway (--over-budget): replies may come late and joints go stale",
                    problem, rate)


def _table(args: argparse.Namespace) -> config.JointTable:
    return config.load(args.robot, args.config, getattr(args, "anatomy", None), getattr(args, "overlay", None))


def resolve_rate(args: argparse.Namespace) -> None:
    """``--rate max`` (None) becomes a number before anything reads it (the ROS parameter is a double)."""
    if args.rate is None:
        args.rate = max_loop_rate(_table(args), args.bitrate or canio.DEFAULT_BITRATE)


def build(args: argparse.Namespace) -> Daemon:
    """Joint table, bus, channels and the loop (started, after reading the start pose)."""
    table = _table(args)
    log.info("joint table: %s", config.describe(table))
    resolve_rate(args)
    ideal = bool(args.nocan and getattr(args, "sim_ideal", False))
    say_budget(table, None if ideal else args.bitrate or canio.DEFAULT_BITRATE, args.rate,
               bool(getattr(args, "over_budget", False)))
    if args.sim_faults and not args.nocan:
        raise ValueError("--sim-faults needs --nocan: faults are injected into the simulated bus only")
    network = None
    if args.nocan:
        pose = parse_pose(args.sim_pose)
        for short, q in pose.items():
            if not table[short].within_limits(q):
                j = table[short]
                raise ValueError(f"--sim-pose: {short}={q} is outside [{j.lower:.4f}, {j.upper:.4f}]")
        network = SimNetwork.from_table(table, pose=pose, bitrate=None if args.sim_ideal else
                                        (args.bitrate or canio.DEFAULT_BITRATE))
    io = canio.make_canio(nocan=args.nocan, network=network, interface=args.interface, channel=args.channel,
                          bitrate=args.bitrate, config_file=args.can_config, replay=args.replay,
                          replay_speed=args.replay_speed, can_log=args.can_log)
    try:
        channels = DaemonChannels.open(lock_timeout=lock_timeout_for(args.rate))
    except Exception:
        io.close()
        raise
    try:
        loop = DaemonLoop(table, io, channels, rate_hz=args.rate, reply_wait=args.reply_wait,
                          stale_after=args.stale_after, filter_length=args.filter_length,
                          collide_gate=not args.no_collide_gate, nocan=args.nocan, rt_priority=args.rt_priority,
                          estop_latch=default_latch_path())
        if args.can_log:  # check-log learns when the Cartesian bound applied (collaborative mode)
            loop.mode_log = ModeLog(args.can_log, io.wall_offset)
        loop.start_up()
    except Exception:
        io.close()
        channels.close()
        raise
    log.info("robot %s (%s), %s, %.4g Hz, filter L %.2f", table.robot, " + ".join(table.sources), io.description,
             args.rate, loop.L)
    faults = None
    if args.sim_faults and network is not None:  # checked above: --sim-faults needs --nocan, which made a network
        faults = FaultControl(args.sim_faults, network)
        log.warning("test-only fault injection on %s", args.sim_faults)
    estop_input = None
    if args.estop_input:
        try:
            estop_input = InputWatcher(open_input(args.estop_input), lambda: loop.submit(mds.MDS_CMD_ESTOP))
        except ValueError:
            io.close()
            channels.close()
            raise
        log.info("e-stop input: %s", args.estop_input)
    loop.start()
    return Daemon(loop, io, channels, network, faults, estop_input)


def parse_command(text: str) -> tuple[int, int]:
    """'home LEP' -> (MDS_CMD_HOME, 0x4C); 'resetbus' -> (MDS_CMD_RESET_BUS, 0); 'enable all' -> (.., 0)."""
    words = text.split()
    if not words or words[0].lower() not in COMMAND_CODES or len(words) > 2:
        raise ValueError(f"expected '<{'|'.join(sorted(set(COMMAND_CODES) - {'zero_encoder', 'reset_bus'}))}> "
                         f"[joint|all]', got {text!r}")
    code = COMMAND_CODES[words[0].lower()]
    if len(words) == 1 or words[1].lower() == "all":
        return code, 0
    try:
        return code, lookup(words[1]).address
    except KeyError as exc:
        raise ValueError(exc.args[0]) from None


def refused_from_ros(code: int, allow_encoder_commands: bool) -> str | None:
    """Why the ROS command service refuses ``code`` (None: it runs).

    ZERO_ENCODER and RESET restart a node's count: the joint is unreferenced (no motion) until HOME. On the Ach side
    only the operators may send them (``mds-cmd`` is writable by the operators' group, ``mds-ach zero|reset``); the
    ROS graph reaches any peer on the domain, so the service sends them only when the daemon was started with the
    parameter ``allow_encoder_commands`` (``--allow-encoder-commands``)."""
    name = ENCODER_COMMANDS.get(code)
    if name is None or allow_encoder_commands:
        return None
    return (f"'{name}' is refused from ROS: it restarts the joint's encoder count (the joint is unreferenced, no "
            f"motion, until HOME); an operator sends it with `mds-ach {name} JOINT` (it writes "
            f"{mds.MDS_CHAN_BOARD_CMD_NAME}), or start the daemon with -p allow_encoder_commands:=true")


def parse_joint_command(command: str, joints: Sequence[str]) -> list[tuple[str, int, int]]:
    """The Command service's request as (label, code, address) per joint: ('home', ['LEP']) -> [('LEP', HOME,
    0x4C)]; no joints or 'all' (and resetbus, which is for the bus): one command for address 0. Every name is
    checked before anything runs, so a typo refuses the whole request."""
    name = command.strip().lower()
    if name not in COMMAND_CODES:
        raise ValueError(f"unknown command {command!r}; expected one of "
                         f"{', '.join(sorted(set(COMMAND_CODES) - {'zero_encoder', 'reset_bus'}))}")
    code = COMMAND_CODES[name]
    if code == mds.MDS_CMD_RESET_BUS or not joints or [j.lower() for j in joints] == ["all"]:
        return [("all", code, 0)]
    out = []
    for j in joints:
        try:
            joint = lookup(j)
        except KeyError as exc:
            raise ValueError(exc.args[0]) from None
        out.append((joint.short, code, joint.address))
    return out


def diagnostic_status(st: ds.MDS_DAEMON_STATUS, running: bool, stale_names: list[str], new_channel_errors: int = 0,
                      bad_reply_names: Sequence[str] = (), new_stalls: int = 0):
    """The daemon's DiagnosticStatus (OK / WARN above 60 % bus load, stale joints, joints with implausible position
    replies, late loop, stalls or channel errors since the last report / ERROR bus-off or loop stopped). Targets
    the daemon had to limit are reported as values (per joint), not as a problem: the limiter did its job."""
    level, problems = DiagnosticStatus.OK, []
    if st.bus_load_avg > BUS_LOAD_WARN:
        level = DiagnosticStatus.WARN
        problems.append(f"bus load {st.bus_load_avg:.0f} % > {BUS_LOAD_WARN:.0f} %")
    if st.stale_count:
        level = DiagnosticStatus.WARN
        problems.append(f"{st.stale_count} stale joint(s): {' '.join(stale_names)}")
    if bad_reply_names:
        level = DiagnosticStatus.WARN
        problems.append(f"implausible position replies (position not trusted): {' '.join(bad_reply_names)}")
    unreferenced = flagged(st, ds.JOINT_UNREFERENCED)
    if unreferenced:
        level = DiagnosticStatus.WARN
        problems.append(f"unreferenced after zero/reset (no motion until `home`): {' '.join(unreferenced)}")
    follow_faults = flagged(st, ds.JOINT_FOLLOW_FAULT)
    if follow_faults:
        level = DiagnosticStatus.WARN
        problems.append(f"follow fault, mode 2/3 held until `enable`: {' '.join(follow_faults)}")
    if new_stalls:
        level = DiagnosticStatus.WARN
        problems.append(f"control loop stalled {new_stalls} time(s) (longest {st.stall_max:.2f} s)"
                        + ("" if st.loop_policy in ds.REALTIME_POLICIES else " without a real-time priority"))
    if new_channel_errors:
        level = DiagnosticStatus.WARN
        problems.append(f"{new_channel_errors} Ach channel error(s): see the log, `mds-ach repair`")
    if st.bus_state == ds.BUS_STATE_PASSIVE:
        level = DiagnosticStatus.WARN
        problems.append("CAN error-passive")
    if st.period_error_p99 > 0.5 / max(st.rate_hz, 1e-9):
        level = DiagnosticStatus.WARN
        problems.append(f"loop late: p99 period error {st.period_error_p99 * 1e3:.1f} ms")
    if st.bus_state == ds.BUS_STATE_BUS_OFF:
        level = DiagnosticStatus.ERROR
        problems.append("CAN bus-off: run `mds-ach resetbus`")
    if not running:
        level = DiagnosticStatus.ERROR
        problems.append("control loop not running")
    if st.estop != ds.ESTOP_OFF:
        level = DiagnosticStatus.ERROR
        problems.append(f"E-STOP {ds.ESTOP_NAMES.get(st.estop, '?')}: nothing moves until `mds-ach estop reset`, "
                        "then `mds-ach enable all`")
    values = {
        "mode": "collaborative" if st.collaborative else "normal",
        "collaborative_speed_mm_s": f"{st.collaborative_speed * 1e3:g}",
        "cartesian_speed_mm_s": f"{st.cartesian_speed * 1e3:.1f}",
        "cartesian_speed_max_mm_s": f"{st.cartesian_speed_max * 1e3:.1f}",
        "cartesian_slowed": str(st.cartesian_slowed), "cartesian_braking": str(st.cartesian_braking),
        "estop": ds.ESTOP_NAMES.get(st.estop, "?"),
        "rate_hz": f"{st.rate_hz:g}", "measured_rate_hz": f"{st.measured_rate_hz:.3f}",
        "period_error_p50_ms": f"{st.period_error_p50 * 1e3:.3f}",
        "period_error_p99_ms": f"{st.period_error_p99 * 1e3:.3f}",
        "period_error_max_ms": f"{st.period_error_max * 1e3:.3f}", "overruns": str(st.overruns),
        "cycle_time_ms": f"{st.cycle_time * 1e3:.3f}", "cpu_per_cycle_ms": f"{st.cpu_per_cycle * 1e3:.3f}",
        "bus_load_percent": f"{st.bus_load:.1f}", "bus_load_avg_percent": f"{st.bus_load_avg:.1f}",
        "bitrate": str(st.bitrate), "bus_state": ds.BUS_STATE_NAMES.get(st.bus_state, "?"),
        "nocan": str(bool(st.nocan)), "cycle": str(st.cycle), "tx_frames": str(st.tx_frames),
        "rx_frames": str(st.rx_frames), "tx_errors": str(st.tx_errors), "error_frames": str(st.error_frames),
        "bus_off_count": str(st.bus_off_count), "unknown_node_frames": str(st.unknown_node_frames),
        "malformed_frames": str(st.malformed_frames), "node_errors": str(st.node_errors),
        "acks_missing": str(st.acks_missing), "refs_refused": str(st.refs_refused),
        "refs_clamped": str(st.refs_clamped), "collision_holds": str(st.collision_holds),
        "channel_errors": str(st.channel_errors),
        "stale_joints": " ".join(stale_names), "replies": f"{st.replies_received}/{st.replies_expected}",
        "max_velocity_rad_s": f"{st.max_velocity:g}", "max_acceleration_rad_s2": f"{st.max_acceleration:g}",
        "targets_limited": str(st.targets_limited), "limited_joints": " ".join(
            f"{BY_ADDRESS[a].short}:{st.joint_limited[a]}" for a in BY_ADDRESS if st.joint_limited[a]),
        "bad_replies": str(st.bad_replies), "bad_reply_joints": " ".join(bad_reply_names),
        "stalls": str(st.stalls), "stall_max_s": f"{st.stall_max:.3f}",
        "unreferenced_joints": " ".join(unreferenced), "follow_fault_joints": " ".join(follow_faults),
        "realtime": str(st.loop_policy in ds.REALTIME_POLICIES),
        "loop_scheduling": f"{ds.LOOP_POLICY_NAMES.get(st.loop_policy, str(st.loop_policy))} {st.loop_priority}",
        "memory_locked": str(bool(st.memory_locked)),
    }
    return DiagnosticStatus(level=level, name="mds_daemon: control loop", hardware_id="mds",
                            message="; ".join(problems) or "OK",
                            values=[KeyValue(key=k, value=v) for k, v in values.items()])


def flagged(st: ds.MDS_DAEMON_STATUS, flag: int) -> list[str]:
    """The short names of the joints whose ``joint_flags`` have ``flag``."""
    return [BY_ADDRESS[a].short for a in BY_ADDRESS if st.joint_flags[a] & flag]


NODE_NAME = "mds_daemon"  # the ROS node name (`ros2 param`, the sections of a params file)

PARAMETERS = (
    Param("robot", "", "robot variant of the joint table (isaac, lucas, octavia, default); empty: $MDS_ACH_ROBOT "
                       "or the choice saved by `mds-ach changerobot` (option --robot)"),
    Param("rate", 1.0 / mds.MDS_LOOP_PERIOD, "control loop rate in Hz: one position query and one reference per "
                                            "joint and cycle (option --rate)", range=(motion.MIN_RATE_HZ, MAX_RATE_HZ)),
    Param("nocan", False, "simulate the robot's CAN bus in this process instead of a python-can interface "
                          "(option --nocan)"),
    Param("allow_encoder_commands", False, "let the command service send zero and reset, which take a joint out of "
                                           "its calibrated frame until HOME (default: only the operators, through "
                                           "mds-cmd: `mds-ach zero|reset`; option --allow-encoder-commands)"),
    Param("rt_priority", DEFAULT_RT_PRIORITY, "SCHED_FIFO priority (1-99) of the control loop thread (option "
                                              "--rt-priority), with the daemon's memory locked; 0 = normal "
                                              "scheduling. Needs root, CAP_SYS_NICE or an rtprio limit; refused: "
                                              "said once at start, normal priority", range=(0, 99)),
)


class DaemonNode(Node):
    """Diagnostics timer and command service around the loop thread (which never waits on ROS).

    The command line gives the parameters' defaults; ``--ros-args -p`` values win (launch files)."""

    def __init__(self, args: argparse.Namespace) -> None:
        super().__init__(NODE_NAME)
        robot = declare(self, find(PARAMETERS, "robot"), args.robot)
        rate = declare(self, find(PARAMETERS, "rate"), args.rate)
        nocan = declare(self, find(PARAMETERS, "nocan"), args.nocan)
        self.allow_encoder_commands = bool(declare(self, find(PARAMETERS, "allow_encoder_commands"),
                                                   args.allow_encoder_commands))
        rt = declare(self, find(PARAMETERS, "rt_priority"), args.rt_priority)
        args = argparse.Namespace(**{**vars(args), "robot": robot or None, "rate": float(rate), "nocan": bool(nocan),
                                     "rt_priority": int(rt)})
        self.daemon = build(args)
        self._channel_errors = 0
        self._stalls = 0
        self.diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self.status_pub = self.create_publisher(DaemonStatus, DAEMON_STATUS_TOPIC, 10)
        self.create_timer(1.0, self._diagnostics)
        self.create_service(Command, "~/command", self._command)

    def _diagnostics(self) -> None:
        st = self.daemon.loop.snapshot()
        if not self.daemon.loop.running:
            # The loop thread died (its traceback is in the log): stop the process so a supervisor notices;
            # the MCB nodes hold their last targets.
            self.get_logger().fatal("control loop stopped; exiting")
            raise SystemExit(1)
        stale = [BY_ADDRESS[a].short for a in BY_ADDRESS if st.joint_flags[a] & ds.JOINT_STALE
                 and st.joint_flags[a] & ds.JOINT_ENABLED]
        bad = [BY_ADDRESS[a].short for a in BY_ADDRESS if st.joint_flags[a] & ds.JOINT_BAD_REPLY]
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        new_errors, self._channel_errors = st.channel_errors - self._channel_errors, st.channel_errors
        new_stalls, self._stalls = st.stalls - self._stalls, st.stalls
        msg.status = [diagnostic_status(st, self.daemon.loop.running, stale, new_errors, bad, new_stalls)]
        self.diag_pub.publish(msg)
        self.status_pub.publish(daemon_status_msg(st, self.daemon.loop.running, stale, bad, msg.header.stamp))

    def _run(self, code: int, address: int, value: float = 0.0) -> tuple[bool, str]:
        """One command through the control loop (which owns the bus): (succeeded, its message)."""
        cmd = self.daemon.loop.submit(code, address, value)
        if not cmd.done.wait(max(2.0, 5 * self.daemon.loop.period)):
            return False, "the control loop did not answer in time"
        return cmd.result == ds.CMD_OK, cmd.message

    def _command(self, request: Command.Request, response: Command.Response) -> Command.Response:
        safety = SAFETY_COMMANDS.get(request.command.strip().lower())
        if safety is not None:  # the mode and the e-stop: the whole robot
            ok, text = self._run(safety[0], 0, safety[1])
            response.success, response.message, response.failed = ok, text, [] if ok else ["all"]
            return response
        try:
            commands = parse_joint_command(request.command, list(request.joints))
        except ValueError as exc:
            response.success, response.message, response.failed = False, str(exc), list(request.joints)
            return response
        refused = refused_from_ros(commands[0][1], self.allow_encoder_commands)  # (one command per request)
        if refused is not None:
            response.success, response.message, response.failed = False, refused, [c[0] for c in commands]
            return response
        lines, failed = [], []
        for label, code, address in commands:
            ok, text = self._run(code, address)
            lines.append(f"{label}: {text}")
            if not ok:
                failed.append(label)
        response.success, response.message, response.failed = not failed, "\n".join(lines), failed
        return response

    def shutdown(self) -> None:
        self.daemon.close()


def _run_plain(args: argparse.Namespace) -> int:
    """No ROS: the loop thread runs until SIGINT/SIGTERM or --duration."""
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        daemon = build(args)
    except ValueError as exc:
        print(f"daemon: error: {exc}", file=sys.stderr)
        return 2
    try:
        while not stop.wait(0.2):
            if not daemon.loop.running:
                log.error("control loop stopped")
                return 1
    finally:
        daemon.close()
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(strip_ros_args(argv)[1:])
    try:
        resolve_rate(args)
    except (ValueError, OSError) as exc:  # the joint table could not be read: build() says the same with its context
        parser.error(f"--rate max: {exc}")
    if rate_problem(args.rate):
        parser.error(f"--rate: {rate_problem(args.rate)}")
    logformat.setup_python_logging("daemon", logging.DEBUG if args.debug else logging.INFO)
    if args.duration is not None:
        timer = threading.Timer(args.duration, lambda: signal.raise_signal(signal.SIGTERM))
        timer.daemon = True
        timer.start()
    if args.no_ros:
        channel_access.enforce_in_this_process()  # refuse planted channel files (run_node does it with ROS)
        return _run_plain(args)
    return run_node(argv, parser, DaemonNode)


if __name__ == "__main__":
    raise SystemExit(main())
