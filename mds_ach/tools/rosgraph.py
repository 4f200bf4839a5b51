"""``mds-ach ros-shell`` and ``mds-ach ros CMD...``: a shell, or one command, inside the running system's ROS 2 graph
(``mds-ach ros topics|echo|hz``: ``mds_ach.tools.rostopic``, for a ROS without the ``ros2`` command line).

``make run`` starts the nodes in a private network namespace (tools/netns-run: DDS on loopback only) with a random
``ROS_DOMAIN_ID``, and for a normal user inside a user namespace too, so a second terminal sees no ROS graph at all.
The handle to that graph is what the system leaves in the runtime directory anyway: the nodes' pid files. A running
node's process gives both halves: its namespaces (``/proc/PID/ns/{user,mnt,net}``, joined with ``nsenter`` where
they differ from ours) and its environment (``/proc/PID/environ``: ``ROS_DOMAIN_ID``, the discovery range, the DDS
profile, ``AMENT_PREFIX_PATH``). A system started without namespaces (``make run ISOLATE=0``, ``ros2 run``) only
lends its environment.
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

from mds_ach.paths import CHANNEL_PREFIX_ENV, host_uid, runtime_dir

# The node whose graph we want first: the bridge publishes /joint_states; any other node shares its namespaces.
GRAPH_NODES: tuple[str, ...] = ("bridge", "daemon", "mux", "filter", "collision", "ik")
# What makes two processes one ROS graph, taken from the running node (and dropped from ours when it lacks them).
GRAPH_ENV_PREFIXES: tuple[str, ...] = ("ROS_", "RMW_", "FASTRTPS_", "FASTDDS_", "CYCLONEDDS_")
GRAPH_ENV_KEYS: tuple[str, ...] = ("AMENT_PREFIX_PATH", "MDS_NETNS_ACTIVE", "MDS_ACH_RUNTIME_DIR", "MDS_ACH_ROBOT",
                                  CHANNEL_PREFIX_ENV)
# nsenter's options per namespace kind, in the order the kernel needs them (the user namespace first).
NAMESPACES: tuple[str, ...] = ("user", "mnt", "net")


class GraphError(RuntimeError):
    """No running system to join, or it cannot be joined; the message says what to do."""


@dataclass(frozen=True)
class Graph:
    """A running node's graph: its pid, its graph environment and the namespaces of it that differ from ours."""

    node: str
    pid: int
    env: dict[str, str]
    join: tuple[str, ...]

    @property
    def domain_id(self) -> str:
        return self.env.get("ROS_DOMAIN_ID", "0")


def _is_graph_key(key: str) -> bool:
    return key.startswith(GRAPH_ENV_PREFIXES) or key in GRAPH_ENV_KEYS


def proc_environ(pid: int) -> dict[str, str]:
    """The environment process ``pid`` was started with."""
    raw = Path(f"/proc/{pid}/environ").read_bytes()
    pairs = (item.split(b"=", 1) for item in raw.split(b"\0") if b"=" in item)
    return {k.decode(errors="replace"): v.decode(errors="replace") for k, v in pairs}


def namespaces_to_join(pid: int) -> tuple[str, ...]:
    """The namespaces of ``pid`` (user, mount, network) that are not ours."""
    return tuple(ns for ns in NAMESPACES
                 if os.readlink(f"/proc/{pid}/ns/{ns}") != os.readlink(f"/proc/self/ns/{ns}"))


def find_graph(rt: Path | None = None) -> Graph:
    """The graph of the system whose pid files are in ``rt`` (default: the runtime directory)."""
    from mds_ach.tools.launcher import read_pid  # the one test of "this pid is that node"

    rt = rt or runtime_dir()
    for node in GRAPH_NODES:
        pid = read_pid(node, rt)
        if pid is None:
            continue
        try:
            env = {k: v for k, v in proc_environ(pid).items() if _is_graph_key(k)}
            join = namespaces_to_join(pid)
        except PermissionError as exc:
            owner = Path(f"/proc/{pid}").stat().st_uid
            raise GraphError(f"the system runs as another user (node {node}, pid {pid}, uid {owner}): run this as "
                             f"that user, or as root ({exc.strerror})") from exc
        except FileNotFoundError:
            continue  # it ended just now
        return Graph(node, pid, env, join)
    raise GraphError(f"no running MDS-Ach node in {rt} (start the system with 'make run' or 'mds-ach start'; "
                     "MDS_ACH_RUNTIME_DIR selects another system's runtime directory)")


def environment(graph: Graph, base: dict[str, str] | None = None) -> dict[str, str]:
    """Our environment with the graph's ROS/DDS settings instead of ours, and this venv's ``bin`` first on PATH
    (``python`` there has rclpy and the package)."""
    env = {k: v for k, v in (os.environ if base is None else base).items() if not _is_graph_key(k)}
    env.update(graph.env)
    bindir = str(Path(sys.executable).parent)
    path = [p for p in env.get("PATH", os.defpath).split(os.pathsep) if p and p != bindir]
    env["PATH"] = os.pathsep.join([bindir, *path])
    if sys.prefix != sys.base_prefix:
        env["VIRTUAL_ENV"] = sys.prefix
    return env


def command(graph: Graph, argv: list[str], cwd: str | None = None) -> list[str]:
    """``argv`` wrapped in ``nsenter`` when the graph lives in other namespaces."""
    if not graph.join:
        return list(argv)
    flags = {"user": ["--user", "--preserve-credentials"], "mnt": ["--mount", f"--wd={cwd or os.getcwd()}"],
             "net": ["--net"]}
    return ["nsenter", f"--target={graph.pid}", *(f for ns in graph.join for f in flags[ns]), "--", *argv]


def summary(env: dict[str, str] | None = None, namespace: str | None = None) -> str:
    """What ``mds-ach run`` prints about its ROS 2 graph: the domain, the nodes' ROS namespace when there is one,
    and how to get into it."""
    env = dict(os.environ if env is None else env)
    domain = env.get("ROS_DOMAIN_ID") or "0 (default)"
    if namespace and namespace != "/":
        domain += f", nodes in the ROS namespace {namespace} ({namespace}/joint_states, {namespace}/mds_daemon/...)"
    if env.get("MDS_NETNS_ACTIVE") == "1":
        return (f"ROS 2 graph: ROS_DOMAIN_ID={domain}, in this system's private network namespace (loopback only).\n"
                "  mds-ach ros-shell            a shell inside that graph (examples/ros_*.py, rclpy scripts)\n"
                "  mds-ach ros CMD...           one command inside it, e.g.\n"
                "                               mds-ach ros python examples/ros_joint_state_subscriber.py --count 5\n"
                "  mds-ach ros topics|echo|hz   its topics, one's messages, its rate (no ros2 command line needed)")
    return (f"ROS 2 graph: ROS_DOMAIN_ID={domain} on this machine's network (not isolated): any shell with\n"
            f"  export ROS_DOMAIN_ID={env.get('ROS_DOMAIN_ID', '0')} reaches it (or 'mds-ach ros-shell')")


def prompt(bash: bool = True) -> str:
    """The shell prompt inside the graph: what the shell is and who the user really is. Inside the user namespace
    of a rootless system the user is uid 0, so the shell's own ``\\u`` would say ``root@...`` (issue 28). ``bash``:
    with the working directory (``\\w``, which sh does not expand)."""
    import pwd
    import socket

    uid = host_uid()
    try:
        user = pwd.getpwuid(uid).pw_name
    except KeyError:
        user = f"uid{uid}"
    where = ":\\w" if bash else ""
    return f"(mds-ach ros) {user}@{socket.gethostname().split('.')[0]}{where}{'#' if uid == 0 else '$'} "


def bash_rc(env: dict[str, str]) -> str:
    """A bash rcfile: the user's ``~/.bashrc``, then this venv first on PATH, the graph's settings again and our
    prompt, so a ``~/.bashrc`` that puts another Python first or sets its own ROS_DOMAIN_ID cannot take the shell
    out of the graph (``python`` there must have rclpy and the package)."""
    keep = {k: v for k, v in env.items() if _is_graph_key(k) or k == "VIRTUAL_ENV"}
    lines = ['if [ -f "$HOME/.bashrc" ]; then . "$HOME/.bashrc"; fi',
             f"export PATH={shlex.quote(str(Path(sys.executable).parent))}:\"$PATH\"",
             *(f"export {k}={shlex.quote(v)}" for k, v in sorted(keep.items())), "hash -r",
             f"PS1={shlex.quote(prompt())}"]
    return "\n".join(lines) + "\n"


def _rcfile(text: str) -> str:
    """``text`` readable as a file by the exec'd shell, in whatever mount namespace it runs: an inherited pipe,
    filled and closed here (no file left behind)."""
    read_fd, write_fd = os.pipe()
    os.write(write_fd, text.encode())  # a few hundred bytes: far below a pipe's buffer
    os.close(write_fd)
    os.set_inheritable(read_fd, True)
    return f"/proc/self/fd/{read_fd}"


def _exec(argv: list[str], verb: str) -> int:
    """Replace this process with ``argv`` inside the graph (its exit status is the verb's)."""
    try:
        graph = find_graph()
    except GraphError as exc:
        print(f"mds-ach {verb}: {exc}", file=sys.stderr)
        return 1
    if graph.join and shutil.which("nsenter") is None:
        print(f"mds-ach {verb}: nsenter (util-linux) is needed to enter the system's namespaces", file=sys.stderr)
        return 1
    env = environment(graph)
    if verb == "ros-shell":
        env["PS1"] = prompt(bash=False)  # sh and dash read it from the environment; bash's comes after ~/.bashrc
    if verb == "ros-shell" and Path(argv[0]).name == "bash":
        argv = [argv[0], "--rcfile", _rcfile(bash_rc(env)), *argv[1:]]
    full = command(graph, argv)
    if verb == "ros-shell":
        where = (f"namespaces ({', '.join(graph.join)}) of {graph.node}, pid {graph.pid}" if graph.join
                 else f"environment of {graph.node}, pid {graph.pid}")
        print(f"MDS-Ach ROS 2 graph: ROS_DOMAIN_ID={graph.domain_id}, the {where}. 'exit' leaves it.",
              file=sys.stderr, flush=True)
    try:
        os.execvpe(full[0], full, env)
    except OSError as exc:
        print(f"mds-ach {verb}: cannot run {full[0]}: {exc.strerror}", file=sys.stderr)
        return 127 if isinstance(exc, FileNotFoundError) else 126
    return 0  # not reached


def add_shell_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("An interactive shell inside the running system's ROS 2 graph: its network (and user/mount) "
                     "namespaces and its ROS_DOMAIN_ID, discovery and DDS settings, with this venv first on PATH. "
                     "The system is found through the pid files in the runtime directory ($MDS_ACH_RUNTIME_DIR).")
    p.add_argument("--shell", default=None, help="the shell to run (default $SHELL, else /bin/bash)")


def run_shell(args: argparse.Namespace) -> int:
    shell = args.shell or os.environ.get("SHELL") or "/bin/bash"
    if Path(shell).name in ("nologin", "false"):
        shell = "/bin/sh"
    return _exec([shell, "-i"], "ros-shell")


TOPIC_VERBS = ("topics", "echo", "hz")  # mds_ach.tools.rostopic: what `ros2 topic` would do, on rclpy alone


def add_ros_arguments(p: argparse.ArgumentParser) -> None:
    p.description = ("Run one command inside the running system's ROS 2 graph (see 'mds-ach ros-shell'), e.g. "
                     "'mds-ach ros python examples/ros_joint_state_subscriber.py --count 5'. Its exit status is "
                     "the command's. Built in, for a ROS without the ros2 command line (pip): 'mds-ach ros topics' "
                     "(every topic, type, publishers and subscribers), 'mds-ach ros echo TOPIC [-n N]' (messages as "
                     "YAML), 'mds-ach ros hz TOPIC [--duration S]' (its rate); relative names are the system's "
                     "(its --namespace), '--help' after the verb for its options.")
    p.add_argument("command", nargs=argparse.REMAINDER, metavar="CMD [ARGS...]", help="the command and its arguments")


def run_ros(args: argparse.Namespace) -> int:
    argv = list(args.command)
    if argv[:1] == ["--"]:
        argv = argv[1:]
    if not argv:
        print("mds-ach ros: give a command, e.g. 'mds-ach ros python examples/ros_joint_state_subscriber.py' "
              "or 'mds-ach ros topics' (or 'mds-ach ros-shell' for a shell)", file=sys.stderr)
        return 2
    if argv[0] in TOPIC_VERBS or argv[0] == "--namespace":
        argv = topic_command(argv)
    return _exec(argv, "ros")


def topic_command(argv: list[str]) -> list[str]:
    """``mds-ach ros topics|echo|hz ...`` as the command run in the graph: this interpreter's
    ``mds_ach.tools.rostopic``, relative names resolved in the running system's namespace (unless given)."""
    from mds_ach.tools.launcher import recorded_namespace

    if "--namespace" not in argv:
        argv = ["--namespace", recorded_namespace() or "/", *argv]
    return [sys.executable, "-m", "mds_ach.tools.rostopic", *argv]
