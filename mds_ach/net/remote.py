"""``mds-ach remote``: run the robot from an operator station over the network (achd protocol).

Operator station: ``mds-ach remote HOST`` pushes the local reference path (``mds-ref-filter``, the input
of the mux's default controller) to the robot's ``mds-ref-filter`` -- so remote references still pass the
mux, smoothing filter and collision gate (a station running the original ``achd push mds-ref`` works too:
``mds-ref`` is the mux's ``direct`` input here, gated like the rest) --
and pulls ``mds-state`` (UDP by default), ``mds-param`` and ``mds-collide`` (TCP) into local channels of
the same names. It runs in the background (pid and log in the runtime directory) until
``mds-ach remote kill``.

Robot: ``mds-ach remote serve`` listens (loopback by default) and only lets clients write the pipeline
inputs and read the state channels.

Secure mode: ``mds-ach remote --ssh user@robot`` carries every stream through an OpenSSH tunnel
(``-L`` forward to the robot's loopback server; BatchMode, StrictHostKeyChecking=yes, key
authentication only), so the robot's server never listens on the network. UDP cannot pass a TCP tunnel,
so the state stream uses TCP there.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import mds_ach as mds
from mds_ach import procs as background
from mds_ach.argtypes import bounded, port, seconds
from mds_ach.net import achd
from mds_ach.net import protocol as ap
from mds_ach.paths import runtime_dir
from mds_ach.robot import contracts
from mds_ach.robot.channels import make_channels

log = logging.getLogger("mds_ach.net.remote")

# What the robot side lets the network read (everything an operator monitors) and write (the safe inputs).
ROBOT_READABLE: tuple[str, ...] = contracts.REMOTE_READABLE
ROBOT_WRITABLE: tuple[str, ...] = contracts.REMOTE_WRITABLE
STATUS_PERIOD_S = 0.5
SSH_RESTART_S = 1.0


def _rt() -> Path:
    path = runtime_dir()
    path.mkdir(parents=True, exist_ok=True)
    return path


def _files(role: str) -> tuple[Path, Path, Path]:
    """pid, log and status file of the operator session (``remote``) or a robot server (``remote-serve``)."""
    rt = _rt()
    return rt / f"{role}.pid", rt / f"{role}.log", rt / f"{role}.status.json"


def _serve_role(port: int) -> str:
    """One set of files per server port, so two servers (e.g. LAN and loopback-only) can run side by side."""
    return "remote-serve" if port == ap.ACHD_PORT else f"remote-serve-{port}"


def _roles() -> list[str]:
    return ["remote"] + sorted(p.name[: -len(".pid")] for p in _rt().glob("remote-serve*.pid"))


# --------------------------------------------------------------------------------------------------
# SSH tunnel
# --------------------------------------------------------------------------------------------------


def free_local_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


_HOST = re.compile(r"[A-Za-z0-9_.:%\[\]-]{1,253}")
_USER = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,31}")


def destination_problem(destination: str, *, ssh: bool) -> str | None:
    """Why ``destination`` (HOST, or USER@HOST with ``ssh``) is not one, or None. A host starting with '-' would
    be read by ssh as an option (``-oProxyCommand=...`` runs a command): refused here, and the tunnel passes
    ``--`` before the destination as well."""
    user, at, host = destination.rpartition("@")
    if ssh and (not at or not _USER.fullmatch(user)):
        return f"--ssh wants USER@HOST (user: letters, digits, '_', '.', '-'), got {destination[:80]!r}"
    if not ssh and at:
        return f"HOST {destination[:80]!r} has a user: give it as --ssh USER@HOST"
    if host.startswith("-") or not _HOST.fullmatch(host):
        return (f"invalid host {host[:80]!r}: a name or address of at most 253 letters, digits, '.', '-', ':' "
                "(and not starting with '-')")
    return None


class SshTunnel:
    """``ssh -N -L 127.0.0.1:LOCAL:127.0.0.1:REMOTE user@host``, restarted whenever it exits.

    Only the system OpenSSH client is used: BatchMode (never a password prompt), StrictHostKeyChecking=yes
    (an unknown or changed host key is an error, never accepted), keepalives so a dead link ends the
    session and the tunnel is rebuilt.
    """

    def __init__(
        self,
        destination: str,
        remote_port: int = ap.ACHD_PORT,
        *,
        identity: str | None = None,
        known_hosts: str | None = None,
        ssh_port: int | None = None,
        options: tuple[str, ...] = (),
        ssh: str = "ssh",
    ) -> None:
        problem = destination_problem(destination, ssh=True)
        if problem:
            raise ValueError(problem)
        self.destination = destination
        self.remote_port = remote_port
        self.identity = identity
        self.known_hosts = known_hosts
        self.ssh_port = ssh_port
        self.options = options
        self.ssh = ssh
        self.local_port = free_local_port()
        self.starts = 0
        self.stderr_tail: deque[str] = deque(maxlen=20)
        self._proc: subprocess.Popen | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def command(self) -> list[str]:
        cmd = [
            self.ssh, "-N", "-T",
            "-o", "BatchMode=yes",
            "-o", "StrictHostKeyChecking=yes",
            "-o", "PasswordAuthentication=no",
            "-o", "KbdInteractiveAuthentication=no",
            "-o", "ExitOnForwardFailure=yes",
            "-o", "ServerAliveInterval=2",
            "-o", "ServerAliveCountMax=3",
            "-o", "ConnectTimeout=5",
            "-L", f"127.0.0.1:{self.local_port}:127.0.0.1:{self.remote_port}",
        ]
        if self.identity:
            cmd += ["-i", self.identity, "-o", "IdentitiesOnly=yes"]
        if self.known_hosts:
            cmd += ["-o", f"UserKnownHostsFile={self.known_hosts}", "-o", "GlobalKnownHostsFile=/dev/null"]
        if self.ssh_port:
            cmd += ["-p", str(self.ssh_port)]
        for opt in self.options:
            cmd += ["-o", opt]
        return cmd + ["--", self.destination]

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def start(self) -> SshTunnel:
        self._thread = threading.Thread(target=self._supervise, name="ssh tunnel", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(3.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(3.0)
        if self._thread is not None:
            self._thread.join(5.0)

    def _supervise(self) -> None:
        while not self._stop.is_set():
            t0 = time.monotonic()
            try:
                self._proc = subprocess.Popen(
                    self.command(), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                    text=True, errors="replace",
                )
            except OSError as exc:
                self.stderr_tail.append(f"cannot run {self.ssh}: {exc}")
                self._stop.wait(SSH_RESTART_S)
                continue
            self.starts += 1
            reader = threading.Thread(target=self._read_stderr, args=(self._proc,), daemon=True)
            reader.start()
            while self._proc.poll() is None and not self._stop.is_set():
                self._stop.wait(achd.POLL_S)
            if self._stop.is_set():
                break
            reader.join(1.0)
            log.warning("ssh tunnel exited (%s): %s", self._proc.returncode, " | ".join(self.stderr_tail) or "-")
            self._stop.wait(max(0.0, t0 + SSH_RESTART_S - time.monotonic()))

    def _read_stderr(self, proc: subprocess.Popen) -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            line = line.strip()
            if line:
                self.stderr_tail.append(line)


# --------------------------------------------------------------------------------------------------
# Operator session
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LinkPlan:
    mode: str  # push | pull (our side)
    local: str
    remote: str
    transport: str


def plan_links(args: argparse.Namespace) -> list[LinkPlan]:
    """The streams an operator station needs, as the original's ``remote`` verb, but into the safe input."""
    state_transport = args.state_transport or ("tcp" if args.ssh else "udp")
    plans = [LinkPlan("push", args.ref_channel, args.remote_ref_channel, "tcp")]
    if args.with_ik:
        plans.append(LinkPlan("push", mds.MDS_CHAN_IK_NAME, mds.MDS_CHAN_IK_NAME, "tcp"))
    plans += [
        LinkPlan("pull", mds.MDS_CHAN_STATE_NAME, mds.MDS_CHAN_STATE_NAME, state_transport),
        LinkPlan("pull", mds.MDS_CHAN_PARAM_NAME, mds.MDS_CHAN_PARAM_NAME, "tcp"),
        LinkPlan("pull", mds.MDS_CHAN_COLLIDE_NAME, mds.MDS_CHAN_COLLIDE_NAME, "tcp"),
    ]
    return plans


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def run_session(args: argparse.Namespace, stop: threading.Event) -> int:
    """Foreground operator session: tunnel (if any), links, a status file every half second, until ``stop``."""
    for report in make_channels():
        if not report.ok:
            print(f"mds-ach remote: local channel {report.name}: {report.detail}", file=sys.stderr)
            return 1
    tunnel = None
    host, port = args.host, args.port
    if args.ssh:
        tunnel = SshTunnel(
            args.ssh, args.port, identity=args.ssh_identity, known_hosts=args.ssh_known_hosts,
            ssh_port=args.ssh_port, options=tuple(args.ssh_option or ()),
        ).start()
        host, port = "127.0.0.1", tunnel.local_port
    links = [
        achd.Link(
            p.mode, host, p.local, remote_channel=p.remote, port=port, transport=p.transport, get_last=True,
            period_ns=int(args.state_period_ms * 1e6) if p.local == mds.MDS_CHAN_STATE_NAME else 0,
            reconnect=True, dead_after_s=args.dead_after,
        ).start()
        for p in plan_links(args)
    ]
    _, _, status_path = _files("remote")
    try:
        while not stop.wait(STATUS_PERIOD_S):
            _write_json(status_path, _session_status(args, links, tunnel))
    finally:
        for link in links:
            link.stop()
        for link in links:
            link.join(3.0)
        if tunnel is not None:
            tunnel.stop()
        _write_json(status_path, _session_status(args, links, tunnel) | {"stopped": True})
    return 0


def _session_status(args: argparse.Namespace, links: list[achd.Link], tunnel: SshTunnel | None) -> dict:
    return {
        "pid": os.getpid(),
        "host": args.ssh or args.host,
        "ssh": bool(args.ssh),
        "tunnel": None if tunnel is None else {
            "running": tunnel.running, "starts": tunnel.starts, "local_port": tunnel.local_port,
            "stderr": list(tunnel.stderr_tail)[-3:],
        },
        "links": [
            {"name": link.name, "connected": link.connected.is_set()} | link.stats.as_dict() for link in links
        ],
        "time": time.time(),
    }


# --------------------------------------------------------------------------------------------------
# Background process, pid files, kill
# --------------------------------------------------------------------------------------------------


def read_pid(pid_path: Path) -> int | None:
    """The pid in ``pid_path`` if that process still runs this module (a reused pid is never trusted)."""
    return background.running_pid(pid_path, lambda argv: "mds_ach.net.remote" in argv)


def _child_argv(argv: list[str]) -> list[str]:
    return [sys.executable, "-m", "mds_ach.net.remote", *argv, "--foreground"]


def _spawn(role: str, argv: list[str], ready, wait_s: float) -> int:
    """Start this verb again in the background, then wait until ``ready(status)`` or fail with the log."""
    pid_path, log_path, status_path = _files(role)
    running = read_pid(pid_path)
    if running is not None:
        print(f"mds-ach remote: already running (pid {running}); stop it with 'mds-ach remote kill'", file=sys.stderr)
        return 1
    status_path.unlink(missing_ok=True)
    proc = background.spawn_detached(_child_argv(argv), log_path)
    background.write_pid_file(pid_path, proc.pid)
    deadline = time.monotonic() + wait_s
    status: dict = {}
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                status = json.loads(status_path.read_text())
            except (OSError, ValueError):
                status = {}
            if status and ready(status):
                break
            time.sleep(0.1)
    except BaseException:  # Ctrl-C, a closed pipe...: never leave a half-started child behind
        _stop_pid(proc.pid)
        proc.wait()
        pid_path.unlink(missing_ok=True)
        raise
    if status and ready(status) and proc.poll() is None:
        print(f"mds-ach remote: running in the background (pid {proc.pid}, log {log_path})")
        for link in status.get("links", []):
            print(f"  {link['name']}: connected")
        return 0
    why = "exited" if proc.poll() is not None else f"not ready after {wait_s:.0f} s"
    _stop_pid(proc.pid)  # first, so nothing below can leave it running
    proc.wait()
    pid_path.unlink(missing_ok=True)
    print(f"mds-ach remote: {why}", file=sys.stderr)
    for link in status.get("links", []):
        if not link.get("connected"):
            print(f"  {link['name']}: NOT connected ({link.get('last_error') or 'no answer'})", file=sys.stderr)
    if status.get("tunnel") and status["tunnel"].get("stderr"):
        print("  ssh: " + " | ".join(status["tunnel"]["stderr"]), file=sys.stderr)
    tail = background.log_tail(log_path, 15)
    if tail:
        print(f"last lines of {log_path}:\n" + "\n".join(tail), file=sys.stderr)
    return 1


def _stop_pid(pid: int, grace_s: float = 5.0) -> None:
    background.stop_pid(pid, grace_s)


def kill_all() -> int:
    """Stop the operator session and a background robot server started from this runtime directory."""
    stopped = 0
    for role in _roles():
        pid_path, _, _ = _files(role)
        pid = read_pid(pid_path)
        if pid is not None:
            _stop_pid(pid)
            print(f"mds-ach remote: stopped {role} (pid {pid})")
            stopped += 1
        pid_path.unlink(missing_ok=True)
    if not stopped:
        print("mds-ach remote: nothing running")
    return 0


def show_status() -> int:
    found = False
    for role in _roles():
        pid_path, _, status_path = _files(role)
        pid = read_pid(pid_path)
        if pid is None:
            continue
        found = True
        try:
            status = json.loads(status_path.read_text())
        except (OSError, ValueError):
            status = {}
        print(f"{role}: pid {pid}")
        for link in status.get("links", []):
            state = "connected" if link.get("connected") else "DOWN"
            print(
                f"  {link['name']}: {state}, sent {link['sent']}, written {link['written']}, dropped "
                f"{link['dropped_size']} size / {link['dropped_invalid']} invalid"
                + (f", last error: {link['last_error']}" if link.get("last_error") else "")
            )
        for key, link in status.get("served", {}).items():
            print(f"  {key}: sent {link['sent']}, written {link['written']}, dropped "
                  f"{link['dropped_size']} size / {link['dropped_invalid']} invalid")
    if not found:
        print("mds-ach remote: nothing running")
    return 0


# --------------------------------------------------------------------------------------------------
# Robot side: serve
# --------------------------------------------------------------------------------------------------


def run_serve(args: argparse.Namespace, stop: threading.Event) -> int:
    binds = tuple(args.bind or ("127.0.0.1",))
    policy = achd.AccessPolicy(
        readable=tuple(args.allow_read or ROBOT_READABLE), writable=tuple(args.allow_write or ROBOT_WRITABLE)
    )
    exposed = [b for b in binds if b not in ("127.0.0.1", "::1", "localhost")]
    if exposed:
        log.warning(
            "listening on %s: anyone who reaches it can write %s; on untrusted networks serve on loopback "
            "and use 'mds-ach remote --ssh'", ", ".join(exposed), ", ".join(policy.writable),
        )
    risky = [c for c in policy.writable if c in (mds.MDS_CHAN_DAEMON_INPUT_NAME, mds.MDS_CHAN_BOARD_CMD_NAME)]
    if risky:
        log.warning("clients may write %s: that bypasses the mux, filter and collision gate", ", ".join(risky))
    try:
        server = achd.Server(binds, args.port, policy=policy, dead_after_s=args.dead_after,
                             send_latest_on_connect=args.newest_on_connect, **achd.server_limits(args)).start()
    except ValueError as exc:
        print(f"mds-ach remote serve: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"mds-ach remote serve: {exc.strerror or exc}", file=sys.stderr)
        return 1
    print(f"mds-ach remote serve: listening on {', '.join(binds)} port {args.port}", flush=True)
    _, _, status_path = _files(_serve_role(args.port))
    try:
        while not stop.wait(STATUS_PERIOD_S):
            served = {k: v.as_dict() for k, v in list(server.stats.items())[-32:]}
            _write_json(status_path, {"pid": os.getpid(), "listening": True, "served": served,
                                      "refused": server.refused, "time": time.time()})
    finally:
        server.stop()
        server.join()
    return 0


# --------------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------------


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = (
        "examples:\n"
        "  robot:     mds-ach remote serve                   (loopback only: for --ssh)\n"
        "  robot:     mds-ach remote serve --bind 10.0.0.2   (plain network: trusted LAN only)\n"
        "  operator:  mds-ach remote 10.0.0.2\n"
        "  operator:  mds-ach remote --ssh mds@robot --ssh-identity ~/.ssh/mds_ed25519\n"
        "  operator:  mds-ach remote status | mds-ach remote kill\n"
        "References written locally to mds-ref-filter (console goto, examples) reach the robot's\n"
        "mds-ref-filter and pass its mux, filter and collision gate; mds-state, mds-param and\n"
        "mds-collide arrive in the local channels of the same names."
    )
    p.add_argument("target", nargs="?", metavar="HOST|serve|kill|status",
                   help="robot host to connect to, or serve (robot side), kill, status")
    p.add_argument("--port", type=port(), default=ap.ACHD_PORT, help="achd TCP port (default 8076)")
    p.add_argument("--ssh", metavar="USER@HOST", help="secure mode: carry every stream through an SSH tunnel")
    p.add_argument("--ssh-identity", metavar="FILE", help="private key for --ssh (pre-shared key)")
    p.add_argument("--ssh-known-hosts", metavar="FILE", help="known_hosts holding the robot's host key")
    p.add_argument("--ssh-port", type=port(), help="sshd port on the robot (default 22)")
    p.add_argument("--ssh-option", action="append", metavar="OPT", help="extra ssh -o option (repeatable)")
    p.add_argument("--state-transport", choices=ap.TRANSPORTS,
                   help="transport of mds-state (default udp; tcp with --ssh)")
    p.add_argument("--state-period-ms", type=bounded(0.0, 60_000.0, unit="ms"), default=0.0,
                   help="send mds-state at most this often")
    p.add_argument("--ref-channel", default=mds.MDS_CHAN_REF_FILTER_NAME,
                   help="local channel whose references are pushed (default mds-ref-filter)")
    p.add_argument("--remote-ref-channel", default=mds.MDS_CHAN_REF_FILTER_NAME,
                   help="robot channel receiving them (default mds-ref-filter, the mux's default input)")
    p.add_argument("--with-ik", action="store_true", help="also push mds-ik (IK requests)")
    p.add_argument("--dead-after", type=seconds(), default=5.0, help="seconds of silence before a link is redone")
    p.add_argument("--wait", type=seconds(), default=15.0, help="seconds to wait for every link at start")
    p.add_argument("--foreground", action="store_true", help="stay in the foreground (Ctrl-C stops)")
    p.add_argument("--bind", action="append", metavar="ADDR", help="serve: listen address (default 127.0.0.1)")
    p.add_argument("--allow-write", action="append", metavar="CHAN",
                   help=f"serve: channels clients may write (default {', '.join(ROBOT_WRITABLE)})")
    p.add_argument("--allow-read", action="append", metavar="CHAN",
                   help="serve: channels clients may read (default the state channels)")
    p.add_argument("--background", action="store_true", help="serve: run in the background")
    achd.add_server_limit_arguments(p, "serve: ")
    achd.add_connect_start_arguments(p, "serve: ")


def _check(args: argparse.Namespace) -> str | None:
    """A usage problem, or None."""
    if args.state_transport == "udp" and args.ssh:
        return "UDP cannot pass an SSH tunnel; leave --state-transport out (tcp) with --ssh"
    if args.ssh:
        problem = destination_problem(args.ssh, ssh=True)
        if problem:
            return problem
    elif args.target not in (None, "serve", "kill", "status"):
        problem = destination_problem(args.target, ssh=False)
        if problem:
            return problem
    for name in (args.ref_channel, args.remote_ref_channel):
        if not ap.valid_channel_name(name):
            return f"invalid channel name {name!r}"
        if achd.rule_for(name).ctype is not mds.MDS_REF:
            return f"{name} is not a reference channel"
    return None


def run(args: argparse.Namespace) -> int:
    """Handler of ``mds-ach remote``."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    target = args.target
    if target == "kill":
        return kill_all()
    if target == "status":
        return show_status()
    problem = _check(args)
    if problem:
        print(f"mds-ach remote: {problem}", file=sys.stderr)
        return 2
    if target == "serve":
        if args.background and not args.foreground:
            return _spawn(_serve_role(args.port), _serve_argv(args), lambda s: s.get("listening"), args.wait)
        return _foreground(run_serve, args)
    if args.ssh:
        args.host = args.ssh.split("@", 1)[1]
        if target and target != args.host:
            print(f"mds-ach remote: HOST {target!r} differs from the --ssh host {args.host!r}", file=sys.stderr)
            return 2
    elif not target:
        print("mds-ach remote: give the robot's HOST (or serve, kill, status); see --help", file=sys.stderr)
        return 2
    else:
        args.host = target
    if is_this_machine(args.host):
        print(f"mds-ach remote: {args.host} is this machine; bridging its channels into themselves would loop "
              "(run 'mds-ach remote HOST' on the operator station, 'mds-ach remote serve' here)", file=sys.stderr)
        return 2
    if args.foreground:
        return _foreground(run_session, args)
    return _spawn(
        "remote", _session_argv(args),
        lambda s: bool(s.get("links")) and all(link["connected"] for link in s["links"]), args.wait,
    )


def is_this_machine(host: str) -> bool:
    """Does ``host`` resolve to an address of this machine? (Only a local address can be bound.)"""
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_DGRAM)
    except OSError:
        return False
    for family, _, _, _, sockaddr in infos:
        with socket.socket(family, socket.SOCK_DGRAM) as s:
            try:
                s.bind((sockaddr[0], 0))
                return True
            except OSError:
                continue
    return False


def _foreground(func, args: argparse.Namespace) -> int:
    stop = threading.Event()
    achd.install_stop_signals(stop.set)
    try:
        return func(args, stop)
    except KeyboardInterrupt:
        stop.set()
        return 0


def _common_argv(args: argparse.Namespace) -> list[str]:
    return ["--port", str(args.port), "--dead-after", str(args.dead_after)]


def _serve_argv(args: argparse.Namespace) -> list[str]:
    argv = ["serve", *_common_argv(args), "--max-clients", str(args.max_clients), "--max-per-peer",
            str(args.max_per_peer), "--max-local", str(args.max_local), "--idle-timeout", str(args.idle_timeout)]
    for flag, values in (("--bind", args.bind), ("--allow-write", args.allow_write), ("--allow-read", args.allow_read)):
        for v in values or ():
            argv += [flag, v]
    if args.newest_on_connect:
        argv.append("--newest-on-connect")
    return argv


def _session_argv(args: argparse.Namespace) -> list[str]:
    argv = [args.target] if args.target else []
    argv += _common_argv(args)
    argv += ["--ref-channel", args.ref_channel, "--remote-ref-channel", args.remote_ref_channel,
             "--state-period-ms", str(args.state_period_ms)]
    if args.state_transport:
        argv += ["--state-transport", args.state_transport]
    if args.with_ik:
        argv.append("--with-ik")
    if args.ssh:
        argv += ["--ssh", args.ssh]
        for flag, value in (("--ssh-identity", args.ssh_identity), ("--ssh-known-hosts", args.ssh_known_hosts),
                            ("--ssh-port", args.ssh_port)):
            if value:
                argv += [flag, str(value)]
        for opt in args.ssh_option or ():
            argv += ["--ssh-option", opt]
    return argv


def main(argv: list[str] | None = None) -> int:
    """``python -m mds_ach.net.remote ...`` = ``mds-ach remote ...`` (the background process runs this)."""
    parser = argparse.ArgumentParser(prog="mds-ach remote", description=__doc__.split("\n\n")[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
