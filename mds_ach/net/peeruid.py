"""Which local user is at the other end of a loopback TCP connection (Linux: ``/proc/net/tcp``, ``tcp6``).

The network server gives each local user a pool of its own (issue 25): the robot's tools and every operator
coming through an SSH tunnel all connect from loopback, so the address tells them apart no more. The kernel does:
the peer's socket, whose local address is the peer address the server accepted and whose remote address is the
server's, is listed with the uid that created it. For an SSH tunnel that is the operator's own user (sshd's
forwarding child runs as the user who logged in), so another local user cannot use up the operator's slots.
Stdlib only.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Sequence
from pathlib import Path
from typing import Any

TABLES: tuple[str, ...] = ("/proc/net/tcp", "/proc/net/tcp6")
"""The kernel's TCP socket tables of this network namespace (IPv4, IPv6)."""
ESTABLISHED = "01"
"""The ``st`` column of a connected socket (a closed one in TIME_WAIT may have had the same addresses)."""

Address = tuple[ipaddress.IPv4Address | ipaddress.IPv6Address, int]


def _plain(host: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address:
    """``host`` as an address; an IPv4-mapped IPv6 address as the IPv4 one (the tables list either form)."""
    address = ipaddress.ip_address(host.split("%", 1)[0])
    mapped = getattr(address, "ipv4_mapped", None)
    return mapped if mapped is not None else address


def parse_address(field: str) -> Address:
    """One ``ADDR:PORT`` column: the address as the kernel's 32-bit words in host (little-endian) order, the port
    big-endian hex. ``ValueError`` if it is not one."""
    host, port = field.split(":")
    raw = bytes.fromhex(host)
    if len(raw) == 4:
        address: ipaddress.IPv4Address | ipaddress.IPv6Address = ipaddress.IPv4Address(raw[::-1])
    elif len(raw) == 16:
        address = ipaddress.IPv6Address(b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4)))
    else:
        raise ValueError(f"not a socket address: {field!r}")
    mapped = getattr(address, "ipv4_mapped", None)
    return (mapped if mapped is not None else address), int(port, 16)


def peer_uid(peer: Sequence[Any], server: Sequence[Any], tables: Sequence[str] = TABLES) -> int | None:
    """The uid owning the connected socket at ``peer`` (host, port) whose other end is ``server`` (host, port): the
    user who opened a connection this machine's server accepted. None when no table lists it (the peer closed
    already, not Linux, or ``/proc`` is not mounted)."""
    want = ((_plain(str(peer[0])), int(peer[1])), (_plain(str(server[0])), int(server[1])))
    for table in tables:
        try:
            lines = Path(table).read_text(encoding="ascii", errors="replace").splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) < 8 or fields[3] != ESTABLISHED:
                continue
            try:
                if (parse_address(fields[1]), parse_address(fields[2])) == want:
                    return int(fields[7])
            except ValueError:
                continue
    return None
