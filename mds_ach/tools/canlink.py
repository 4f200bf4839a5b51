"""The SocketCAN link of a real start: ``can0`` at 1 Mbit/s by default, brought up like the original did.

Why: the original ``mds-ach start``/``resetbus`` assumed ``can0`` and configured it (``OpenCan``: down, bitrate
1000000, sample-point 0.5, restart-ms 100, up) on every start, so labs never wrote a CAN configuration. Here:

* no python-can configuration at all (no ``--interface``, ``$CAN_INTERFACE``, ``~/.canrc``...) means SocketCAN
  ``can0`` at 1 Mbit/s (:func:`default_bus`);
* for a SocketCAN link, :func:`ensure_up` reads its state with ``ip -json -details link show`` and, when it is down
  or at another bitrate, configures it with ``ip link`` if this process may (``CAP_NET_ADMIN``); otherwise it says
  exactly which commands to run, and nothing is started;
* :func:`restart` is ``resetbus``'s part: down, configure, up (the kernel's CAN controller restart).

``ip`` is found on ``$PATH`` (the tests put a fake one there; this machine's kernel has no SocketCAN).
"""

from __future__ import annotations

import json
import shlex
import subprocess
from dataclasses import dataclass
from pathlib import Path

DEFAULT_CHANNEL = "can0"
DEFAULT_BITRATE = 1_000_000  # the MDS bus
CAP_NET_ADMIN = 12
LINK_FILE = "can-link"  # in the runtime dir: the SocketCAN link of the running system, for resetbus


class CanLinkError(RuntimeError):
    """The link cannot be used or configured; the message says what to do."""


@dataclass(frozen=True)
class LinkState:
    """What ``ip -json -details link show`` says about a CAN link."""

    up: bool
    bitrate: int | None
    can_state: str  # ERROR-ACTIVE, ERROR-PASSIVE, BUS-OFF, STOPPED, ... ('' when unknown)


def configure_commands(channel: str, bitrate: int) -> list[list[str]]:
    """The original's OpenCan, in ``ip`` commands: configure the (down) link, then bring it up."""
    return [["ip", "link", "set", channel, "type", "can", "bitrate", str(bitrate), "sample-point", "0.5",
             "restart-ms", "100"],
            ["ip", "link", "set", channel, "up"]]


def restart_commands(channel: str, bitrate: int) -> list[list[str]]:
    return [["ip", "link", "set", channel, "down"], *configure_commands(channel, bitrate)]


def as_text(commands: list[list[str]], sudo: bool = False) -> str:
    return " && ".join(("sudo " if sudo else "") + shlex.join(c) for c in commands)


def may_configure() -> bool:
    """Does this process hold CAP_NET_ADMIN (root, or granted), i.e. may it run ``ip link set``?"""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("CapEff:"):
                return bool(int(line.split()[1], 16) >> CAP_NET_ADMIN & 1)
    except (OSError, ValueError, IndexError):
        pass
    return False


def _run(cmd: list[str]) -> subprocess.CompletedProcess[str]:
    try:
        return subprocess.run(cmd, capture_output=True, text=True, timeout=10)
    except FileNotFoundError:
        raise CanLinkError("the 'ip' command (iproute2) is not installed: install it, or configure the CAN link "
                           "yourself") from None
    except subprocess.TimeoutExpired:
        raise CanLinkError(f"'{shlex.join(cmd)}' did not finish within 10 s") from None


def link_state(channel: str) -> LinkState:
    """The link's state; CanLinkError when it does not exist or ``ip`` cannot tell."""
    proc = _run(["ip", "-json", "-details", "link", "show", "dev", channel])
    if proc.returncode != 0:
        detail = proc.stderr.strip() or f"exit status {proc.returncode}"
        raise CanLinkError(f"CAN interface {channel} not found ({detail}): plug in the CAN adapter and load its "
                           f"driver, choose another interface (CAN_INTERFACE/CAN_CHANNEL, ~/.canrc), or use the "
                           f"simulated robot ('nocan')")
    try:
        info = json.loads(proc.stdout)[0]
        data = (info.get("linkinfo") or {}).get("info_data") or {}
        kind = (info.get("linkinfo") or {}).get("info_kind", "")
    except (ValueError, IndexError, AttributeError, TypeError):
        raise CanLinkError(f"cannot read the state of {channel} from 'ip -json -details link show': "
                           f"{proc.stdout.strip()[:200]!r}") from None
    if kind not in ("can", "vcan"):
        raise CanLinkError(f"{channel} is not a CAN interface (link kind {kind or 'unknown'!r})")
    up = "UP" in (info.get("flags") or [])
    bitrate = (data.get("bittiming") or {}).get("bitrate")
    return LinkState(up, int(bitrate) if bitrate else None, str(data.get("state", "")))


def _apply(commands: list[list[str]], why: str) -> None:
    if not may_configure():
        raise CanLinkError(f"{why}, and this user may not configure it (no CAP_NET_ADMIN). Run:\n  "
                           f"{as_text(commands, sudo=True)}\nthen start again")
    for cmd in commands:
        proc = _run(cmd)
        if proc.returncode != 0:
            raise CanLinkError(f"{why}; '{shlex.join(cmd)}' failed: {proc.stderr.strip() or proc.returncode}. "
                               f"Run as root:\n  {as_text(commands, sudo=True)}")


def ensure_up(channel: str = DEFAULT_CHANNEL, bitrate: int = DEFAULT_BITRATE) -> str:
    """Make ``channel`` a running CAN link at ``bitrate``; returns what was done, for the operator."""
    state = link_state(channel)
    if state.up and state.bitrate in (None, bitrate):
        return f"{channel} is up ({state.bitrate or '?'} bit/s{', ' + state.can_state if state.can_state else ''})"
    if state.up:
        commands = restart_commands(channel, bitrate)
        why = f"{channel} runs at {state.bitrate} bit/s, the MDS bus at {bitrate}"
    else:
        commands = configure_commands(channel, bitrate)
        why = f"{channel} is down"
    _apply(commands, why)
    return f"{channel} configured: {as_text(commands)}"


def restart(channel: str, bitrate: int = DEFAULT_BITRATE) -> str:
    """``resetbus``: down, configure, up (clears bus-off in the CAN controller)."""
    link_state(channel)
    commands = restart_commands(channel, bitrate)
    _apply(commands, f"restarting {channel}")
    return f"{channel} restarted: {as_text(commands)}"


def save_link(rt: Path, channel: str, bitrate: int) -> None:
    (rt / LINK_FILE).write_text(f"{channel} {bitrate}\n")


def saved_link(rt: Path) -> tuple[str, int] | None:
    """The SocketCAN link ``mds-ach start`` used, or None (simulated bus, another interface, none recorded)."""
    try:
        channel, bitrate = (rt / LINK_FILE).read_text().split()
        return channel, int(bitrate)
    except (OSError, ValueError):
        return None


def clear_link(rt: Path) -> None:
    (rt / LINK_FILE).unlink(missing_ok=True)
