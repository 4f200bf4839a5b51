"""Simulated machines for network tests and benchmarks: namespaces joined by a veth pair.

A :class:`Host` is a network namespace (only ``lo`` at first) plus a mount namespace with its own tmpfs
``/dev/shm`` (so its Ach channels are its own) and ``/run`` (so an sshd can have ``/run/sshd``). It is
held open by a ``sleep`` process; commands enter it with ``nsenter``. Everything disappears with that
process: the veth end inside, the mounts, the namespaces. Needs root, and refuses to run outside a
private namespace (``tools/netns-run``), so no interface is ever added to the real host.
"""

from __future__ import annotations

import os
import pwd
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Sequence
from pathlib import Path

from . import other_ids_missing

HOLD_S = 900  # a forgotten host removes itself after this long


def _require_private_namespace() -> None:
    if os.geteuid() != 0:
        raise RuntimeError("simulated hosts need root (network and mount namespaces, veth pairs)")
    if os.environ.get("MDS_NETNS_ACTIVE") != "1":
        raise RuntimeError("simulated hosts are made only inside tools/netns-run (a private network namespace)")


def _ip(*args: str, argv_prefix: Sequence[str] = ()) -> None:
    cmd = [*argv_prefix, "ip", *args]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=10)
    if result.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {result.stderr.strip()}")


class Host:
    """One simulated machine. ``argv(cmd)`` runs ``cmd`` inside it; ``close()`` (or ``with``) ends it."""

    def __init__(self, name: str) -> None:
        _require_private_namespace()
        self.name = name
        script = (
            "mount -t tmpfs -o mode=1777 tmpfs /dev/shm && mount -t tmpfs -o mode=755 tmpfs /run && "
            "mkdir -p -m 755 /run/sshd && mkdir -p -m 1777 /run/lock && ip link set lo up && "
            f"echo ready && exec sleep {HOLD_S}"
        )
        self._proc = subprocess.Popen(
            ["unshare", "-n", "-m", "--propagation", "private", "sh", "-c", script],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        assert self._proc.stdout is not None
        line = self._proc.stdout.readline().strip()
        if line != "ready":
            self._proc.kill()
            err = self._proc.communicate(timeout=5)[1]
            raise RuntimeError(f"cannot create simulated host {name}: {err.strip() or line}")
        self.pid = self._proc.pid

    def argv(self, cmd: Sequence[str]) -> list[str]:
        """``cmd`` run inside this host, in the caller's current directory."""
        return ["nsenter", "-t", str(self.pid), "-m", "-n", f"--wd={os.getcwd()}", "--", *cmd]

    def run(self, cmd: Sequence[str], **kwargs) -> subprocess.CompletedProcess:
        kwargs.setdefault("timeout", 30)
        return subprocess.run(self.argv(cmd), **kwargs)

    def popen(self, cmd: Sequence[str], **kwargs) -> subprocess.Popen:
        return subprocess.Popen(self.argv(cmd), **kwargs)

    def close(self) -> None:
        if self._proc.poll() is None:
            self._proc.send_signal(signal.SIGKILL)
        self._proc.wait(timeout=10)

    def __enter__(self) -> Host:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Veth:
    """A veth pair: ``local`` end in this process's namespace (or in ``host_a``), ``peer`` end in ``host_b``."""

    def __init__(
        self, name: str, host_b: Host, addr_a: str, addr_b: str, prefix: int = 24, host_a: Host | None = None
    ) -> None:
        _require_private_namespace()
        self.local = f"{name}a"
        self.peer = f"{name}b"
        self.host_a = host_a
        self.host_b = host_b
        self.addr_a = addr_a
        self.addr_b = addr_b
        _ip("link", "add", self.local, "type", "veth", "peer", "name", self.peer)
        _ip("link", "set", self.peer, "netns", str(host_b.pid))
        if host_a is not None:
            _ip("link", "set", self.local, "netns", str(host_a.pid))
        _ip("addr", "add", f"{addr_a}/{prefix}", "dev", self.local, argv_prefix=self._prefix_a())
        _ip("link", "set", self.local, "up", argv_prefix=self._prefix_a())
        _ip("addr", "add", f"{addr_b}/{prefix}", "dev", self.peer, argv_prefix=host_b.argv([]))
        _ip("link", "set", self.peer, "up", argv_prefix=host_b.argv([]))

    def _prefix_a(self) -> list[str]:
        return self.host_a.argv([]) if self.host_a is not None else []

    def down(self) -> None:
        """Cut the link (the ``a`` end goes down, as if its cable were pulled)."""
        _ip("link", "set", self.local, "down", argv_prefix=self._prefix_a())

    def up(self) -> None:
        _ip("link", "set", self.local, "up", argv_prefix=self._prefix_a())

    def close(self) -> None:
        """Delete the pair (it also disappears when host_b ends)."""
        subprocess.run([*self._prefix_a(), "ip", "link", "del", self.local], capture_output=True, timeout=10)


SSHD = "/usr/sbin/sshd"


class Sshd:
    """A real OpenSSH server inside ``host``: key-only, its own host key, one authorized client key.

    ``identity`` (client private key) and ``known_hosts`` (the server's host key for ``address``) are
    what an operator needs for ``mds-ach remote --ssh``. The client key may only forward to
    ``permit_open`` (``host:port``): no shell, no other forwards.
    """

    def __init__(self, host: Host, address: str, workdir: Path, permit_open: str, port: int = 22) -> None:
        if not (os.path.exists(SSHD) and shutil.which("ssh") and shutil.which("ssh-keygen")):
            raise RuntimeError("OpenSSH is missing: install the Debian packages openssh-server and openssh-client "
                               "(apt-get install openssh-server openssh-client)")
        self.dir = workdir
        self.address = address
        self.port = port
        for key in ("host_key", "client_key"):
            subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(workdir / key)],
                           check=True, timeout=30, capture_output=True)
        self.identity = workdir / "client_key"
        self.known_hosts = workdir / "known_hosts"
        host_pub = " ".join((workdir / "host_key.pub").read_text().split()[:2])
        where = address if port == 22 else f"[{address}]:{port}"
        self.known_hosts.write_text(f"{where} {host_pub}\n")
        (workdir / "authorized_keys").write_text(
            f'restrict,port-forwarding,permitopen="{permit_open}" ' + (workdir / "client_key.pub").read_text()
        )
        config = workdir / "sshd_config"
        config.write_text(
            f"ListenAddress {address}\nPort {port}\nHostKey {workdir / 'host_key'}\n"
            f"AuthorizedKeysFile {workdir / 'authorized_keys'}\nPidFile {workdir / 'sshd.pid'}\n"
            "PermitRootLogin prohibit-password\nPasswordAuthentication no\nKbdInteractiveAuthentication no\n"
            "UsePAM no\nStrictModes no\nAllowTcpForwarding local\nX11Forwarding no\nAllowAgentForwarding no\n"
            "PermitTunnel no\nLogLevel VERBOSE\n"
        )
        if not os.access("/etc/shadow", os.R_OK):
            # Rootless (tools/netns-run's user namespace): the machine's shadow file belongs to an id not mapped here,
            # and sshd takes an account it cannot look up there for a locked one. The simulated robot gets a shadow
            # database of its own (in its mount namespace only): root without a password, key-only as configured.
            shadow = workdir / "shadow"
            shadow.write_text("root:*:19000:0:99999:7:::\n")
            shadow.chmod(0o600)
            host.run(["mount", "--bind", str(shadow), "/etc/shadow"], check=True, capture_output=True)
        self.log = workdir / "sshd.log"
        with open(self.log, "wb") as logf:
            self.proc = host.popen([SSHD, "-D", "-e", "-f", str(config)], stdout=logf, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 20
        while not reachable(address, port):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.close()
                raise RuntimeError(f"sshd did not start:\n{self.log.read_text()[-2000:]}")
            time.sleep(0.05)

    @staticmethod
    def missing_ids() -> str | None:
        """Why sshd cannot run here, or None: its privilege separation switches to user sshd (setgroups, setuid),
        which a user namespace of tools/netns-run maps only with the user's subordinate ids."""
        try:
            user = pwd.getpwnam("sshd")
        except KeyError:
            return None  # not installed: __init__ says how to get it
        return other_ids_missing((user.pw_uid,), (user.pw_gid,))

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)


def reachable(address: str, port: int) -> bool:
    try:
        with socket.create_connection((address, port), timeout=0.5):
            return True
    except OSError:
        return False
