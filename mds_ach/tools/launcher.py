"""Process manager behind ``mds-ach start|stop|kill|killall|status|run|resetbus|changerobot``.

Each node runs as its own process, as in the original (nohup'd daemons, one pid log), so any node can be
stopped, restarted or replaced by hand. Pid files and logs live in ``paths.runtime_dir()``; every terminal,
and ``scripts/start_nodes.sh`` (which writes the same one-number pid files), sees the same system.

A pid file is trusted only while that pid is alive and its command line names the node, so a stale file
whose pid was reused by another program never gets that program killed.
"""

from __future__ import annotations

import argparse
import ctypes
import importlib
import os
import shlex
import shutil
import signal
import stat
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import mds_ach as mds
from mds_ach import ach
from mds_ach import procs as background
from mds_ach.argtypes import ros_namespace, seconds
from mds_ach.kinematics.limits import current_limits, read_published
from mds_ach.paths import CHANNEL_PREFIX_ENV, bin_name, config_path, runtime_dir, user_label
from mds_ach.robot import calibfiles, contracts
from mds_ach.robot.channels import StructChannel, check_existing, make_channels, remove_channels
from mds_ach.robot.choice import effective_robot, name_problem, save_robot
from mds_ach.robot.config import ROBOT_ENV, XML_ROBOT, ConfigError, available_robots, describe, load
from mds_ach.robot.msgs import MDS_MUX_STATE
from mds_ach.robot.msgs.daemon_status import BUS_STATE_NAMES, CMD_OK, MDS_DAEMON_STATUS
from mds_ach.robot.msgs.ik_status import IK_PROBE_MOVE
from mds_ach.tools import canlink, repair
from mds_ach.tools.holdcmd import held_summary, newest_enabled
from mds_ach.tools.monitor import (
    TABLE_FILE,
    Latest,
    collision_summary,
    daemon_line,
    limits_line,
    recorded_table,
    table_line,
)
from mds_ach.tools.rosgraph import summary as ros_graph_summary

# Start order follows the data flow back from the bus: the daemon first (it publishes mds-state, which
# the others start from), then the reference pipeline, then the clients that feed it.
NODES: tuple[str, ...] = ("daemon", "mux", "filter", "collision", "ik", "bridge")
ENTRY_POINTS: dict[str, str] = {
    "daemon": "mds_ach.nodes.daemon:main",
    "mux": "mds_ach.nodes.mux:main",
    "filter": "mds_ach.nodes.filter:main",
    "collision": "mds_ach.nodes.collision:main",
    "ik": "mds_ach.nodes.ik:main",
    "bridge": "mds_ach_bridge.bridge:main",
}
DEFAULT_START_TIMEOUT = 60.0  # s; first start on a loaded 2-core machine imports torch, fcl and rclpy
DEFAULT_STOP_GRACE = 5.0  # s between SIGTERM and SIGKILL
LOG_TAIL_LINES = 25
WORLD_RECORD = "world"  # in the runtime dir: the world file the collision gate started with (the viewer draws it)
NAMESPACE_RECORD = "namespace"  # in the runtime dir: the ROS namespace the nodes were started in ('/': none)

Printer = Callable[[str], None]


class LaunchError(RuntimeError):
    """A node did not come up; ``node`` names it and the message carries its log tail."""

    def __init__(self, node: str, message: str) -> None:
        super().__init__(message)
        self.node = node


def _write(stream_name: str, text: str) -> None:
    """Print, and survive a reader that went away: EPIPE (``make run | tee log``, tee killed by the same Ctrl-C) or
    EIO (the terminal was closed). The stream is then pointed at /dev/null, so the caller carries on (it must
    still stop the nodes) and nothing fails again at exit when Python flushes it."""
    stream = getattr(sys, stream_name)
    try:
        print(text, file=stream, flush=True)
    except (OSError, ValueError):  # ValueError: the stream was closed
        _to_devnull(stream)


def _to_devnull(stream: object) -> None:
    try:
        fd = stream.fileno()  # type: ignore[attr-defined]
    except (OSError, ValueError, AttributeError):
        return
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, fd)
    finally:
        os.close(null)


def _err(text: str) -> None:
    _write("stderr", text)


def _out(text: str) -> None:
    _write("stdout", text)


# --------------------------------------------------------------------------------------------- files


def pid_path(name: str, rt: Path | None = None) -> Path:
    return (rt or runtime_dir()) / f"{name}.pid"


def log_path(name: str, rt: Path | None = None) -> Path:
    return (rt or runtime_dir()) / f"{name}.log"


def log_tail(name: str, lines: int = LOG_TAIL_LINES, rt: Path | None = None) -> str:
    """The last ``lines`` lines of a node's log (or a note that there is none)."""
    path = log_path(name, rt)
    if not path.exists():
        return f"(no log at {path})"
    tail = background.log_tail(path, lines)
    return "\n".join(tail) if tail else f"(log {path} is empty)"


# --------------------------------------------------------------------------------------------- processes


def _names_node(argv: list[str], name: str) -> bool:
    """Does a command line name node ``name`` (bin/ script ``mds-ach-NAME``, ros2 run path ``lib/mds_ach/NAME`` or
    launcher exec)?"""
    return any(Path(a).name in (name, bin_name(name)) for a in argv[:5])


def read_pid(name: str, rt: Path | None = None) -> int | None:
    """The pid in ``name``'s pid file if that process is alive and really is the node, else None."""
    return background.running_pid(pid_path(name, rt), lambda argv: _names_node(argv, name))


def running_nodes(rt: Path | None = None) -> dict[str, int]:
    """node -> pid for every node of ``NODES`` that runs according to its pid file."""
    return {n: pid for n in NODES if (pid := read_pid(n, rt)) is not None}


def _is_mds_script(path: Path) -> bool:
    """A console script of this package (not e.g. Debian's unrelated /usr/bin/daemon)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return os.access(path, os.X_OK) and (b"mds_ach" in head or b"mds-ach" in head)


def node_command(name: str) -> list[str]:
    """How to run node ``name``: the console script ``mds-ach-NAME`` beside this interpreter, else
    ``<ament prefix>/lib/mds_ach/NAME`` (what ``ros2 run`` executes), else this module's ``exec`` entry (always works
    from a source checkout)."""
    if name not in ENTRY_POINTS:
        raise ValueError(f"unknown node {name!r}; nodes: {', '.join(NODES)}")
    candidates = [Path(sys.executable).parent / bin_name(name)]
    candidates += [Path(p) / "lib" / "mds_ach" / name for p in os.environ.get("AMENT_PREFIX_PATH", "").split(":") if p]
    for path in candidates:
        if path.is_file() and _is_mds_script(path):
            return [str(path)]
    return [sys.executable, "-m", "mds_ach.tools.launcher", "exec", name]


WORLD_NODES = ("collision", "ik")  # the nodes that check collisions, so take the world file


def node_args(name: str, nocan: bool, world: str | None = None, can_args: Sequence[str] = (),
              params: str | None = None, namespace: str | None = None) -> list[str]:
    """Node ``name``'s command-line arguments. ``params``: a checked params file, passed as ``--ros-args
    --params-file``; the launcher's own options (``--world``) follow it as ``-p``, so they win over the file.
    ``namespace`` (absolute, ``/robot1``): every node's ``__ns``, so every topic, service and action of the system
    (all relative) moves under it."""
    args = ["--nocan"] if name == "daemon" and nocan else []
    if name == "daemon" and not nocan:
        args += list(can_args)
    if world and name in WORLD_NODES:
        args += ["--world", world]
    ros: list[str] = []
    if params:
        ros += ["--params-file", params]
        if world and name in WORLD_NODES:
            ros += ["-p", f"world:={world}"]
    if namespace and namespace != "/":
        ros += ["-r", f"__ns:={namespace}"]
    return args + (["--ros-args", *ros] if ros else [])


def recorded_namespace(rt: Path | None = None) -> str | None:
    """The namespace the running system's nodes were started in (``NAMESPACE_RECORD``), None when unknown."""
    try:
        return (rt or runtime_dir()).joinpath(NAMESPACE_RECORD).read_text().strip() or None
    except OSError:
        return None


def params_choice(path: str | None, no_params: bool = False) -> str | None:
    """The params file a start uses: none with ``--no-params``, ``--params FILE``, else the shipped
    config/params.yaml when it exists."""
    if no_params:
        return None
    if path:
        return str(Path(path).absolute())
    from mds_ach.tools.params import default_path  # lazy: see check_params

    shipped = default_path()
    return str(shipped) if shipped.is_file() else None


def check_params(path: str | None, nocan: bool, out: Printer = _out, namespace: str = "/") -> None:
    """Refuse (LaunchError) a params file that does not fit the nodes' declarations (started in ``namespace``), or
    whose ``nocan`` for the daemon disagrees with this start's mode; prints which file is used."""
    if path is None:
        return
    from mds_ach.tools import params  # lazy: imports the node modules (rclpy), only for a start with a file

    try:
        values = params.load(path, namespace=namespace)
    except params.ParamsFileError as exc:
        raise LaunchError("", f"{exc}\n  (nothing was started; 'python -m mds_ach.tools.params' prints a valid file "
                              "with every parameter)") from None
    daemon = next(n.ros_name for n in params.nodes() if n.name == "daemon")
    given = values.get(daemon, {}).get("nocan")
    if given is not None and bool(given) != nocan:
        mode = "the simulated bus (nocan)" if nocan else "the CAN bus"
        raise LaunchError("daemon", f"params file {path}: {daemon} nocan: {str(given).lower()}, but this start is on "
                                    f"{mode}; use 'nocan' on the command line to choose the bus, and remove nocan "
                                    "from the file (nothing was started)")
    out(f"  parameters {path}")


def world_file(path: str | None) -> str | None:
    """The absolute path of a valid world file (``--world``), None for none; LaunchError saying what is wrong."""
    if not path:
        return None
    from mds_ach.kinematics.collision import check_world_file  # lazy: numpy/yaml only when a world is given

    try:
        check_world_file(path)
    except ValueError as exc:
        raise LaunchError("", f"--world: {exc}") from None
    return str(Path(path).resolve())


def another_users_channels(names: Sequence[str], then: str = "start again") -> str | None:
    """One explanation when the refused channels are another user's system's (issue 28: after `sudo make run`,
    `make run` as a normal user on the same /dev/shm listed every channel with a fix that cannot work without that
    user): all owned by one other user, with the modes the stack gives them; both users as the machine names them
    (``paths.user_label``). None otherwise (a plant: each line says what is wrong). ``then``: what to do after."""
    from mds_ach.robot import access

    if set(names) != {n for n in mds.ALL_CHANNELS if os.path.lexists(ach.shm_path(n))}:
        return None  # some are ours: a plant, not another user's system
    owners = set()
    for name in names:
        try:
            st = os.lstat(ach.shm_path(name))
        except OSError:
            return None
        a_system_made_it = stat.S_ISREG(st.st_mode) and not st.st_mode & 0o777 & ~access.channel_mode(name)
        if st.st_uid in access.trusted_owners() or not a_system_made_it:
            return None
        owners.add(st.st_uid)
    if len(owners) != 1:
        return None
    who = user_label(owners.pop())
    script = Path(sys.executable).parent / "mds-ach"
    killall = str(script) if script.is_file() else f"{sys.executable} -m mds_ach.tools.cli"
    return (f"the MDS channels in /dev/shm belong to {who}, not to you ({user_label(os.geteuid())}): a system that "
            f"user runs or ran here (make run shares this machine's /dev/shm). As that user, stop it and remove them, "
            f"e.g. 'sudo {killall} killall' (it also stops that user's nodes), then {then}.")


def child_env(anatomy: str | None = None, overlay: str | None = None) -> dict[str, str]:
    """The nodes' environment: ours, unbuffered output for live logs, the saved robot choice, and the calibration
    files of ``--anatomy``/``--overlay`` (as $MDS_ACH_ANATOMY/$MDS_ACH_OVERLAY: every node reads the same table)."""
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    robot, _ = effective_robot(env)
    env[ROBOT_ENV] = robot
    if anatomy:
        env[calibfiles.ANATOMY_ENV] = str(Path(anatomy).absolute())
    if overlay:
        env[calibfiles.OVERLAY_ENV] = str(Path(overlay).absolute())
    return env


def check_table(anatomy: str | None = None, overlay: str | None = None, out: Printer = _out) -> str:
    """Load the joint table the nodes will load (same rule, same files) and say where it comes from; returns that
    line. Calibration XML that does not load is a LaunchError before anything starts (its message names file and
    line); a YAML problem (e.g. an unknown $MDS_ACH_ROBOT) is left to the nodes, whose log tail explains it."""
    try:
        files = calibfiles.resolve(anatomy, overlay)
        table = load(None, None, anatomy, overlay)
    except calibfiles.CalibrationError as exc:
        raise LaunchError("", f"joint table: {exc}") from None
    except ValueError as exc:  # ConfigError (XML: with file and line)
        if files is None:
            return ""
        raise LaunchError("", f"joint table: {exc}") from None
    out(f"  joint table {describe(table)}")
    return describe(table)


def can_plan(nocan: bool) -> tuple[list[str], tuple[str, int] | None]:
    """The daemon's bus arguments and the SocketCAN link (channel, bitrate) to bring up, for a start: none with
    ``nocan``; python-can's configuration when there is one; else SocketCAN can0 at 1 Mbit/s, as the original."""
    if nocan:
        return [], None
    from mds_ach.bus.canio import BusConfigError, bus_config  # lazy: python-can only for a real start

    try:
        cfg = bus_config()
    except BusConfigError as exc:
        if "no CAN interface configured" not in str(exc):
            raise LaunchError("daemon", str(exc)) from None
        channel, bitrate = canlink.DEFAULT_CHANNEL, canlink.DEFAULT_BITRATE
        return ["-i", "socketcan", "-c", channel, "-b", str(bitrate)], (channel, bitrate)
    if cfg.get("interface") == "socketcan" and cfg.get("channel"):
        return [], (str(cfg["channel"]), int(cfg.get("bitrate") or canlink.DEFAULT_BITRATE))
    return [], None


def start_node(name: str, args: Sequence[str] = (), rt: Path | None = None,
               env: dict[str, str] | None = None, die_with_launcher: bool = False) -> subprocess.Popen:
    """Start one node in its own session (a Ctrl-C meant for the launcher never reaches it directly),
    output to ``<runtime>/<name>.log``, pid in ``<runtime>/<name>.pid``. ``die_with_launcher``: SIGTERM to the
    node when this process dies, however (``mds-ach run``); otherwise the node outlives it (``mds-ach start``)."""
    rt = rt or runtime_dir()
    rt.mkdir(parents=True, exist_ok=True)
    proc = background.spawn_detached(node_command(name) + list(args), log_path(name, rt),
                                     env=env if env is not None else child_env(),
                                     die_with_parent=die_with_launcher)
    background.write_pid_file(pid_path(name, rt), proc.pid)
    return proc


# --------------------------------------------------------------------------------------------- start


def _exit_text(code: int | None) -> str:
    if code is None:
        return "is still running"
    if code < 0:
        try:
            return f"was killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"was killed by signal {-code}"
    return f"exited with status {code}"


def _dead(procs: dict[str, subprocess.Popen]) -> tuple[str, int] | None:
    for name, proc in procs.items():
        code = proc.poll()
        if code is not None:
            return name, code
    return None


class _Heartbeat:
    """Counts new frames on a node's periodic output channel (opened read-only, flushed first, so frames
    from an earlier run never count)."""

    def __init__(self, channel: str) -> None:
        self.name = channel
        self.chan = ach.Channel(channel, create=False)
        self.chan.flush()
        self.buf = bytearray(self.chan.data_size)
        self.frames = 0

    def ready(self) -> bool:
        status, _ = self.chan.get(self.buf, last=True)
        if status in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
            self.frames += 1
        return self.frames >= 2

    def what(self) -> str:
        return f"no new frames on {self.name}"

    def close(self) -> None:
        self.chan.close()


class _IkProbe(_Heartbeat):
    """The IK node publishes only answers, and drops requests sent before it is ready: send it the probe request
    (``move = IK_PROBE_MOVE``: refused, nothing can move, logged as a probe) every 0.5 s until an answer appears on
    ``mds-ik-state``."""

    def __init__(self) -> None:
        super().__init__(mds.MDS_CHAN_IK_STATE_NAME)
        self.requests = ach.Channel(mds.MDS_CHAN_IK_NAME, create=False)
        self.next_probe = 0.0

    def ready(self) -> bool:
        status, _ = self.chan.get(self.buf, last=True)
        if status in (ach.ACH_OK, ach.ACH_MISSED_FRAME):
            return True
        if time.monotonic() >= self.next_probe:
            self.requests.put(mds.MDS_IK(move=IK_PROBE_MOVE))
            self.next_probe = time.monotonic() + 0.5
        return False

    def what(self) -> str:
        return f"no answer on {self.name} to a probe request on {mds.MDS_CHAN_IK_NAME}"

    def close(self) -> None:
        super().close()
        self.requests.close()


# How each node shows it is up (the contracts registry's ``ready`` channels): new frames on its periodic output
# (the daemon's mds-state first of all), or the IK node's answer to a probe; the bridge only needs to stay alive
# (its output is ROS, not a channel).
READINESS: dict[str, tuple[str, contracts.Readiness]] = contracts.readiness()
READY_CHANNELS: dict[str, str] = {node: channel for node, (channel, _how) in READINESS.items()}


def _readiness(name: str) -> _Heartbeat | None:
    channel, how = READINESS.get(name, ("", None))
    if how == "answer":
        return _IkProbe()
    return _Heartbeat(channel) if how == "stream" else None


def _check_dead(procs: dict[str, subprocess.Popen], rt: Path) -> None:
    dead = _dead(procs)
    if dead:
        name, code = dead
        raise LaunchError(name, f"{name} {_exit_text(code)} during start-up; last lines of "
                                f"{log_path(name, rt)}:\n{log_tail(name, rt=rt)}")


def wait_ready(procs: dict[str, subprocess.Popen], checks: dict[str, _Heartbeat], timeout: float, rt: Path,
               abort: Callable[[], bool] = lambda: False) -> None:
    """Return once every check passes (two new ``mds-state`` frames: the daemon's loop runs; likewise each
    pipeline node's output); raise LaunchError naming the node if one of ``procs`` dies first or a check
    does not pass within ``timeout``."""
    deadline = time.monotonic() + timeout
    pending = dict(checks)
    while pending:
        _check_dead(procs, rt)
        if abort():
            raise LaunchError("", "start-up interrupted")
        for name, check in list(pending.items()):
            if check.ready():
                del pending[name]
        if not pending:
            break
        if time.monotonic() > deadline:
            name, check = next(iter(pending.items()))
            raise LaunchError(name, f"{name} is not up after {timeout:g} s ({check.what()}); last lines of "
                                    f"{log_path(name, rt)}:\n{log_tail(name, rt=rt)}")
        time.sleep(0.05)
    _check_dead(procs, rt)


def launch(nocan: bool, timeout: float = DEFAULT_START_TIMEOUT, names: Sequence[str] = NODES,
           rt: Path | None = None, abort: Callable[[], bool] = lambda: False,
           out: Printer = _out, group: str | None = None, foreground: bool = False,
           world: str | None = None, anatomy: str | None = None,
           overlay: str | None = None, params: str | None = None, verb: str = "start",
           namespace: str | None = None) -> dict[str, subprocess.Popen]:
    """Create the channels (given to ``group`` if set), start ``names`` (those not already running) and wait
    until ``mds-state`` is live and each started node is up (see ``READY_CHANNELS``). ``foreground``: the nodes
    die with this process (``start_node``'s ``die_with_launcher``). ``world``: a world objects file for the
    collision gate and the IK node (checked first; the package's config/world.yaml otherwise).

    Existing channels must be ones the stack may trust (``channel_access``: owner, mode, group); otherwise
    nothing is started.

    On failure every node started here is stopped again and LaunchError is raised (the system is left as
    it was found).

    ``params``: a ROS 2 params file for every node (``params_choice``); checked first (``check_params``), so a bad
    file starts nothing.

    ``anatomy``/``overlay``: calibration XML for every node (``mds_ach.robot.calibfiles``); the joint table is
    loaded here first, so a bad file starts nothing. A real start (not ``nocan``) without any CAN configuration
    uses SocketCAN can0 at 1 Mbit/s and brings a SocketCAN link up first (``canlink``). ``verb``: the command that
    called (``start``/``run``), named in the hint for the simulated robot. ``namespace``: the ROS namespace of
    every node (``node_args``); with ``names`` a part of a running system, default: the one it was started in."""
    rt = rt or runtime_dir()
    world = world_file(world)
    if namespace is None and running_nodes(rt):
        namespace = recorded_namespace(rt)
    namespace = namespace or "/"
    check_params(params, nocan, out, namespace)
    starts_daemon = "daemon" in names and read_pid("daemon", rt) is None
    table_text = check_table(anatomy, overlay, out) if starts_daemon else ""
    can_args, link = can_plan(nocan) if starts_daemon else ([], None)
    if link is not None:
        try:
            out("  CAN link " + canlink.ensure_up(*link))
        except canlink.CanLinkError as exc:
            raise LaunchError("daemon", f"CAN link: {exc}\n  no robot here? the simulated one: "
                                        f"'mds-ach {verb} nocan'") from None
    try:
        reports = make_channels(group=group)
    except ValueError as exc:  # unknown group
        raise LaunchError("", str(exc)) from None
    for r in reports:
        if r.action == "tightened":  # made by the stack's own user the original way (ach mk, chmod 777)
            out(f"  channel {r.name}: {r.detail}")
    bad = [r for r in reports if not r.ok]
    if bad:
        theirs = another_users_channels([r.name for r in bad])
        raise LaunchError("", f"refusing to start: {theirs}" if theirs else "refusing to start, channel "
                          "problems:\n" + "\n".join(f"  {r.name}: {r.detail}" for r in bad))
    already = running_nodes(rt)
    env = child_env(anatomy, overlay)
    procs: dict[str, subprocess.Popen] = {}
    checks: dict[str, _Heartbeat] = {}
    try:
        for name in names:
            if name in already:
                out(f"  {name:<10} already running (pid {already[name]})")
                continue
            check = _readiness(name)
            if check is not None:
                checks[name] = check
            procs[name] = start_node(name, node_args(name, nocan, world, can_args, params, namespace), rt, env,
                                     die_with_launcher=foreground)
            out(f"  {name:<10} started (pid {procs[name].pid}, log {log_path(name, rt)})")
        wait_ready(procs, checks, timeout, rt, abort)
        if procs:
            (rt / NAMESPACE_RECORD).write_text(namespace + "\n")
        if "collision" in procs:  # what the running gate uses, for `mds-ach sim` (viewer.system_world)
            (rt / WORLD_RECORD).write_text((world or str(config_path("world.yaml"))) + "\n")
        if starts_daemon:
            (rt / TABLE_FILE).write_text(table_text + "\n")
            if link is not None:
                canlink.save_link(rt, *link)
            else:
                canlink.clear_link(rt)
    except BaseException:
        stop_nodes(list(procs), rt=rt, procs=procs, out=lambda _t: None)
        raise
    finally:
        for check in checks.values():
            check.close()
    return procs


# --------------------------------------------------------------------------------------------- stop / kill


def _wait_gone(pids: dict[str, int], children: dict[str, subprocess.Popen], timeout: float) -> dict[str, int]:
    """Wait until the processes exit (reaping our own children); returns those still alive."""
    def reap() -> None:
        for name, pid in pids.items():
            if name in children and children[name].pid == pid:
                children[name].poll()

    left = set(background.wait_gone(list(pids.values()), timeout, reap))
    return {n: p for n, p in pids.items() if p in left}


def stop_nodes(names: Iterable[str] = NODES, grace: float = DEFAULT_STOP_GRACE, rt: Path | None = None,
               procs: dict[str, subprocess.Popen] | None = None, sig: int = signal.SIGTERM,
               out: Printer = _out) -> list[str]:
    """Stop nodes: ``sig`` to the clients and pipeline first, the daemon last (the robot holds its last
    reference meanwhile), SIGKILL after ``grace`` s. Returns the nodes that were running."""
    rt = rt or runtime_dir()
    procs = procs or {}
    names = list(names)
    pids: dict[str, int] = {}
    for name in names:
        pid = read_pid(name, rt)
        if pid is None and name in procs and procs[name].poll() is None:
            pid = procs[name].pid
        if pid is not None:
            pids[name] = pid
    stages = [{n: p for n, p in pids.items() if n != "daemon"}, {n: p for n, p in pids.items() if n == "daemon"}]
    for stage in stages:
        if not stage:
            continue
        for pid in stage.values():
            background.signal_pid(pid, sig)
        left = _wait_gone(stage, procs, grace if sig != signal.SIGKILL else 2.0)
        for name, pid in left.items():
            out(f"  {name:<10} did not exit {grace:g} s after {signal.Signals(sig).name}; sending SIGKILL")
            background.signal_pid(pid, signal.SIGKILL)
        _wait_gone(left, procs, 2.0)
        for name, pid in stage.items():
            out(f"  {name:<10} stopped (pid {pid})")
    for name in names:
        if read_pid(name, rt) is None:
            background.remove_pid_file(pid_path(name, rt))
    return list(pids)


def stop_viewer(rt: Path | None = None, out: Printer = _out) -> None:
    """Stop the background 3-D viewer (`mds-ach sim`) of this runtime dir: it ends with the system, so its page
    (a way to move the robot) is never left open after a stop."""
    from mds_ach.tools.viewer import stop_viewer as stop  # light: the viewer's heavy imports are lazy

    pid = stop(rt or runtime_dir())
    if pid is not None:
        out(f"  {'viewer':<10} stopped (pid {pid})")


# --------------------------------------------------------------------------------------------- commands


def send_command(cmd: int, address: int = 0, value: float = 0.0) -> int:
    """Put one ``MDS_CMD`` on ``mds-cmd`` with the next sequence number; returns that number."""
    chan = ach.Channel(mds.MDS_CHAN_BOARD_CMD_NAME, create=False)
    try:
        last = mds.MDS_CMD()
        status, size = chan.get(last, last=True, copy=True)
        seq = (last.seq + 1) & 0xFFFFFFFF if status in (ach.ACH_OK, ach.ACH_MISSED_FRAME) and \
            size == ctypes.sizeof(mds.MDS_CMD) else 1
        chan.put(mds.MDS_CMD(seq=seq, cmd=cmd, address=address, value=value))
    finally:
        chan.close()
    return seq


def state_rate(window: float = 1.0) -> tuple[float, int] | None:
    """New ``mds-state`` frames per second over ``window`` s, and how many frames of the wrong size arrived
    (None when the channel does not exist). Raises ``ach.AchException``/``ValueError`` for a damaged channel."""
    if not ach.exists(mds.MDS_CHAN_STATE_NAME):
        return None
    with StructChannel(mds.MDS_CHAN_STATE_NAME, mds.MDS_STATE, create=False) as chan:
        chan.latest()
        frames, t0 = 0, time.monotonic()
        first = last = None
        while time.monotonic() - t0 < window:
            if chan.wait(max(0.0, window - (time.monotonic() - t0))) is not None:
                frames += 1
                now = time.monotonic()
                first = now if first is None else first
                last = now
        if frames >= 2 and first is not None and last is not None and last > first:
            return (frames - 1) / (last - first), chan.bad_frames
        return float(frames) / window, chan.bad_frames


def channel_problems(names: Sequence[str] = mds.ALL_CHANNELS) -> dict[str, str]:
    """channel -> what is wrong with it and what to do, for every MDS channel the system cannot use: missing
    (while others exist), owned by another user or too open, not an Ach file, truncated, corrupt, locked, or of
    the wrong size."""
    if not any(os.path.lexists(ach.shm_path(n)) for n in names):
        return {}  # nothing made yet: the node lines already say that nothing runs
    problems = {}
    for name in names:
        health = repair.check(name)
        if not health.ok:
            problems[name] = f"{health.state}: {health.detail}; {health.hint()}"
            continue
        made = check_existing(name)
        if not made.ok:
            problems[name] = made.detail
    return problems


def status_report(rt: Path | None = None, window: float = 1.0) -> tuple[list[str], int]:
    """Lines for ``mds-ach status`` and its exit status: 0 all well, 1 a channel is damaged or not to be
    trusted, 3 a node is not running. Never raises for a damaged channel: it is reported with the repair hint."""
    rt = rt or runtime_dir()
    lines = [f"runtime dir {rt}"]
    if contracts.CHANNEL_PREFIX:
        prefix = contracts.CHANNEL_PREFIX
        lines.append(f"channels   named {prefix}mds-* (${CHANNEL_PREFIX_ENV}={prefix})")
    running = running_nodes(rt)
    namespace = recorded_namespace(rt) if running else None
    if namespace and namespace != "/":
        lines.append(f"namespace  {namespace} (ROS: {namespace}/joint_states, {namespace}/mds_daemon/command, ...)")
    if not running:
        lines.append("MDS-Ach is not running (no node runs; start it with 'mds-ach run nocan' or 'mds-ach start')")
    for name in NODES:
        pid = running.get(name)
        stale = pid is None and pid_path(name, rt).exists()
        state = f"running   pid {pid}" if pid else ("stopped   (stale pid file)" if stale else "stopped")
        lines.append(f"  {name:<10} {state}")
    robot, where = effective_robot()
    try:
        xml = calibfiles.resolve() is not None
    except calibfiles.CalibrationError:
        xml = True  # the table line below says what is wrong
    lines.append(f"robot      {robot} ({where})" + ("  (the variant is not used: the calibration XML wins)"
                                                    if xml and robot != XML_ROBOT else ""))
    lines.append("table      " + table_line(read_published(), recorded_table(rt)))
    problems = channel_problems()
    theirs = another_users_channels(list(problems), then="'mds-ach status' again") if problems else None
    lines += [f"channels   {theirs}"] if theirs else [f"channel    {name}: {text}" for name, text in problems.items()]
    if not problems and any(ach.exists(n) for n in mds.ALL_CHANNELS):
        lines.append(f"channels   ok ({len(mds.ALL_CHANNELS)})")
    try:
        measured = None if mds.MDS_CHAN_STATE_NAME in problems else state_rate(window)
    except (ach.AchException, ValueError) as exc:
        lines.append(f"state      unreadable: {exc}")
    else:
        if mds.MDS_CHAN_STATE_NAME in problems:
            lines.append(f"state      unreadable (channel {mds.MDS_CHAN_STATE_NAME} above)")
        elif measured is None:
            lines.append(f"state      no {mds.MDS_CHAN_STATE_NAME} channel")
        else:
            rate, bad = measured
            lines.append(f"state      {rate:.1f} frames/s on {mds.MDS_CHAN_STATE_NAME}" + ("" if rate > 0 else
                                                                                             "  (not live)")
                         + (f"  {bad} frame(s) of the wrong size ignored (not {ctypes.sizeof(mds.MDS_STATE)} B: "
                            "a writer built against another mds.h?)" if bad else ""))
    daemon = Latest(mds.MDS_CHAN_DAEMON_STATUS_NAME, MDS_DAEMON_STATUS)
    collide = Latest(mds.MDS_CHAN_COLLIDE_NAME, mds.MDS_COLLIDE)
    mux = Latest(mds.MDS_CHAN_MUX_STATE_NAME, MDS_MUX_STATE)
    gate_input = Latest(mds.MDS_CHAN_REF_SMOOTH_NAME, mds.MDS_REF)  # what the gate checks against the limits
    seen: list[str] = []
    try:
        daemon.read()
        live = bool(running) and daemon.wait_new(0.5) is not None  # a dead daemon's last frame stays in the channel
        stale_note = "" if live or daemon.frame is None or not running else "  STALE: no update within 0.5 s"
        seen.append("daemon     " + daemon_line(daemon.frame, None) + stale_note)
        seen.append("collision  " + collision_summary(collide.read()))
        seen.append("held       " + held_summary(mux.read(), newest_enabled()))
        try:
            seen.append("limits     " + limits_line(current_limits(), gate_input.read()))
        except ValueError as exc:  # a broken joint table or URDF: say so, the rest of the status still counts
            seen.append(f"limits     unknown: {exc}")
        if not running and daemon.frame is not None:  # history, never to be read as the robot's state now
            age = time.monotonic() - float(daemon.frame.time)
            when = f"{age:.0f} s ago" if 0 <= age < 10 * 86400 else "before this boot or clock"
            lines.append(f"last seen  (history, not live: what the channels held when the system stopped, "
                         f"last daemon frame {when})")
            seen = ["  " + line for line in seen]
        elif not running:
            seen = []
    finally:
        daemon.close()
        collide.close()
        mux.close()
        gate_input.close()
    return lines + seen, 1 if problems else (0 if len(running) == len(NODES) else 3)


# --------------------------------------------------------------------------------------------- foreground run


NEXT_STEPS = """\
MDS-Ach is running{mode}. Node logs: {rt}
In another terminal (same machine){activate}{prefix}:
  mds-ach read                 live joint table (q quits)
  mds-ach console              goto / get / get fk / ik  (try: get fk left, goto LSP -0.3)
  mds-ach status               nodes, loop rate, bus load, collisions
  python examples/one_joint.py
{ros}
Press Ctrl-C to stop everything."""


def _activate_hint() -> str:
    """How to get `mds-ach` on PATH in another shell, when it is not there already (e.g. after `make run`)."""
    if shutil.which("mds-ach"):
        return ""
    activate = Path(sys.prefix) / "bin" / "activate"
    return f", after `source {activate}`" if activate.is_file() else ""


def _prefix_hint() -> str:
    """A system with prefixed channel names is seen only by clients with the same prefix."""
    if not contracts.CHANNEL_PREFIX:
        return ""
    return f", with `export {CHANNEL_PREFIX_ENV}={contracts.CHANNEL_PREFIX}` (this system's channels)"


def _surviving(out: Printer) -> Printer:
    """``out``, but a write error (the reader or the terminal is gone) never stops the caller."""
    def safe(text: str) -> None:
        try:
            out(text)
        except (OSError, ValueError):
            pass

    return safe


def run_foreground(nocan: bool, timeout: float, out: Printer = _out, group: str | None = None,
                   world: str | None = None, anatomy: str | None = None, overlay: str | None = None,
                   params: str | None = None, namespace: str | None = None) -> int:
    """``mds-ach run``: start everything, print what to do next, supervise, stop cleanly. Leaves no orphans.

    It stops every node on Ctrl-C, SIGTERM and SIGHUP (the terminal closed), when its output is gone (``make run |
    tee log``: the Ctrl-C kills tee first, every print then fails with EPIPE), and when its parent exits (it is
    re-parented: ``make`` killed). The nodes get SIGTERM from the kernel if this process dies without stopping them
    (SIGKILL). A node that dies takes the whole system down (with its log tail): a half-running pipeline would hold
    the robot without anyone noticing."""
    rt = runtime_dir()
    out = _surviving(out)
    stop_requested: list[int] = []
    parent = os.getppid()

    def on_signal(signum: int, _frame: object) -> None:
        stop_requested.append(signum)

    def parent_gone() -> bool:
        return os.getppid() != parent

    def abort() -> bool:
        return bool(stop_requested) or parent_gone()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    procs: dict[str, subprocess.Popen] = {}
    started = False
    try:
        already = running_nodes(rt)
        if already:
            _err("mds-ach run: already running: " + ", ".join(f"{n} (pid {p})" for n, p in already.items())
                 + "; stop them first with 'mds-ach stop'")
            return 1
        out(f"starting MDS-Ach{' on the simulated robot (nocan)' if nocan else ''} ...")
        started = True
        try:
            procs = launch(nocan, timeout, rt=rt, abort=abort, out=out, group=group, foreground=True, world=world,
                           anatomy=anatomy, overlay=overlay, params=params, verb="run", namespace=namespace)
        except LaunchError as exc:
            if abort():
                out("interrupted; everything stopped")
                return 0
            _err(f"mds-ach run: {exc}")
            return 1
        out(NEXT_STEPS.format(mode=" on the simulated robot (nocan)" if nocan else "", rt=rt,
                              activate=_activate_hint(), ros=ros_graph_summary(namespace=namespace),
                              prefix=_prefix_hint()))
        failed = None
        while not abort() and failed is None:
            failed = _dead(procs)
            if failed is None:
                time.sleep(0.2)
        if failed:
            name, code = failed
            _err(f"mds-ach run: {name} {_exit_text(code)}; last lines of {log_path(name, rt)}:\n"
                 f"{log_tail(name, rt=rt)}\nstopping everything")
        elif parent_gone() and not stop_requested:
            out(f"mds-ach run: its parent (pid {parent}) exited; stopping everything")
        else:
            why = {signal.SIGHUP: " (SIGHUP: the terminal was closed)"}.get(signal.Signals(stop_requested[0]), "")
            out(f"stopping{why} ...")
        return 1 if failed else 0
    finally:
        if started:  # whatever happened above (an error included), nothing this run started is left behind
            stop_nodes(NODES, rt=rt, procs=procs, out=out)
            stop_viewer(rt, out)
        for s, handler in old.items():
            signal.signal(s, handler)


# --------------------------------------------------------------------------------------------- CLI verbs


def _add_nocan(p: argparse.ArgumentParser) -> None:
    p.add_argument("mode", nargs="?", choices=["nocan"],
                   help="'nocan': run on the simulated MDS bus instead of the CAN interface")
    p.add_argument("--nocan", dest="nocan_flag", action="store_true", help="same as the 'nocan' word")
    p.add_argument("--timeout", type=seconds(), default=DEFAULT_START_TIMEOUT,
                   help=f"seconds to wait for the state channel to go live (default {DEFAULT_START_TIMEOUT:g})")
    p.add_argument("--group", metavar="GROUP",
                   help="give channels created now to this group (the operators'), like 'mds-ach make --group'; "
                        "existing channels must belong to it")
    p.add_argument("--world", metavar="FILE",
                   help="world objects YAML (e.g. a table, see config/world.yaml) for the collision gate and the IK "
                        "node; default: the package's config/world.yaml")
    p.add_argument("--anatomy", metavar="FILE",
                   help="Xitome anatomy.xml to read the joint table from (default: $MDS_ACH_ANATOMY, else "
                        "/etc/mds-ach/anatomy.xml or /etc/mds-ach/configs/anatomy.xml, else the packaged YAML)")
    p.add_argument("--overlay", metavar="FILE",
                   help="MDS-Ach mdsach.xml for the anatomy (default: $MDS_ACH_OVERLAY, else "
                        "/etc/mds-ach/configs/mdsach.xml, else the mdsach.xml beside the anatomy)")
    p.add_argument("--params", metavar="FILE",
                   help="ROS 2 params file for the nodes (<node>: ros__parameters: ...), checked before anything "
                        "starts; default: the package's config/params.yaml when it exists (docs/parameters.md)")
    p.add_argument("--no-params", action="store_true", help="pass no params file: the nodes' built-in defaults")
    p.add_argument("--namespace", metavar="NAME", type=ros_namespace,
                   help="ROS namespace of every node (e.g. robot1: /robot1/joint_states, /robot1/mds_daemon/command, "
                        "...), for several robots on one ROS graph; default: none (/joint_states). A params file's "
                        "sections then need /**/NODE: (as config/params.yaml has) or /NAME/NODE:")


def add_start_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Create the channels, then start each node as its own process (" + ", ".join(NODES) +
                     "), with pid files and logs in the runtime directory ($MDS_ACH_RUNTIME_DIR). Returns once "
                     "mds-state is live; exits 1 with the failing node's log tail otherwise.")
    _add_nocan(p)
    p.add_argument("--only", nargs="+", choices=NODES, metavar="NODE",
                   help="start only these nodes (e.g. to restart one that was killed)")


def run_start(args: argparse.Namespace) -> int:
    nocan = args.mode == "nocan" or args.nocan_flag
    names = args.only or NODES
    rt = runtime_dir()
    running = running_nodes(rt)
    if not args.only and running:
        _err("mds-ach start: already running: " + ", ".join(f"{n} (pid {p})" for n, p in running.items())
             + "\n  use 'mds-ach stop' first, or 'mds-ach start --only NODE' to start missing nodes")
        return 1
    _out(f"starting MDS-Ach{' (nocan: simulated bus)' if nocan else ''}; runtime dir {rt}")
    try:
        launch(nocan, args.timeout, names, rt, group=args.group, world=args.world, anatomy=args.anatomy,
               overlay=args.overlay, params=params_choice(args.params, args.no_params), namespace=args.namespace)
    except LaunchError as exc:
        _err(f"mds-ach start: {exc}")
        return 1
    except KeyboardInterrupt:
        _err("mds-ach start: interrupted; the nodes started were stopped")
        return 130
    _out(f"MDS-Ach is running in the background ({mds.MDS_CHAN_STATE_NAME} is live): it keeps running after this "
         "command and this terminal end; 'mds-ach stop' stops it ('mds-ach run' runs it in the foreground instead).")
    return 0


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Start everything in the foreground, print what to do next, and stop everything cleanly "
                     "on Ctrl-C, SIGTERM or SIGHUP (terminal closed), when its output pipe breaks and when its parent "
                     "exits: nothing is left running, the 3-D viewer ('mds-ach sim') included (this is what 'make run' "
                     "does, with --nocan).")
    _add_nocan(p)


def run_run(args: argparse.Namespace) -> int:
    return run_foreground(args.mode == "nocan" or args.nocan_flag, args.timeout, group=args.group,
                          world=args.world, anatomy=args.anatomy, overlay=args.overlay,
                          params=params_choice(args.params, args.no_params), namespace=args.namespace)


def add_stop_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Stop the nodes: SIGTERM (clients and pipeline first, the daemon last), SIGKILL after a grace "
                     "time; without NODE also the 3-D viewer ('mds-ach sim').")
    p.add_argument("--grace", type=seconds(zero=True), default=DEFAULT_STOP_GRACE,
                   help=f"seconds to wait after SIGTERM before SIGKILL (default {DEFAULT_STOP_GRACE:g})")
    p.add_argument("nodes", nargs="*", metavar="NODE", help=f"only these nodes ({', '.join(NODES)})")


def run_stop(args: argparse.Namespace) -> int:
    unknown = [n for n in args.nodes if n not in NODES]
    if unknown:
        _err(f"mds-ach stop: unknown node(s) {', '.join(unknown)}; nodes: {', '.join(NODES)}")
        return 2
    stopped = stop_nodes(args.nodes or NODES, grace=args.grace)
    if not args.nodes:
        stop_viewer()
    if not stopped:
        _out("nothing was running")
    return 0


def add_kill_arguments(p: argparse.ArgumentParser) -> None:
    p.description = "SIGKILL every node (no clean shutdown; prefer 'stop')."


def run_kill(args: argparse.Namespace) -> int:
    stopped = stop_nodes(NODES, sig=signal.SIGKILL)
    stop_viewer()
    if not stopped:
        _out("nothing was running")
    return 0


def add_killall_arguments(p: argparse.ArgumentParser) -> None:
    p.description = "SIGKILL every node, then remove every MDS channel from /dev/shm."


def run_killall(args: argparse.Namespace) -> int:
    stop_nodes(NODES, sig=signal.SIGKILL)
    stop_viewer()
    removed = remove_channels()
    _out(f"removed {len(removed)} channels" + (": " + " ".join(removed) if removed else ""))
    return 0


def add_status_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Which nodes run, the health of every MDS channel (with the command that repairs a damaged "
                     "one), the state rate, the daemon's loop rate and bus load, and the collision state; when no "
                     "node runs it says 'not running' and shows what the channels last held as history. Exit "
                     "status 0 when every node runs and every channel is sound, 1 when a channel is damaged or "
                     "not to be trusted, 3 when a node is not running (none included).")
    p.add_argument("--window", type=seconds(60.0), default=1.0, help="seconds to measure the state rate (default 1)")


def run_status(args: argparse.Namespace) -> int:
    lines, status = status_report(window=args.window)
    _out("\n".join(lines))
    return status


def add_resetbus_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Reset the CAN bus (recover from bus-off), like the original: restart the SocketCAN link the "
                     "system was started on (ip link set CHANNEL down / type can bitrate ... / up; or print those "
                     "commands when this user may not run them), then ask the daemon to re-open its bus: "
                     f"MDS_CMD_RESET_BUS on {mds.MDS_CHAN_BOARD_CMD_NAME}.")
    p.add_argument("--timeout", type=seconds(), default=5.0, help="seconds to wait for the daemon's acknowledgement")
    p.add_argument("--channel", help="SocketCAN link to restart (default: the one 'mds-ach start' brought up; none "
                                     "for the simulated bus or another interface)")
    p.add_argument("--no-link", action="store_true", help="only reset the daemon's side, not the link")


def run_resetbus(args: argparse.Namespace) -> int:
    link = None if args.no_link else (
        (args.channel, canlink.DEFAULT_BITRATE) if args.channel else canlink.saved_link(runtime_dir()))
    if link is not None:
        try:
            _out(canlink.restart(*link))
        except canlink.CanLinkError as exc:
            _err(f"mds-ach resetbus: {exc}\n  (after restarting the link yourself, 'mds-ach resetbus --no-link' resets "
                 "the daemon's side)")
            return 1
    status = Latest(mds.MDS_CHAN_DAEMON_STATUS_NAME, MDS_DAEMON_STATUS)
    try:
        status.read()
        try:
            seq = send_command(mds.MDS_CMD_RESET_BUS)
        except ach.AchException as exc:
            _err(f"mds-ach resetbus: cannot write {mds.MDS_CHAN_BOARD_CMD_NAME}: {exc} (is the system started?)")
            return 1
        _out(f"sent MDS_CMD_RESET_BUS (seq {seq}) on {mds.MDS_CHAN_BOARD_CMD_NAME}")
        deadline = time.monotonic() + args.timeout
        while time.monotonic() < deadline:  # the daemon echoes the seq of each command it handled
            st = status.wait_new(0.2)
            if st is not None and st.cmd_seq == seq:
                if st.cmd_result != CMD_OK:
                    _err(f"mds-ach resetbus: the daemon could not reset the bus (result {st.cmd_result}); see "
                         f"{log_path('daemon')}")
                    return 1
                _out(f"bus reset by the daemon: state {BUS_STATE_NAMES.get(st.bus_state, '?')}, "
                     f"{st.bus_resets} reset(s) so far")
                return 0
    finally:
        status.close()
    _err(f"mds-ach resetbus: no acknowledgement from the daemon within {args.timeout:g} s (is it running? "
         "'mds-ach status')")
    return 1


def add_changerobot_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Choose the robot for the next start. With an original installation (/etc/mds-ach, or "
                     f"${calibfiles.ETC_ENV}), like the original: copy configs/<Robot>.anatomy.xml (isaac, lucas, "
                     "octavia) or the anatomy file given as a path over its anatomy.xml. Otherwise: save the "
                     "packaged robot variant whose joint table the daemon loads (in $MDS_ACH_CONFIG_DIR/robot, "
                     "default ~/.config/mds-ach/robot; $MDS_ACH_ROBOT overrides it). Restart the system for it to "
                     "take effect. An unknown name changes nothing (exit status 2).")
    p.add_argument("robot", type=_robot_argument,
                   help=f"robot ({', '.join(available_robots())}) or, with /etc/mds-ach, a path to an anatomy file")


PATH_MAX = 4096  # Linux: longer paths (or components over NAME_MAX) fail in every system call


def _robot_argument(text: str) -> str:
    """A robot name, or a path when it has a '/' or ends in .xml: checked for sense before any file access (a
    5,000-character name traced back in stat)."""
    if "/" in text or text.endswith(".xml"):
        if len(text) > PATH_MAX or any(len(part) > 255 for part in text.split("/")) or "\0" in text:
            raise argparse.ArgumentTypeError(f"path too long or invalid: {text[:80]!r}...")
        return text
    problem = name_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(problem)
    return text


NO_CHANGE = "-- No Change to Robot --"  # the original's words for an unknown robot


def _changerobot_etc(name: str, etc: Path) -> int:
    """The original's ChangeRobot: copy the robot's anatomy (or the file ``name``) over ``etc``'s anatomy.xml,
    after checking that it loads with the installation's overlay."""
    path = Path(name).expanduser()
    source = path if path.is_file() else calibfiles.robot_anatomy(name, etc)
    if source is None:
        _out(NO_CHANGE)
        _err(f"mds-ach changerobot: unknown robot {name!r}: give one of {', '.join(calibfiles.ROBOT_ANATOMIES)} "
             f"(an anatomy in {etc / 'configs'}) or the path of an anatomy file")
        return 2
    try:
        current = calibfiles.resolve(env={calibfiles.ETC_ENV: str(etc)})
        overlay = current.overlay if current else None
        load(None, None, source, overlay)  # refuse a file that does not load, before copying it
        written = calibfiles.install_anatomy(source, etc)
    except (ConfigError, ValueError) as exc:
        _out(NO_CHANGE)
        _err(f"mds-ach changerobot: {exc}")
        return 1
    except OSError as exc:
        _out(NO_CHANGE)
        _err(f"mds-ach changerobot: cannot write in {etc}: {exc.strerror} (run it as root: sudo mds-ach "
             f"changerobot {shlex.quote(name)})")
        return 1
    label = name.strip().capitalize() if source != path else str(source)
    _out(f"-- Robot Changed to {label} -- ({source} copied to {', '.join(map(str, written))})")
    return 0


def run_changerobot(args: argparse.Namespace) -> int:
    etc = calibfiles.etc_dir()
    if etc.is_dir():
        status = _changerobot_etc(args.robot, etc)
    else:
        name = args.robot.strip().lower()
        if name not in available_robots():
            _out(NO_CHANGE)
            hint = (f"; an anatomy file is used with 'mds-ach start --anatomy FILE' or ${calibfiles.ANATOMY_ENV} "
                    f"(no {etc} here to copy it into)" if Path(args.robot).is_file() else "")
            _err(f"mds-ach changerobot: unknown robot {args.robot!r}; choose one of: {', '.join(available_robots())}"
                 + hint)
            return 2
        try:
            load(name)  # refuse a variant whose files do not load, before saving it
            path = save_robot(name)
        except (ConfigError, ValueError, OSError) as exc:
            _err(f"mds-ach changerobot: {exc}")
            return 1
        _out(f"robot variant '{name}' saved in {path}")
        if os.environ.get(ROBOT_ENV) and os.environ[ROBOT_ENV].strip().lower() != name:
            _err(f"note: ${ROBOT_ENV}={os.environ[ROBOT_ENV]} is set in this shell and overrides the saved choice")
        status = 0
    if status == 0 and running_nodes():
        _out("the system is running: restart it ('mds-ach stop', then 'mds-ach start') to use the new robot")
    return status


# --------------------------------------------------------------------------------------------- exec entry


def _exec(argv: list[str]) -> int:
    """``python -m mds_ach.tools.launcher exec NODE [ARGS]``: run a node's main() when no console script exists."""
    if not argv or argv[0] not in ENTRY_POINTS:
        _err(f"usage: python -m mds_ach.tools.launcher exec {{{','.join(NODES)}}} [ARGS...]")
        return 2
    module, _, func = ENTRY_POINTS[argv[0]].partition(":")
    sys.argv = [argv[0], *argv[1:]]
    return int(getattr(importlib.import_module(module), func)() or 0)


if __name__ == "__main__":
    if sys.argv[1:2] == ["exec"]:
        raise SystemExit(_exec(sys.argv[2:]))
    _err("usage: python -m mds_ach.tools.launcher exec NODE [ARGS...]  (use the 'mds-ach' command instead)")
    raise SystemExit(2)
