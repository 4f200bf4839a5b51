"""Which local user is at the other end of a loopback TCP connection (Linux: sock_diag, else ``/proc/net/tcp{,6}``).

The network server gives each local user a pool of its own (issue 25): the robot's tools and every operator
coming through an SSH tunnel all connect from loopback, so the address tells them apart no more. The kernel does:
the peer's socket, whose local address is the peer address the server accepted and whose remote address is the
server's, is listed with the uid that created it. For an SSH tunnel that is the operator's own user (sshd's
forwarding child runs as the user who logged in), so another local user cannot use up the operator's slots.

The kernel is asked for that one socket over netlink (``NETLINK_SOCK_DIAG``, an exact lookup: constant time however
many sockets exist); the ``/proc`` tables, which the kernel writes out whole (about 20 ms per 1000 connections),
are the fallback. Stdlib only.
"""

from __future__ import annotations

import errno
import ipaddress
import socket
import struct
from collections.abc import Sequence
from pathlib import Path
from typing import Any

TABLES: tuple[str, ...] = ("/proc/net/tcp", "/proc/net/tcp6")
"""The kernel's TCP socket tables of this network namespace (IPv4, IPv6)."""
ESTABLISHED = "01"
"""The ``st`` column of a connected socket (a closed one in TIME_WAIT may have had the same addresses)."""

Address = tuple[ipaddress.IPv4Address | ipaddress.IPv6Address, int]

# linux/netlink.h, linux/sock_diag.h, linux/inet_diag.h
_NETLINK_SOCK_DIAG = 4
_SOCK_DIAG_BY_FAMILY = 20
_NLM_F_REQUEST = 1
_NLMSG_ERROR = 2
_NLMSG = struct.Struct("=IHHII")  # nlmsghdr: length, type, flags, seq, pid
_REQ = struct.Struct("=BBBxI2s2s16s16sIII")  # inet_diag_req_v2: family, protocol, ext, states, inet_diag_sockid
_MSG = struct.Struct("=BBBB2s2s16s16sIIIIIIII")  # inet_diag_msg up to idiag_uid, idiag_inode
_NOCOOKIE = 0xFFFFFFFF
_ALL_STATES = 0xFFFFFFFF


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


def _fields(address: ipaddress.IPv4Address | ipaddress.IPv6Address, port: int) -> dict[str, str]:
    """``{table: "ADDR:PORT"}``: how each table prints this address (an IPv4 one also as IPv4-mapped IPv6)."""
    out = {}
    if isinstance(address, ipaddress.IPv4Address):
        out[TABLES[0]] = f"{int.from_bytes(address.packed, 'little'):08X}:{port:04X}"
        address = ipaddress.IPv6Address(b"\0" * 10 + b"\xff\xff" + address.packed)
    raw = address.packed
    out[TABLES[1]] = "".join(f"{int.from_bytes(raw[i:i + 4], 'little'):08X}" for i in range(0, 16, 4)) + f":{port:04X}"
    return out


def _diag_uid(address: ipaddress.IPv4Address | ipaddress.IPv6Address, port: int,
              other: ipaddress.IPv4Address | ipaddress.IPv6Address, other_port: int) -> int | None:
    """sock_diag's exact lookup of the TCP socket at ``address:port`` connected to ``other:other_port``: its uid, None
    when there is none. ``OSError`` when netlink cannot answer (not Linux, no sock_diag)."""
    family = socket.AF_INET if address.version == 4 else socket.AF_INET6
    if address.version != other.version:
        return None
    body = _REQ.pack(family, socket.IPPROTO_TCP, 0, _ALL_STATES, port.to_bytes(2, "big"),
                     other_port.to_bytes(2, "big"), address.packed.ljust(16, b"\0"), other.packed.ljust(16, b"\0"), 0,
                     _NOCOOKIE, _NOCOOKIE)
    request = _NLMSG.pack(_NLMSG.size + len(body), _SOCK_DIAG_BY_FAMILY, _NLM_F_REQUEST, 1, 0) + body
    with socket.socket(socket.AF_NETLINK, socket.SOCK_DGRAM, _NETLINK_SOCK_DIAG) as nl:
        nl.settimeout(1.0)
        nl.sendto(request, (0, 0))
        reply = nl.recv(65536)
    length, kind, _, _, _ = _NLMSG.unpack_from(reply)
    if kind == _NLMSG_ERROR:
        code = -struct.unpack_from("=i", reply, _NLMSG.size)[0]
        if code in (errno.ENOENT, 0):
            return None
        raise OSError(code, f"sock_diag: {errno.errorcode.get(code, code)}")
    if kind != _SOCK_DIAG_BY_FAMILY or length < _NLMSG.size + _MSG.size:
        raise OSError(errno.EPROTO, f"sock_diag: unexpected reply type {kind}")
    fields = _MSG.unpack_from(reply, _NLMSG.size)
    state, uid = fields[1], fields[14]
    return int(uid) if state == int(ESTABLISHED, 16) else None


def _table_uid(peer: tuple[ipaddress.IPv4Address | ipaddress.IPv6Address, int],
               server: tuple[ipaddress.IPv4Address | ipaddress.IPv6Address, int]) -> int | None:
    """The same from the ``/proc`` tables: one substring search per table (no per-line parsing)."""
    mine, theirs = _fields(*peer), _fields(*server)
    for table in mine:
        try:
            text = Path(table).read_text(encoding="ascii", errors="replace")
        except OSError:
            continue
        needle = f" {mine[table]} {theirs[table]} "
        at = text.find(needle)
        while at >= 0:
            end = text.find("\n", at)
            fields = text[at:end if end >= 0 else len(text)].split()
            if len(fields) >= 7 and fields[2] == ESTABLISHED and fields[6].isdigit():
                return int(fields[6])
            at = text.find(needle, at + 1)
    return None


def peer_uid(peer: Sequence[Any], server: Sequence[Any]) -> int | None:
    """The uid owning the connected socket at ``peer`` (host, port) whose other end is ``server`` (host, port): the
    user who opened a connection this machine's server accepted. None when there is no such socket (the peer
    closed already) or neither sock_diag nor ``/proc`` can tell."""
    mine = (_plain(str(peer[0])), int(peer[1]))
    theirs = (_plain(str(server[0])), int(server[1]))
    try:
        return _diag_uid(*mine, *theirs)
    except OSError:
        return _table_uid(mine, theirs)
